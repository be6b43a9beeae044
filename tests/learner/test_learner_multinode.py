"""Two torchrun "nodes" on one host, one rank each, meeting through a c10d rendezvous on loopback (gloo),
each in a folder of its own as separate hosts would be: training runs, the replicas stay bit-identical,
rank 0 alone writes (its node's folder holds the run, the other node's folder nothing), and a killed
node ends the other with an error that names the rank and the collective timeout.

The rendezvous store is this test's: a TCPStore bound to a port the OS picks, its port read back and
given to both nodes, which join it as clients (`is_host=false`)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from .test_learner_distributed import TRAIN_ARGS, navi_env, rank_pids

NODES = 2
RUN_STEPS = 4 * NODES * 4 * 32  # 4 updates of 2 ranks x 4 actors x 32 steps


@contextlib.contextmanager
def rendezvous_store() -> Iterator[int]:
    """A c10d rendezvous store served by this process on a loopback port the OS picks; yields the port."""
    from torch.distributed import TCPStore

    store = TCPStore("127.0.0.1", 0, is_master=True, wait_for_workers=False, multi_tenant=True)
    try:
        yield int(store.port)
    finally:
        del store


def node(rank: int, port: int, cwd: Path, *args: str, **env: str) -> subprocess.Popen[str]:
    """One "node": torchrun with one rank, joining the c10d rendezvous at 127.0.0.1:port as a client."""
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--nnodes", str(NODES), "--node-rank", str(rank),
        "--nproc-per-node", "1", "--rdzv-backend", "c10d", "--rdzv-endpoint", f"127.0.0.1:{port}",
        "--rdzv-conf", "is_host=false", "--rdzv-id", "navi-multinode-test", "-m", "navi", "train", *TRAIN_ARGS,
        *args,
    ]  # fmt: skip
    cwd.mkdir(parents=True, exist_ok=True)
    return subprocess.Popen(
        cmd,
        cwd=cwd,
        env=navi_env(**env),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.fixture(scope="module")
def two_nodes(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[tuple[int, str, str]]]:
    """A finished 2-node run: (root, [(exit code, stdout, stderr) per node]); node r ran in root/node<r>."""
    root = tmp_path_factory.mktemp("multinode")
    debug = {"NAVI_DIST_DEBUG_DIR": str(root / "debug")}
    args = ("--total-steps", str(RUN_STEPS), "--checkpoint-every", "1000000000", "--fresh")
    with rendezvous_store() as port:
        procs = [node(r, port, root / f"node{r}", *args, **debug) for r in range(NODES)]
        results = []
        try:
            for proc in procs:
                out, err = proc.communicate(timeout=900)  # bounds a hang only
                results.append((proc.returncode, out, err))
        finally:
            for proc in procs:
                stop(proc)
    return root, results


def test_two_nodes_train_with_identical_replicas_and_rank_0_alone_writes(
    two_nodes: tuple[Path, list[tuple[int, str, str]]],
) -> None:
    root, results = two_nodes
    for code, _, err in results:
        assert code == 0, err[-3000:]
    ranks = [json.loads((root / "debug" / f"rank{r}.json").read_text()) for r in range(NODES)]
    assert ranks[0]["step_id"] == ranks[1]["step_id"] == RUN_STEPS
    assert ranks[0]["model"] == ranks[1]["model"] and ranks[0]["optimizer"] == ranks[1]["optimizer"]
    # the rendezvous numbers the ranks; rank 0 is the node that printed the run's summary
    printed = [r for r, (_, out, _) in enumerate(results) if any(x.startswith("{") for x in out.splitlines())]
    assert len(printed) == 1
    writer, other = root / f"node{printed[0]}", root / f"node{1 - printed[0]}"
    (line,) = [x for x in results[printed[0]][1].splitlines() if x.startswith("{")]
    assert json.loads(line)["steps"] == RUN_STEPS
    (run,) = (writer / "artifacts" / "runs").iterdir()
    manifest = json.loads((run / "manifests" / "run.json").read_text())
    assert manifest["world_size"] == NODES and [r["rank"] for r in manifest["ranks"]] == [0, 1]
    rows = [json.loads(x) for x in (run / "metrics" / "metrics.jsonl").read_text().splitlines()]
    assert rows[-1]["step"] == RUN_STEPS
    assert [p for p in other.rglob("*") if p.is_file()] == []  # the other node wrote nothing


def stop(proc: subprocess.Popen[str]) -> None:
    """Kill a node's torchrun and its rank if they are still running (a failed test leaves none)."""
    if proc.poll() is not None:
        return
    for pid in [*rank_pids(proc.pid).values(), proc.pid]:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    proc.wait(timeout=30)


def test_a_killed_node_ends_the_other_with_a_clear_error(
    tmp_path: Path, request: pytest.FixtureRequest, rendezvous_port: int
) -> None:
    args = ("--total-steps", "100000000", "--checkpoint-every", "1000000000", "--fresh")
    procs = [
        node(r, rendezvous_port, tmp_path / f"node{r}", *args, NAVI_DIST_TIMEOUT_S="20") for r in range(NODES)
    ]

    def stop_both() -> None:
        for proc in procs:
            stop(proc)

    request.addfinalizer(stop_both)
    deadline = time.monotonic() + 600  # bounds a hang only
    while not list(tmp_path.glob("node*/artifacts/runs/*/metrics/metrics.jsonl")):  # both ranks train
        assert all(p.poll() is None for p in procs), procs[0].communicate()
        assert time.monotonic() < deadline, "no training row within the hang bound"
        time.sleep(0.2)
    (worker,) = rank_pids(procs[1].pid).values()  # torchrun starts its rank in a session of its own
    for pid in (procs[1].pid, worker):  # node 1 goes down whole: its torchrun agent and its rank
        os.kill(pid, signal.SIGKILL)
    procs[1].wait(timeout=60)
    _, err = procs[0].communicate(timeout=600)  # the collective timeout (20 s) ends it; this bounds a hang
    assert procs[0].returncode != 0
    assert " of 2: " in err and "NAVI_DIST_TIMEOUT_S=20 s" in err, err[-3000:]


@pytest.fixture
def rendezvous_port() -> Iterator[int]:
    with rendezvous_store() as port:
        yield port
