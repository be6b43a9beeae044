"""Synchronous data-parallel PPO (DD-PPO) on the CPU with gloo: replicas stay bit-identical and rank 0
alone writes; one update on 2 ranks is one single-process update on the union of their batches; the
bucketed gradient all-reduce gives one flat all-reduce's averages bit for bit; the RND normaliser pooled
one step late is one process's normaliser on the union one step late; a 2-rank checkpoint resumes on 1
rank and a 1-rank checkpoint on 2; a SIGKILLed rank ends the run with an error naming the timeout, a
SIGTERMed rank stops both with one final checkpoint; `navi bench train --nproc 2` reports per-rank, total
SPS, the scaling efficiency and every rank's timeline of a step."""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
import torch
import torch.distributed as tdist
import typer

from navi_learner.config import EngineConfig, PPOConfig, TrainConfig
from navi_learner.envs.toy import ToyEnv
from navi_learner.ppo import timing as timing_module
from navi_learner.ppo.dist import BUCKET_ENV, Dist, bucket_mb_from_env, bucket_plan, setup, strip_option
from navi_learner.ppo.timing import StageTimers
from navi_learner.ppo.train import train, update
from navi_learner.serving.checkpoint import load_checkpoint

ROOT = Path(__file__).resolve().parents[2]
ACTORS, ROLLOUT = 4, 32  # per rank, in the CLI runs
PER_RANK_UPDATE = ACTORS * ROLLOUT
TRAIN_ARGS = ["--env", "toy", "--device", "cpu", "--actors", str(ACTORS), "--rollout-length", str(ROLLOUT),
              "--temporal-core", "gru"]  # fmt: skip


def navi_env(**extra: str) -> dict[str, str]:
    """This checkout's packages first on the path (the ranks are fresh interpreters)."""
    paths = [ROOT, *(ROOT / p for p in ("services/compiler", "services/env", "services/learner"))]
    paths += [ROOT / "services/auditor", ROOT / "shared/contracts", ROOT / "shared/mesh"]
    path = os.pathsep.join([*map(str, paths), os.environ.get("PYTHONPATH", "")])
    return {**os.environ, "PYTHONPATH": path, "OMP_NUM_THREADS": "1", **extra}


TORCHRUN = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2"]


def torchrun(*args: str) -> list[str]:
    return [*TORCHRUN, "-m", "navi", *args]


def run_navi(args: list[str], cwd: Path, timeout: float) -> subprocess.CompletedProcess[str]:
    """`python -m navi ARGS` in cwd with this checkout's packages, output captured."""
    cmd = [sys.executable, "-m", "navi", *args]
    return subprocess.run(cmd, cwd=cwd, env=navi_env(), capture_output=True, text=True, timeout=timeout)


def run_folder(cwd: Path) -> Path:
    (run,) = (cwd / "artifacts" / "runs").iterdir()
    return run


def rank_pids(root: int) -> dict[int, int]:
    """RANK -> pid of the torchrun workers below process `root`."""
    found: dict[int, int] = {}
    todo = [root]
    while todo:
        pid = todo.pop()
        try:
            children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
            env = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
        except OSError:
            continue
        todo += [int(c) for c in children]
        for item in env:
            if item.startswith(b"RANK=") and pid != root:
                found[int(item[5:])] = pid
    return found


def start_long_run(
    cwd: Path, *extra: str, timeout_s: str = "20", wrapper: bool = False
) -> subprocess.Popen[str]:
    """A 2-rank run with a budget it never reaches, once both ranks train (rank 0 logged a row)."""
    args = ["train", *TRAIN_ARGS, "--total-steps", "100000000", "--checkpoint-every", "1000000000", *extra]
    cmd = [sys.executable, "-m", "navi", *args, "--nproc", "2"] if wrapper else torchrun(*args)
    env = navi_env(NAVI_DIST_TIMEOUT_S=timeout_s)
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not list(cwd.glob("artifacts/runs/*/metrics/metrics.jsonl")):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.2)
    return proc


@pytest.fixture(scope="module")
def two_rank_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """4 updates of 2 ranks x 4 actors x 32 steps, a periodic checkpoint at 512, debug hashes."""
    cwd = tmp_path_factory.mktemp("two")
    args = torchrun("train", *TRAIN_ARGS, "--total-steps", "1024", "--checkpoint-every", "512", "--fresh")
    env = navi_env(NAVI_DIST_DEBUG_DIR=str(cwd / "debug"))
    out = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr[-3000:]
    (cwd / "stdout.txt").write_text(out.stdout)
    return cwd


