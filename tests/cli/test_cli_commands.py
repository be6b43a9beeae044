"""`navi run` and local `navi infer` invoked as commands on a tiny procedural corpus (64^3 scenes): what
they print, the files they write, and for `navi infer` parity with the same checkpoint flown in-process."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

import pytest
import torch
from typer.testing import CliRunner

from navi.cli import build_app
from navi_env.corpus.folder import build_default_corpus
from navi_learner.envs.factory import make_env
from navi_learner.evaluation.baselines import RandomPolicy
from navi_learner.evaluation.competence import EvalProtocol
from navi_learner.evaluation.evaluate import (
    CheckpointPolicy,
    EvalMetrics,
    beats_supported,
    comparison_table,
    competent_supported,
    contact_line,
    evaluate,
    jsonable,
    mean_outside_line,
)
from navi_learner.evaluation.main_job import POINTGOAL_REFERENCE, REFERENCE, UNSEEN_SEED
from navi_learner.serving.checkpoint import load_checkpoint

pytestmark = pytest.mark.usefixtures("single_thread")

ROOT = Path(__file__).resolve().parents[2]
NAVI = Path(sys.executable).with_name("navi")
"""The console script `make setup` installs beside the interpreter: the command users type."""

runner = CliRunner()

SMALL = EvalProtocol(actors=4, steps=64, episode_steps=32, seed=12345)
"""`navi run`'s unseen evaluation, shrunk: the command has no option for it, and the CPU protocol (48
actors x 500 steps, three policies) takes minutes on 2 cores."""

CPU_STEPS = 256
"""`navi run --cpu-steps`: one PPO update of the CPU path's 4 actors x 64-step rollouts."""

INFER_ACTORS, INFER_STEPS, INFER_SEED = 2, 32, 3


