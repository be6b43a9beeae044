"""The training loop on the toy env: PPO beats random after 24,576 CPU steps; resume continues counters and
optimizer state; the run folder holds logs, metrics, manifest, checkpoints and a report."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
import torch

from navi_learner.config import EngineConfig, PPOConfig, TrainConfig
from navi_learner.engine.policy import CognitiveMambaPolicy
from navi_learner.envs.protocol import StepOut
from navi_learner.envs.toy import ToyEnv
from navi_learner.evaluation.baselines import RandomPolicy, reactive_for_env
from navi_learner.evaluation.evaluate import CheckpointPolicy, evaluate
from navi_learner.ppo import timing as timing_module
from navi_learner.ppo.learner import InitError, init_engine, init_weights
from navi_learner.ppo.timing import StageTimers
from navi_learner.ppo.train import train
from navi_learner.serving.checkpoint import load_checkpoint
from navi_learner.serving.references import REFERENCES
from navi_learner.serving.registry import ModelRegistry

ENGINE = EngineConfig.tiny()

pytestmark = pytest.mark.usefixtures("single_thread")


def config(total: int, **kw: Any) -> TrainConfig:
    ppo = PPOConfig(lr=2e-3, num_minibatches=2, bptt_chunk=16, ppo_epochs=2, ent_coef=0.0)
    return TrainConfig(
        n_actors=32,
        rollout_length=32,
        total_steps=total,
        engine=ENGINE,
        ppo=ppo,
        checkpoint_every=10**9,
        log_every=4,
        **kw,
    )


@pytest.mark.parametrize("action_input", [False, True])
def test_ppo_beats_random_on_the_toy_env(tmp_path: Path, action_input: bool) -> None:
    """24,576 steps of PPO on the toy env earn clearly more reward per step than random actions, with
    or without the previous action as an input of the temporal core."""
    cfg = replace(config(24_576), engine=replace(ENGINE, action_input=action_input))
    result = train(ToyEnv(32, seed=1), cfg, run_dir=tmp_path / "run", progress=False)
    assert (load_checkpoint(result.final_checkpoint).meta.config["engine"]["action_input"]) is action_input
    trained = evaluate(
        ToyEnv(16, seed=5), CheckpointPolicy(result.final_checkpoint, torch.device("cpu"), 0.0), 200, seed=5
    )
    rand = evaluate(ToyEnv(16, seed=5), RandomPolicy(5), 200, seed=5)
    assert abs(rand.reward_per_step) < 0.1
    assert trained.reward_per_step > rand.reward_per_step + 0.25, (trained, rand)
    assert result.skipped_updates == 0


def test_run_folder_and_resume_continue_counters_and_optimizer(tmp_path: Path) -> None:
    per_update = 32 * 32
    registry = ModelRegistry(tmp_path / "models")
    logged: list[tuple[str, dict[str, float]]] = []
    first = train(
        ToyEnv(32, seed=1),
        config(2 * per_update),
        run_dir=tmp_path / "r1",
        registry=registry,
        on_log=lambda rid, row: logged.append((rid, row)),
        run_id="r1",
        progress=False,
    )
    assert first.step_id == 2 * per_update
    assert first.promoted == "v001" and registry.latest_path.is_file()
    for sub in ("logs", "metrics", "manifests", "checkpoints", "reports"):
        assert (tmp_path / "r1" / sub).is_dir()
    rows = [
        json.loads(line) for line in (tmp_path / "r1" / "metrics" / "metrics.jsonl").read_text().splitlines()
    ]
    assert rows and all(r["run_id"] == "r1" for r in rows)
    assert {"sps", "ms_env", "ms_forward", "ms_learn", "policy_loss", "approx_kl", "entropy"} <= rows[
        -1
    ].keys()
    assert logged and logged[-1][0] == "r1"
    assert json.loads((tmp_path / "r1" / "manifests" / "run.json").read_text())["run_id"] == "r1"
    assert "r1" in (tmp_path / "r1" / "logs" / "train.log").read_text()
    report = (tmp_path / "r1" / "reports" / "report.md").read_text()
    assert report.startswith("# Training run r1")
    png = tmp_path / "r1" / "reports" / "report.png"  # matplotlib comes with `make setup` (learner[plots])
    assert "![reward and SPS](report.png)" in report and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    events = list((tmp_path / "r1" / "logs" / "tensorboard").glob("events.out.tfevents.*"))
    assert events and events[0].stat().st_size > 0  # TensorBoard scalars (learner[tensorboard])
    c1 = load_checkpoint(first.final_checkpoint)
    assert c1.meta.run_id == "r1" and c1.meta.step_id == 2 * per_update
    assert c1.optimizer is not None
    steps1 = {k: float(v["step"]) for k, v in c1.optimizer["state"].items()}
    assert set(steps1.values()) == {8.0}  # 2 updates x 2 epochs x 2 minibatches

    second = train(
        ToyEnv(32, seed=2),
        config(5 * per_update),
        run_dir=tmp_path / "r2",
        resume_from=first.final_checkpoint,
        run_id="r2",
        progress=False,
    )
    assert second.step_id == 5 * per_update  # continues from 2 updates to the 5-update budget
    c2 = load_checkpoint(second.final_checkpoint)
    assert c2.meta.parent_checkpoint == str(first.final_checkpoint)
    assert c2.meta.episode_count >= c1.meta.episode_count
    assert c2.meta.wall_time_hours > c1.meta.wall_time_hours
    assert c2.optimizer is not None
    steps2 = {k: float(v["step"]) for k, v in c2.optimizer["state"].items()}
    assert set(steps2.values()) == {8.0 + 3 * 4.0}  # the Adam step count carried on


def test_baselines_on_the_toy_env() -> None:
    """The reactive baseline steers toward the open direction, so it clearly beats random."""
    reactive = evaluate(ToyEnv(16, seed=3), reactive_for_env(ToyEnv(16)), 200, seed=3)
    rand = evaluate(ToyEnv(16, seed=3), RandomPolicy(3), 200, seed=3)
    assert reactive.reward_per_step > rand.reward_per_step + 0.3
    assert reactive.coverage_per_1k > 0 and reactive.distance_per_1k > rand.distance_per_1k
    assert rand.collisions_per_1k >= 0 and rand.episodes > 0


class InterruptingEnv(ToyEnv):
    """A toy env whose step raises KeyboardInterrupt (Ctrl+C) after `after` steps."""

    def __init__(self, after: int) -> None:
        super().__init__(32, seed=1)
        self.after = after

    def step(self, actions: torch.Tensor) -> StepOut:
        self.after -= 1
        if self.after < 0:
            raise KeyboardInterrupt
        return super().step(actions)


def test_ctrl_c_saves_a_checkpoint_first(tmp_path: Path) -> None:
    result = train(InterruptingEnv(after=32 * 2 + 5), config(10**9), run_dir=tmp_path / "run", progress=False)
    assert result.interrupted
    ckpt = load_checkpoint(result.final_checkpoint)
    assert ckpt.meta.step_id == 2 * 32 * 32  # the two completed updates
    assert ckpt.optimizer is not None and ckpt.optimizer["state"]


def test_adaptive_rate_is_a_device_tensor_that_moves_and_resumes(tmp_path: Path) -> None:
    """With a KL target the run's rate lives in the optimizer as a tensor, moves away from --lr, and a
    resumed run starts from the checkpoint's rate."""
    per_update = 32 * 32
    cfg = config(2 * per_update)
    cfg.ppo.target_kl, cfg.ppo.lr = 0.01, 5e-4
    first = train(ToyEnv(32, seed=1), cfg, run_dir=tmp_path / "r1", progress=False)
    c1 = load_checkpoint(first.final_checkpoint)
    assert c1.optimizer is not None
    rate = c1.optimizer["param_groups"][0]["lr"]
    assert isinstance(rate, torch.Tensor) and float(rate) != pytest.approx(cfg.ppo.lr)
    assert cfg.ppo.lr_min * 0.999 <= float(rate) <= cfg.ppo.lr_max * 1.001
    rows = [json.loads(x) for x in (tmp_path / "r1" / "metrics" / "metrics.jsonl").read_text().splitlines()]
    assert all("lr" in r for r in rows)
    cfg2 = config(3 * per_update)
    cfg2.ppo.target_kl = 0.01
    cfg2.ppo.ppo_epochs = 0  # no step: the resumed rate is what the checkpoint held
    second = train(ToyEnv(32, seed=2), cfg2, run_dir=tmp_path / "r2", resume_from=first.final_checkpoint,
                   progress=False)  # fmt: skip
    c2 = load_checkpoint(second.final_checkpoint)
    assert c2.optimizer is not None
    assert float(c2.optimizer["param_groups"][0]["lr"]) == pytest.approx(float(rate))