def test_two_ranks_hold_bit_identical_replicas_and_rank_0_alone_writes(two_rank_run: Path) -> None:
    cwd = two_rank_run
    ranks = [json.loads((cwd / "debug" / f"rank{r}.json").read_text()) for r in (0, 1)]
    assert ranks[0]["step_id"] == ranks[1]["step_id"] == 1024 == 4 * 2 * PER_RANK_UPDATE
    assert ranks[0]["model"] == ranks[1]["model"] and ranks[0]["optimizer"] == ranks[1]["optimizer"]
    (line,) = [x for x in (cwd / "stdout.txt").read_text().splitlines() if x.startswith("{")]
    summary = json.loads(line)  # rank 0 alone prints
    assert summary["steps"] == 1024 and summary["promoted"] == "v001" and not summary["interrupted"]
    run = run_folder(cwd)  # one run folder: rank 1 wrote nothing
    ckpts = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert ckpts == ["ckpt_step_0000000512.pt", "ckpt_step_0000001024.pt"]
    final = load_checkpoint(run / "checkpoints" / ckpts[-1])
    assert final.meta.step_id == 1024 and final.meta.run_id == run.name
    digest = hashlib.sha256()
    for name, t in sorted(final.model.items()):
        digest.update(name.encode())
        digest.update(t.contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    assert digest.hexdigest() == ranks[0]["model"]  # the checkpoint is the replicas' common state
    assert final.optimizer is not None
    assert {float(s["step"]) for s in final.optimizer["state"].values()} == {
        16.0
    }  # 4 updates x 4 minibatches
    manifest = json.loads((run / "manifests" / "run.json").read_text())
    assert manifest["world_size"] == 2 and manifest["actors_per_rank"] == ACTORS
    assert [(r["rank"], r["seed"]) for r in manifest["ranks"]] == [(0, 0), (1, 1)]
    rows = [json.loads(line) for line in (run / "metrics" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [256.0, 512.0, 768.0, 1024.0]  # both ranks' steps per update
    assert rows[-1]["episode_count"] == final.meta.episode_count > 0
    registry = json.loads((cwd / "artifacts" / "models" / "registry.json").read_text())
    assert [v["version"] for v in registry["versions"]] == ["v001"]  # promoted once, by rank 0
    written = {p.relative_to(cwd).parts[:2] for p in cwd.rglob("*") if p.is_file()}
    assert written == {("artifacts", "runs"), ("artifacts", "models"), ("debug", "rank0.json"),
                       ("debug", "rank1.json"), ("stdout.txt",)}  # fmt: skip


@pytest.fixture(scope="module")
def one_rank_resume(two_rank_run: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The 2-rank checkpoint resumed by one process for 2 more updates; returns its final checkpoint."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        parent = run_folder(two_rank_run) / "checkpoints" / "ckpt_step_0000001024.pt"
        cfg = TrainConfig(
            n_actors=ACTORS,
            rollout_length=ROLLOUT,
            total_steps=1024 + 2 * PER_RANK_UPDATE,
            checkpoint_every=10**9,
            engine=EngineConfig(temporal_core="gru"),
            ppo=PPOConfig(lr=5e-4, ppo_epochs=1),
        )
        run_dir = tmp_path_factory.mktemp("one") / "run"
        result = train(ToyEnv(ACTORS, seed=3), cfg, run_dir=run_dir, resume_from=parent, progress=False)
    finally:
        torch.set_num_threads(before)
    return result.final_checkpoint


def test_a_two_rank_checkpoint_resumes_on_one_rank(one_rank_resume: Path, two_rank_run: Path) -> None:
    ckpt = load_checkpoint(one_rank_resume)
    parent = run_folder(two_rank_run) / "checkpoints" / "ckpt_step_0000001024.pt"
    assert ckpt.meta.step_id == 1024 + 2 * PER_RANK_UPDATE and ckpt.meta.parent_checkpoint == str(parent)
    assert ckpt.meta.episode_count > load_checkpoint(parent).meta.episode_count
    assert ckpt.optimizer is not None
    assert {float(s["step"]) for s in ckpt.optimizer["state"].values()} == {16.0 + 2 * 4.0}  # Adam carried on


def test_sigterm_to_one_rank_stops_both_with_one_checkpoint_and_resumes_on_two(
    one_rank_resume: Path, tmp_path: Path
) -> None:
    """`navi train --nproc 2` (torchrun underneath) resuming a 1-rank checkpoint; SIGTERM to rank 1."""
    proc = start_long_run(tmp_path, "--checkpoint", str(one_rank_resume), wrapper=True)
    pids = rank_pids(proc.pid)
    assert sorted(pids) == [0, 1]
    os.kill(pids[1], signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode != 0  # torchrun reports rank 0's exit code 130 (interrupted) as a failure
    assert "exitcode  : 130" in err, err[-3000:]
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["interrupted"] and summary["promoted"] is None
    (ckpt_path,) = (run_folder(tmp_path) / "checkpoints").iterdir()  # exactly one, the final one
    ckpt = load_checkpoint(ckpt_path)
    resumed_from = 1024 + 2 * PER_RANK_UPDATE
    assert ckpt.meta.step_id == summary["steps"] > resumed_from
    assert (ckpt.meta.step_id - resumed_from) % (2 * PER_RANK_UPDATE) == 0  # whole 2-rank updates
    assert ckpt.meta.parent_checkpoint == str(one_rank_resume)
    assert ckpt.optimizer is not None
    updates = (ckpt.meta.step_id - resumed_from) // (2 * PER_RANK_UPDATE)
    assert {float(s["step"]) for s in ckpt.optimizer["state"].values()} == {24.0 + 4.0 * updates}


def test_a_killed_rank_ends_the_run_with_an_error_naming_the_timeout(tmp_path: Path) -> None:
    """SIGKILL to rank 1: rank 0's next collective times out (NAVI_DIST_TIMEOUT_S) and the run ends with an
    error naming that timeout instead of hanging."""
    proc = start_long_run(tmp_path, "--fresh", timeout_s="20")
    pids = rank_pids(proc.pid)
    os.kill(pids[1], signal.SIGKILL)
    try:
        _, err = proc.communicate(timeout=180)  # the 20 s collective timeout and teardown, on a loaded host
    except subprocess.TimeoutExpired:
        for pid in (proc.pid, *pids.values()):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        proc.communicate()
        pytest.fail("the run outlived its 20 s collective timeout by minutes: rank 0 hangs on the dead rank")
    assert proc.returncode != 0
    assert "error: rank 0 of 2:" in err and "NAVI_DIST_TIMEOUT_S=20 s" in err, err[-3000:]


PARITY = Path(__file__).with_name("dist_parity.py")


def parity_module() -> ModuleType:
    """dist_parity.py imported: the setup the ranks ran, for the single-process references."""
    spec = importlib.util.spec_from_file_location("dist_parity", PARITY)
    assert spec is not None and spec.loader is not None
    parity = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(parity)
    return parity


@pytest.fixture(scope="module")
def parity_ranks(tmp_path_factory: pytest.TempPathFactory) -> list[dict[str, Any]]:
    """dist_parity.py on 2 gloo ranks: what each rank wrote."""
    folder = tmp_path_factory.mktemp("parity")
    out = subprocess.run(
        [*TORCHRUN, str(PARITY), str(folder)], env=navi_env(), capture_output=True, text=True, timeout=180
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return [torch.load(folder / f"rank{r}.pt", weights_only=True) for r in (0, 1)]


def test_one_update_on_two_ranks_equals_one_update_on_the_union(parity_ranks: list[dict[str, Any]]) -> None:
    ranks = parity_ranks
    parity = parity_module()
    assert ranks[0]["buckets"] == ranks[1]["buckets"] > 1  # the gradients travel in several buckets
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        policy, optimizer, buf, cfg = parity.parity_setup()
        initial = {k: v.clone() for k, v in policy.state_dict().items()}
        policy.rnd.intrinsic(parity.embeddings())
        _, skipped = update(policy, optimizer, buf, cfg, torch.Generator().manual_seed(0))
    finally:
        torch.set_num_threads(before)
    for k in range(2):  # each minibatch's advantage moments over the union of the ranks' minibatches
        union = torch.cat(
            [parity.shard(buf, r, 2).minibatch(ranks[r]["adv"]["ids"][k]).advantages for r in (0, 1)]
        )
        moments = torch.stack([union.mean(), union.std(unbiased=False)])  # (2,)
        for r in ranks:
            torch.testing.assert_close(r["adv"]["moments"][k], moments, atol=1e-6, rtol=1e-5)
    for k, v in policy.state_dict().items():
        assert torch.equal(ranks[0]["state"][k], ranks[1]["state"][k]), k  # replicas bit-identical
        torch.testing.assert_close(ranks[0]["state"][k], v, atol=2e-6, rtol=1e-5, msg=k)  # RND stats too
    moved = [k for k, v in policy.state_dict().items() if not torch.equal(v, initial[k])]
    assert "heads.log_std" in moved and "rnd.predictor.0.weight" in moved and "rnd.err_mean" in moved
    assert skipped == 0 and [r["skipped"] for r in ranks] == [[0, 1], [0, 1]]  # rank 1's NaN: both skip
    assert ranks[0]["unchanged"] and ranks[1]["unchanged"]
    adaptive = [r["adaptive"] for r in ranks]
    assert adaptive[0]["lr"] == adaptive[1]["lr"]  # one rate on both ranks
    assert adaptive[0]["lr"] != pytest.approx(1e-3)  # and it moved
    for k, v in adaptive[0]["state"].items():
        assert torch.equal(adaptive[1]["state"][k], v), k


def test_bucketed_gradients_equal_one_flat_all_reduce_and_go_while_backward_runs(
    parity_ranks: list[dict[str, Any]],
) -> None:
    """Sync.backward against one flat all-reduce of every gradient, both ÷ world: the same averages bit
    for bit in one bucket, a few, and one per parameter, with the eager and the compiled objective. The
    eager backward launches every bucket but the last before it reaches the first parameter; the compiled
    backward (one graph) hands every gradient over at its end, so its buckets all go after it."""
    for r in parity_ranks:
        for kind in ("eager", "compiled"):
            got = r["bucket_parity"][kind]
            assert set(got) == {"one bucket", "a few", "one per parameter"}
            for name, (buckets, early, same) in got.items():
                assert same, (kind, name)
                assert early == (buckets - 1 if kind == "eager" else 0), (kind, name, buckets, early)
            assert got["one bucket"][0] == 1 and got["one per parameter"][0] == 42  # the tiny engine's
            assert 1 < got["a few"][0] < 42


def test_bucket_plan_covers_every_parameter_once_in_reverse_order(monkeypatch: pytest.MonkeyPatch) -> None:
    sizes = [10, 300, 95, 5, 1000, 7]  # float32 elements
    plan = bucket_plan(sizes, cap_bytes=400 * 4)
    assert plan == [[5, 4], [3, 2, 1], [0]]  # closes once it holds the cap or more; the rest last
    assert sorted(i for b in plan for i in b) == list(range(len(sizes)))
    assert bucket_plan(sizes, cap_bytes=10**9) == [[5, 4, 3, 2, 1, 0]]
    assert bucket_plan([], cap_bytes=4) == [[]]  # the flag's bucket
    monkeypatch.setenv(BUCKET_ENV, "0.5")
    assert bucket_mb_from_env() == 0.5
    for bad in ("big", "0", "-1"):
        monkeypatch.setenv(BUCKET_ENV, bad)
        with pytest.raises(ValueError, match=BUCKET_ENV):
            bucket_mb_from_env()


class HandClock:
    """A host clock that moves only when told: `perf_counter` for the timing module."""

    def __init__(self) -> None:
        self.now = 0.0

    def perf_counter(self) -> float:
        return self.now


def test_the_waits_within_a_stage_count_as_sync_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    """A rank's timeline: forward and learn leave out the sync within them, so the four stages and the
    sync outside any stage add up to the time timed, each part once."""
    clock = HandClock()
    monkeypatch.setattr(timing_module, "time", clock)
    timers = StageTimers(sync=False)
    with timers("forward"):
        clock.now += 0.004
        with timers("sync"):
            clock.now += 0.003
        clock.now += 0.001
    with timers("learn"):
        with timers("sync"):
            clock.now += 0.010
        clock.now += 0.020
    with timers("sync"):  # between stages (the stop flags)
        clock.now += 0.002
    ms = timers.read(steps=1)
    assert ms == pytest.approx({"ms_env": 0.0, "ms_forward": 5.0, "ms_learn": 20.0, "ms_sync": 15.0})
    assert sum(ms.values()) == pytest.approx(1000.0 * clock.now)
    with pytest.raises(RuntimeError), timers("learn"), timers("sync"):
        raise RuntimeError("a failed collective")
    assert timers.open == []  # it left both stages: the next one opened is within none


def one_call_late() -> Callable[[torch.Tensor], torch.Tensor]:
    """One process's sums handed back one call late: the first call's at once, and again at the second."""
    calls: list[torch.Tensor] = []

    def reduce(t: torch.Tensor) -> torch.Tensor:
        out = calls[-1] if calls else t
        calls.append(t)
        return out

    return reduce


def test_the_normaliser_pooled_one_step_late_is_the_unions_one_step_late(
    parity_ranks: list[dict[str, Any]],
) -> None:
    """5 rollout steps on 2 ranks through the step a rank trains with (PooledForward: its graph between
    the normaliser's all-reduces): each rank's novelty is that of one process on both ranks' embeddings
    whose normaliser folds in the previous step's moments; the normaliser ends the same on both ranks,
    bit for bit. The first step is the same-step normaliser's; the lag shows from the third."""
    parity = parity_module()
    lagged = [r["lagged"] for r in parity_ranks]
    steps = torch.cat([r["emb"] for r in lagged], dim=1)  # (K, 16, D): rank 0's actors, then rank 1's
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        late, same_step, reduce = parity.fresh_rnd(), parity.fresh_rnd(), one_call_late()
        for rnd in (late, same_step):
            rnd.load_state_dict(lagged[0]["start"])
        want = torch.stack([late.intrinsic(batch, reduce) for batch in steps])  # (K, 16)
        plain = torch.stack([same_step.intrinsic(batch) for batch in steps])  # (K, 16)
    finally:
        torch.set_num_threads(before)
    assert all(torch.equal(lagged[1]["start"][k], v) for k, v in lagged[0]["start"].items())
    got = torch.cat([r["novelty"] for r in lagged], dim=1)  # (K, 16)
    torch.testing.assert_close(got, want, atol=1e-6, rtol=1e-5)
    for name, value in lagged[0]["normaliser"].items():
        assert torch.equal(lagged[1]["normaliser"][name], value), name  # identical on both ranks
        torch.testing.assert_close(value, dict(late.named_buffers())[name], atol=1e-7, rtol=1e-5)
    # step 0 waits for its own sums (the same-step normaliser's moments are float32, the pooled float64)
    torch.testing.assert_close(got[0], plain[0], atol=1e-5, rtol=1e-4)
    assert not torch.allclose(got[2:], plain[2:], atol=1e-3)  # later steps: the previous step's moments


def test_scaling_is_against_the_faster_one_process_run() -> None:
    """Two one-process runs that disagree: the ratio uses the faster (the lower ratio); one run is its own
    baseline; none is refused."""
    from navi_bench.train import scaling_report, timeline_table

    def run(sps: int) -> dict[str, Any]:
        ms = {"collect": 1.0, "forward": 1.0, "update": 1.0, "sync": 0.0, "other": 0.0, "step": 3.0}
        return {
            "env_only_sps": 4 * sps,
            "env_inference_sps": 2 * sps,
            "env_train_sps": sps,
            "timeline_ms": ms,
        }

    ranks = {"ranks": [run(95) | {"rank": 0}, run(95) | {"rank": 1}], "total": {}}
    ranks["total"] = {k: 2 * v for k, v in run(95).items() if k.endswith("_sps")}
    slow, fast = run(90), run(100)
    report = scaling_report(2, [slow, fast], ranks)
    assert report["single"] is fast and report["single_runs"] == [slow, fast]
    assert report["scaling_efficiency"] == {"env_only": 0.95, "env_inference": 0.95, "env_train": 0.95}
    assert "90 and 100 train SPS (the faster is the baseline)" in timeline_table(report)
    alone = scaling_report(2, [slow], ranks)
    assert alone["scaling_efficiency"]["env_train"] == pytest.approx(190 / 180, abs=1e-3)
    assert "before and after" not in timeline_table(alone)
    with pytest.raises(ValueError, match="at least one"):
        scaling_report(2, [], ranks)


def test_bench_train_nproc_reports_ranks_totals_and_scaling(tmp_path: Path) -> None:
    args = ["bench", "train", *TRAIN_ARGS, "--updates", "1", "--nproc", "2", "--json"]
    out = run_navi(args, tmp_path, 240)
    assert out.returncode == 0, out.stderr[-3000:]
    report: dict[str, Any] = json.loads(out.stdout)
    assert report["nproc"] == 2 and [r["rank"] for r in report["ranks"]] == [0, 1]
    # one process before and after the ranks; the faster run is the baseline
    runs = report["single_runs"]
    assert len(runs) == 2 and report["single"] == max(runs, key=lambda r: r["env_train_sps"])
    assert f"{runs[0]['env_train_sps']:,} and {runs[1]['env_train_sps']:,} train SPS" in out.stderr
    columns = ("env_only_sps", "env_inference_sps", "env_train_sps")
    for col in columns:
        assert report["single"][col] > 0 and all(r[col] > 0 for r in report["ranks"])
        assert report["total"][col] == sum(r[col] for r in report["ranks"])
        expected = report["total"][col] / (2 * report["single"][col])
        assert report["scaling_efficiency"][col.removesuffix("_sps")] == pytest.approx(expected, abs=1e-3)
    assert report["single"]["actors"] == ACTORS and all(r["actors"] == ACTORS for r in report["ranks"])
    # every rank's timeline: its stages without their waits, the waits, the rest; they make up its step
    assert report["single"]["ms_per_step"]["sync"] == report["single"]["timeline_ms"]["sync"] == 0.0
    table = out.stderr[out.stderr.index("ms per env step: collect") :].splitlines()
    for name, r in [("single", report["single"]), *((f"rank {r['rank']}", r) for r in report["ranks"])]:
        ms, line = r["timeline_ms"], r["ms_per_step"]
        assert [ms[k] for k in ("collect", "forward", "update", "sync")] == [
            line[k] for k in ("env", "forward", "learn", "sync")
        ]
        assert min(ms[k] for k in ("collect", "forward", "update", "sync")) >= 0.0
        parts = ms["collect"] + ms["forward"] + ms["update"] + ms["sync"] + ms["other"]
        assert parts == pytest.approx(ms["step"], abs=5e-3)
        assert ms["step"] >= 1000.0 * ACTORS / r["env_train_sps"] * (1 - 2e-3)  # mean step ≥ 1 / mean SPS
        (row,) = [x[8:].split() for x in table if x.startswith(f"{name:>8}")]  # the name, right-aligned
        assert [float(v) for v in row[:6]] == pytest.approx([ms[k] for k in ms], abs=1e-3)
        assert row[6] == f"{r['env_train_sps']:,}"
    assert all(r["timeline_ms"]["sync"] > 0.0 for r in report["ranks"])  # each rank waits in collectives


def test_one_gpu_per_rank_is_checked_before_joining(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("LOCAL_RANK", str(torch.cuda.device_count()))  # one past the last GPU
    with pytest.raises(ValueError, match="one rank per GPU"):
        setup("cuda")
    monkeypatch.setenv("NAVI_DIST_TIMEOUT_S", "soon")
    with pytest.raises(ValueError, match="NAVI_DIST_TIMEOUT_S"):
        setup("cpu")
    assert not tdist.is_initialized()


def test_the_launchers_pass_the_command_on_without_nproc() -> None:
    from navi.stack import StackConfig, service_specs

    argv = ["train", "--nproc", "2", "--env", "toy", "--nproc=3", "--actors", "4"]
    assert strip_option(argv, "--nproc") == ["train", "--env", "toy", "--actors", "4"]
    learner = service_specs(StackConfig(navi=("navi",), nproc=2), with_auditor=False)[3].argv
    assert learner[learner.index("--nproc") + 1] == "2"
    from navi import cli as root

    group: Any = typer.main.get_command(root.build_app())
    serve = group.commands["serve"].commands["learner"]
    assert serve.make_context("navi serve learner", list(learner[3:])).params["nproc"] == 2
    assert "--nproc" not in service_specs(StackConfig(navi=("navi",)), with_auditor=False)[3].argv


def test_a_single_process_run_makes_no_collective_call(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, single_thread: None
) -> None:
    """World size 1 keeps today's loop: no process group, and any collective would raise here."""

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("a single-process run called torch.distributed")

    for name in (
        "init_process_group",
        "all_reduce",
        "broadcast",
        "broadcast_object_list",
        "all_gather_object",
    ):
        monkeypatch.setattr(tdist, name, refuse)
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    cfg = TrainConfig(
        n_actors=ACTORS,
        rollout_length=ROLLOUT,
        total_steps=2 * PER_RANK_UPDATE,
        checkpoint_every=10**9,
        engine=EngineConfig(
            temporal_core="gru", embed_dim=32, patch_size=4, encoder_layers=1, head_hidden=32
        ),
    )
    d, device = setup("cpu")
    result = train(ToyEnv(ACTORS, seed=0), cfg, run_dir=tmp_path / "run", progress=False, dist=d)
    assert d == Dist(timeout_s=d.timeout_s) and device == "cpu" and not d.active
    assert result.step_id == 2 * PER_RANK_UPDATE and "world_size" not in json.loads(
        (tmp_path / "run" / "manifests" / "run.json").read_text()
    )


def test_bench_learn_trains_each_run_on_two_ranks(tmp_path: Path) -> None:
    """`navi bench learn --nproc 2`: one run trained data-parallel, each rank on every train scene (its
    own spawns and seed), after an untimed warm-up on both ranks, rank 0 evaluating during training and
    at the end; steps count both ranks."""
    from navi_env.corpus.folder import build_default_corpus

    root = tmp_path / "corpora"
    build_default_corpus(root / "procedural-train-64", resolution=64, count=2, seed=0)
    build_default_corpus(root / "procedural-unseen-64", resolution=64, count=1, seed=1000)
    out = tmp_path / "out"
    args = "bench learn --nproc 2 --seeds 1 --temporal-core gru --budget-s 2 --eval-every-s 1"
    args += f" --actors {ACTORS} --rollout-length 16 --eval-actors 4 --eval-steps 16 --eval-episode-steps 8"
    args += f" --resolution 64 --no-compile --device cpu --json --corpus-root {root} --out {out}"
    args += f" --openarena {tmp_path / 'none.pk3'} --warmup-updates 1"
    done = run_navi(args.split(), tmp_path, 300)
    assert done.returncode == 0, done.stderr[-3000:]
    saved = json.loads((out / "result.json").read_text())
    assert "x 2 (each run data-parallel on 2 ranks)" in saved["device"] and saved["config"]["nproc"] == 2
    (run,) = saved["runs"]
    assert run["ranks"] == 2 and run["train_config"]["n_actors"] == ACTORS
    assert run["steps"] > 0 and run["steps"] % (2 * ACTORS * 16) == 0  # both ranks' steps per update
    assert run["train_s"] >= 2.0 and run["curve"] and run["curve"][-1]["step"] == run["steps"]
    assert set(run["final_by_split"]) == {"procedural"}
    manifest = json.loads((out / "runs" / "gru-seed0" / "manifests" / "run.json").read_text())
    assert manifest["world_size"] == 2 and manifest["actors_per_rank"] == ACTORS
    shares = [sorted(r["scenes"]) for r in manifest["ranks"]]
    assert shares == [["corridors_0001", "rooms_0000"]] * 2  # every rank flies every scene
    # the job's files are gone; the ranks' untimed warm-up trained in a folder of its own, off the clock
    assert sorted(p.name for p in (out / "runs").iterdir()) == ["gru-seed0", "gru-seed0-warmup"]
    warm = json.loads((out / "runs" / "gru-seed0-warmup" / "manifests" / "run.json").read_text())
    assert warm["world_size"] == 2 and warm["actors_per_rank"] == ACTORS
    (entry,) = saved["warmups"]
    assert (entry["arm"], entry["seed"], entry["updates"], entry["device"]) == ("gru", 0, 1, "cpu x 2 ranks")
    assert entry["seconds"] > 0 and "warmup" not in run
    report = (out / "report.md").read_text()
    assert "1 untimed updates per data-parallel run (gru seed 0 " in report
    assert json.loads(done.stdout)["summary"]["gru"]["seeds"] == 1


def test_bench_learn_nproc_refuses_what_it_cannot_do(tmp_path: Path) -> None:
    """--nproc with --parallel or --gpus: one clear line, exit status 2, before any corpus is built."""
    from typer.testing import CliRunner

    from navi.cli import build_app

    base = f"bench learn --nproc 2 --out {tmp_path / 'out'} --corpus-root {tmp_path / 'none'}".split()
    cases = [
        (["--parallel", "2", "--device", "cpu"], "leave out --parallel and --gpus"),
        (["--gpus", "2", "--device", "cpu"], "leave out --parallel and --gpus"),
    ]
    for extra, said in cases:
        result = CliRunner().invoke(build_app(), [*base, *extra])
        assert result.exit_code == 2 and said in result.output, result.output
        assert not (tmp_path / "none").exists()  # refused before any corpus is built