@pytest.fixture(scope="module")
def corpora(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A one-scene training corpus (procedural seed 0) and a one-scene unseen corpus (seed 1000), 64^3."""
    root = tmp_path_factory.mktemp("corpora")
    build_default_corpus(root / "train", resolution=64, count=1, seed=0)
    build_default_corpus(root / "unseen", resolution=64, count=1, seed=UNSEEN_SEED)
    return root / "train", root / "unseen"


def checkout_env() -> dict[str, str]:
    """This checkout's packages first on the path and one intra-op thread, as in the in-process runs."""
    paths = [ROOT, *(ROOT / p for p in ("services/compiler", "services/env", "services/learner"))]
    paths += [ROOT / "services/auditor", ROOT / "shared/contracts", ROOT / "shared/mesh"]
    path = os.pathsep.join([*map(str, paths), os.environ.get("PYTHONPATH", "")])
    return {**os.environ, "PYTHONPATH": path, "OMP_NUM_THREADS": "1"}


def navi(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """`navi ARGS` as a user types it, in cwd; a hang ends the test at the time-out."""
    assert NAVI.is_file(), f"{NAVI} is missing: `make setup` installs the navi console script"
    cmd = [str(NAVI), *args]
    return subprocess.run(cmd, cwd=cwd, env=checkout_env(), capture_output=True, text=True, timeout=300)


def without_timing(row: dict[str, Any]) -> dict[str, Any]:
    """An evaluation row less its speed (steps per second), the one field that differs run to run."""
    return {k: v for k, v in row.items() if k != "sps"}


def in_process(metrics: EvalMetrics) -> dict[str, Any]:
    """An in-process evaluation as the commands print it (NaN as null), less its speed."""
    row = jsonable(asdict(metrics))
    assert isinstance(row, dict)
    return without_timing(row)


def test_navi_run_fine_tunes_promotes_and_reports_the_unseen_comparison(
    corpora: tuple[Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`navi run --device cpu` fine-tunes the reference, promotes it, and its evaluation files describe the
    promoted checkpoint flown against random and reactive on the unseen corpus."""
    train, unseen = corpora
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(EvalProtocol, "for_device", classmethod(lambda cls, device, task="explore": SMALL))
    args = ["run", "--corpus", str(train), "--unseen", str(unseen), "--device", "cpu", "--no-real-maps"]
    result = runner.invoke(build_app(), [*args, "--cpu-steps", str(CPU_STEPS)])
    assert result.exit_code == 0, result.output[-3000:]
    reference_step = load_checkpoint(REFERENCE).meta.step_id
    lines = result.stdout.splitlines()
    assert lines[0].startswith(
        f"[navi run] path: CPU. Fine-tuning the explore reference checkpoint {REFERENCE}"
    )
    assert f"for {CPU_STEPS:,} steps on {train}" in lines[0]
    assert any(x.startswith(f"[navi run] trained to step {reference_step + CPU_STEPS:,} in ") for x in lines)
    assert any(x.endswith("promoted: v001") for x in lines), result.stdout
    report = Path(lines[-1].removeprefix("report: "))
    assert lines[-1].startswith("report: artifacts/runs/") and report.name == "evaluation.md"
    assert f"[navi run] evaluation: {report}" in lines

    # the promoted checkpoint: a plain torch file, the reference's child, CPU_STEPS further on
    latest = tmp_path / "artifacts" / "models" / "latest.pt"
    payload = torch.load(latest, map_location="cpu", weights_only=True)
    assert isinstance(payload, dict) and payload["meta"]["step_id"] == reference_step + CPU_STEPS
    meta = load_checkpoint(latest).meta
    assert meta.parent_checkpoint == str(REFERENCE) and meta.run_id == report.parents[1].name
    registry = json.loads((tmp_path / "artifacts" / "models" / "registry.json").read_text())
    assert [v["version"] for v in registry["versions"]] == ["v001"]

    # evaluation.json: the documented keys, the protocol, one row per pilot, verdicts that follow the rows
    data = json.loads(report.with_name("evaluation.json").read_text())
    assert set(data) == {"path", "protocol", "results", "beats", "competent"}
    assert data["path"] == "cpu" and data["protocol"] == asdict(SMALL)
    trained, rand, reactive = (EvalMetrics(**r) for r in data["results"])
    assert [trained.policy, rand.policy, reactive.policy] == [
        f"trained ({meta.run_id})",
        "random",
        "reactive",
    ]
    for row in (trained, rand, reactive):
        assert (row.steps, row.actors, row.task) == (SMALL.steps, SMALL.actors, "explore")
        assert row.episodes >= SMALL.actors * SMALL.steps // SMALL.episode_steps
        assert row.per_actor["steps"] == [float(SMALL.steps)] * SMALL.actors
        assert row.collisions_per_1k >= 0 and 0 < row.coverage_per_1k <= 1000
        for name in ("collisions_per_1k", "coverage_per_1k", "distance_per_1k"):
            low, high = row.ci[name]
            assert low <= getattr(row, name) <= high, (row.policy, name, row.ci[name])
    assert data["beats"] == {
        "random": beats_supported(trained, rand),
        "reactive": beats_supported(trained, reactive),
    }
    assert data["competent"] == competent_supported(trained, reactive)
    text = report.read_text()
    assert text.startswith("# navi run: evaluation on unseen scenes (cpu path, task explore)")
    assert f"| trained ({meta.run_id}) |" in text and "| random |" in text and "| reactive |" in text
    assert ("): yes." if data["competent"] else "): no.") in text

    # the row labelled trained is the promoted checkpoint, flown again in-process on the same spawns
    env = make_env(unseen, SMALL.actors, "cpu", SMALL.seed, episode_steps=SMALL.episode_steps)
    flown = CheckpointPolicy(latest, torch.device("cpu"), seed=SMALL.seed)  # sampled, as explore flies
    again = evaluate(env, flown, SMALL.steps, SMALL.seed)
    assert in_process(again) | {"policy": trained.policy} == without_timing(data["results"][0])


def test_navi_run_point_goal_fine_tunes_its_reference_and_compares_with_the_seekers(
    corpora: tuple[Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`navi run --task pointgoal --device cpu` fine-tunes the point-goal reference and scores the
    promoted checkpoint against random, greedy and oracle with success and SPL."""
    train, unseen = corpora
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(EvalProtocol, "for_device", classmethod(lambda cls, device, task="explore": SMALL))
    args = ["run", "--corpus", str(train), "--unseen", str(unseen), "--device", "cpu", "--task", "pointgoal"]
    result = runner.invoke(build_app(), [*args, "--cpu-steps", str(CPU_STEPS), "--no-real-maps"])
    assert result.exit_code == 0, result.output[-3000:]
    lines = result.stdout.splitlines()
    assert lines[0].startswith(
        f"[navi run] path: CPU. Fine-tuning the pointgoal reference checkpoint {POINTGOAL_REFERENCE}"
    )
    meta = load_checkpoint(tmp_path / "artifacts" / "models" / "latest.pt").meta
    reference_step = load_checkpoint(POINTGOAL_REFERENCE).meta.step_id
    assert meta.parent_checkpoint == str(POINTGOAL_REFERENCE) and meta.step_id == reference_step + CPU_STEPS
    assert meta.config["task"] == "pointgoal"
    report = Path(lines[-1].removeprefix("report: "))
    data = json.loads(report.with_name("evaluation.json").read_text())
    rows = [EvalMetrics(**r) for r in data["results"]]
    assert [r.policy for r in rows] == [f"trained ({meta.run_id})", "random", "greedy", "oracle"]
    assert all(r.task == "pointgoal" and r.episodes > 0 for r in rows)
    assert all(0 <= r.success_rate <= 1 and 0 <= r.spl <= r.success_rate for r in rows)
    trained = rows[0]
    assert data["beats"] == {
        r.policy: trained.success_rate > r.success_rate
        and trained.collisions_per_episode <= r.collisions_per_episode
        for r in rows[1:]
    }
    # 32-step episodes are short for reaching a goal; the soft SPL still shows who closes in on it
    assert rows[3].soft_spl > rows[2].soft_spl > rows[1].soft_spl, [(r.policy, r.soft_spl) for r in rows]
    assert "| policy | success_rate | spl | soft_spl |" in report.read_text()


def test_navi_run_refuses_an_unknown_task_before_building_anything(tmp_path: Path) -> None:
    """A bad --task is a usage error naming the choices (exit 2), and nothing is built or written."""
    done = navi("run", "--task", "racing", "--device", "cpu", cwd=tmp_path)
    assert done.returncode == 2 and done.stdout == "" and "Traceback" not in done.stderr
    assert done.stderr.startswith("Usage: navi run [OPTIONS]"), done.stderr
    assert "--task must be one of explore, pointgoal, got 'racing'" in done.stderr, done.stderr
    assert list(tmp_path.iterdir()) == []


def test_navi_infer_prints_what_the_checkpoint_does_in_process(
    corpora: tuple[Path, Path], tmp_path: Path
) -> None:
    """`navi infer --deterministic --json` (the console script) reports exactly the metrics, per-actor sums
    included, of the same checkpoint flown in-process from the same seed (a random pilot's differ); without
    --json the same row as a markdown table, and under it the share of its action means outside [-1, 1]."""
    train, _ = corpora
    args = ["infer", "--checkpoint", str(REFERENCE), "--corpus", str(train), "--device", "cpu"]
    sizes = ["--actors", str(INFER_ACTORS), "--total-steps", str(INFER_STEPS), "--seed", str(INFER_SEED)]
    done = navi(*args, *sizes, "--deterministic", "--json", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    (row,) = json.loads(done.stdout)["results"]
    assert row["policy"] == str(REFERENCE) and (row["steps"], row["actors"]) == (INFER_STEPS, INFER_ACTORS)
    env = make_env(train, INFER_ACTORS, "cpu", INFER_SEED)
    want = evaluate(env, CheckpointPolicy(REFERENCE, torch.device("cpu"), 0.0), INFER_STEPS, INFER_SEED)
    assert without_timing(row) == in_process(want)
    rand = evaluate(env, RandomPolicy(INFER_SEED), INFER_STEPS, INFER_SEED)
    assert (rand.distance_per_1k, rand.mean_clearance) != (want.distance_per_1k, want.mean_clearance)
    table = runner.invoke(build_app(), [*args, *sizes, "--deterministic"])  # without --json: a table
    assert table.exit_code == 0, table.output[-3000:]
    under = [line for line in (mean_outside_line(want), contact_line(want, want.policy)) if line]
    assert table.stdout.strip() == "\n\n".join([comparison_table([want]), *under])


def test_navi_infer_samples_actions_from_its_seed(corpora: tuple[Path, Path], tmp_path: Path) -> None:
    """Without --deterministic `navi infer` samples actions from torch seeded with --seed: the same seed
    reproduces the in-process sampled flight, and differs from the mean actions."""
    train, _ = corpora
    args = ["infer", "--checkpoint", str(REFERENCE), "--corpus", str(train), "--device", "cpu", "--json"]
    sizes = ["--actors", str(INFER_ACTORS), "--total-steps", str(INFER_STEPS), "--seed", str(INFER_SEED)]
    rows = []
    for _ in range(2):
        result = runner.invoke(build_app(), [*args, *sizes])
        assert result.exit_code == 0, result.output[-3000:]
        rows.append(without_timing(json.loads(result.stdout)["results"][0]))
    assert rows[0] == rows[1]
    env = make_env(train, INFER_ACTORS, "cpu", INFER_SEED)
    sampled = CheckpointPolicy(REFERENCE, torch.device("cpu"), 1.0, INFER_SEED)
    assert rows[0] == in_process(evaluate(env, sampled, INFER_STEPS, INFER_SEED))
    mean = evaluate(env, CheckpointPolicy(REFERENCE, torch.device("cpu"), 0.0), INFER_STEPS, INFER_SEED)
    assert rows[0]["distance_per_1k"] != mean.distance_per_1k


def test_navi_evaluate_flies_explore_sampled_and_any_spread_asked(corpora: tuple[Path, Path]) -> None:
    """`navi evaluate` flies an explore checkpoint as Navi flies explore everywhere (sampled with its std,
    the draws seeded by --seed): the same row as that flight in-process; `--action-noise 0` is its mean
    action, `--action-noise 0.5` a third flight; `--episode-steps` sets the episodes' length."""
    train, _ = corpora
    episode = 16
    args = ["evaluate", str(REFERENCE), "--corpus", str(train), "--device", "cpu", "--json"]
    sizes = ["--actors", str(INFER_ACTORS), "--steps", str(INFER_STEPS), "--seed", str(INFER_SEED)]
    rows = {}
    for noise in (None, 0.0, 0.5):
        extra = [] if noise is None else ["--action-noise", str(noise)]
        done = runner.invoke(build_app(), [*args, *sizes, "--episode-steps", str(episode), *extra])
        assert done.exit_code == 0, done.output[-3000:]
        rows[noise] = without_timing(json.loads(done.stdout)["results"][0])
    env = make_env(train, INFER_ACTORS, "cpu", INFER_SEED, episode_steps=episode)
    for noise in (1.0, 0.0):
        flown = CheckpointPolicy(REFERENCE, torch.device("cpu"), noise, INFER_SEED)
        want = in_process(evaluate(env, flown, INFER_STEPS, INFER_SEED))
        assert rows[None if noise == 1.0 else 0.0] == want
    assert rows[None]["episodes"] == INFER_ACTORS * INFER_STEPS // episode
    assert len({r["distance_per_1k"] for r in rows.values()}) == 3  # three spreads, three flights


def test_navi_infer_bad_input_is_an_error_and_exit_2(corpora: tuple[Path, Path], tmp_path: Path) -> None:
    """A missing checkpoint, a file that is no checkpoint, and a missing corpus each end `navi infer` with an
    `error:` naming the problem and exit code 2, printing no metrics and no traceback."""
    train, _ = corpora
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    missing = tmp_path / "missing.pt"
    cases = {
        f"{missing} is neither random, reactive, greedy, oracle, a checkpoint file nor a registry version":
            (missing, train),
        f"{junk} is not a loadable checkpoint: ": (junk, train),
        f"corpus folder {tmp_path / 'nowhere'} does not exist": (REFERENCE, tmp_path / "nowhere"),
    }  # fmt: skip
    for message, (checkpoint, corpus) in cases.items():
        result = runner.invoke(
            build_app(),
            ["infer", "--checkpoint", str(checkpoint), "--corpus", str(corpus), "--device", "cpu", "--json"],
        )
        assert result.exit_code == 2, (message, result.output[-3000:])
        assert result.stdout == "" and result.stderr.startswith(f"error: {message}"), result.output[-3000:]
        assert "Traceback" not in result.stderr and result.stderr.count("\n") == 1, result.stderr  # one line
    done = navi(
        "infer", "--checkpoint", str(missing), "--corpus", str(train), "--device", "cpu", cwd=tmp_path
    )
    assert (done.returncode, done.stdout) == (2, ""), done.stderr[-3000:]
    assert done.stderr == f"error: {next(iter(cases))}\n"