class Clock:
    """A host clock that moves only when told: `perf_counter` for the timing module."""

    def __init__(self) -> None:
        self.now = 100.0

    def perf_counter(self) -> float:
        return self.now


def test_stage_timers_without_sync_sum_the_host_time_per_stage_and_clear_on_read(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Without sync each stage adds the host time between its boundaries; a read gives ms per env step
    and starts again from zero."""
    clock = Clock()
    monkeypatch.setattr(timing_module, "time", clock)
    timers = StageTimers(sync=False)
    for seconds in (0.010, 0.020, 0.030):
        with timers("env"):
            clock.now += seconds
        clock.now += 1.0  # between stages: counted nowhere
    with timers("forward"):
        clock.now += 0.006
    ms = timers.read(steps=3)  # ms per step
    assert ms == pytest.approx({"ms_env": 20.0, "ms_forward": 2.0, "ms_learn": 0.0, "ms_sync": 0.0})
    assert timers.read(steps=1) == {"ms_env": 0.0, "ms_forward": 0.0, "ms_learn": 0.0, "ms_sync": 0.0}


def test_a_resumed_run_trains_at_its_own_learning_rate(tmp_path: Path) -> None:
    """The checkpoint's optimizer state brings its moments, not its constant rate: resumed at lr 0 (the checkpoint
    trained at 2e-3), no weight moves, while the Adam step count carries on."""
    per_update = 32 * 32
    first = train(ToyEnv(32, seed=1), config(per_update), run_dir=tmp_path / "r1", progress=False)
    frozen = replace(config(3 * per_update), ppo=replace(config(1).ppo, lr=0.0))
    second = train(
        ToyEnv(32, seed=2),
        frozen,
        run_dir=tmp_path / "r2",
        resume_from=first.final_checkpoint,
        progress=False,
    )
    before, after = load_checkpoint(first.final_checkpoint), load_checkpoint(second.final_checkpoint)
    moved = [
        k for k, v in before.model.items() if v.is_floating_point() and not torch.equal(v, after.model[k])
    ]
    learned = [k for k in moved if not k.startswith("rnd.err_")]  # running error statistics, not weights
    assert learned == []
    assert after.optimizer is not None and before.optimizer is not None
    assert {float(v["step"]) for v in after.optimizer["state"].values()} == {4.0 + 2 * 4.0}


def test_a_run_started_from_a_checkpoints_weights_takes_nothing_else(tmp_path: Path) -> None:
    """init_from starts a fresh run from a checkpoint's weights: at lr 0 its final weights are the
    checkpoint's (a run without it ends elsewhere), while its counters and optimizer are its own."""
    per_update = 32 * 32
    first = train(ToyEnv(32, seed=1), config(2 * per_update), run_dir=tmp_path / "r1", progress=False)
    frozen = replace(config(per_update), ppo=replace(config(1).ppo, lr=0.0))
    started = train(
        ToyEnv(32, seed=2),
        replace(frozen, init_from=str(first.final_checkpoint)),
        run_dir=tmp_path / "r2",
        progress=False,
    )
    fresh = train(ToyEnv(32, seed=2), frozen, run_dir=tmp_path / "r3", progress=False)
    source = load_checkpoint(first.final_checkpoint)

    def moved(path: Path) -> list[str]:
        after = load_checkpoint(path).model
        return [
            k
            for k, v in source.model.items()
            if v.is_floating_point() and not torch.equal(v, after[k]) and not k.startswith("rnd.err_")
        ]

    assert moved(started.final_checkpoint) == [] and moved(fresh.final_checkpoint) != []
    after = load_checkpoint(started.final_checkpoint)
    assert after.meta.step_id == per_update and after.meta.parent_checkpoint in (None, "")
    assert after.optimizer is not None
    assert {float(v["step"]) for v in after.optimizer["state"].values()} == {4.0}  # its own 1 x 2 x 2 steps
    manifest = json.loads((tmp_path / "r2" / "manifests" / "run.json").read_text())
    assert manifest["init_from"] == str(first.final_checkpoint) and manifest["resume_from"] is None


def test_init_from_names_a_fitting_checkpoint_or_the_run_stops_with_why() -> None:
    """A task's name loads its shipped reference, bit for bit, into an engine of the shape it stored
    (init_engine), whatever today's default; a missing file, another temporal core or another engine
    shape is an InitError naming the checkpoint and, for a shape, the fields that differ."""
    obs_shape = (3, 256, 48)
    stored = EngineConfig.from_dict(load_checkpoint(REFERENCES["explore"]).meta.config["engine"])
    engine = init_engine("explore", "mamba2", {"attention": "sdpa"})
    assert engine == replace(stored, attention="sdpa")  # the run's own fields on top of the stored shape
    policy = CognitiveMambaPolicy(obs_shape, engine)
    assert init_weights(policy, "explore", TrainConfig(engine=engine)) == REFERENCES["explore"]
    reference = load_checkpoint(REFERENCES["explore"]).model
    assert all(torch.equal(v, reference[k]) for k, v in policy.state_dict().items())
    with pytest.raises(InitError, match="does not exist"):
        init_engine("absent.pt", "mamba2", {})
    other = replace(stored, encoder_layers=stored.encoder_layers + 1)
    with pytest.raises(
        InitError, match=f"encoder_layers={stored.encoder_layers} \\(the run's {other.encoder_layers}\\)"
    ):
        init_weights(CognitiveMambaPolicy(obs_shape, other), "explore", TrainConfig(engine=other))
    tiny = CognitiveMambaPolicy(obs_shape, ENGINE)
    for spec, cfg, why in (
        ("absent.pt", TrainConfig(engine=ENGINE), "does not exist"),
        (
            "explore",
            TrainConfig(engine=replace(ENGINE, temporal_core="gru")),
            "temporal core mamba2, not gru",
        ),
        ("explore", TrainConfig(engine=ENGINE), "do not fit this run's engine"),
    ):
        with pytest.raises(InitError, match=why):
            init_weights(tiny, spec, cfg)
