"""Signals: SIGTERM and Ctrl+C only set a stop flag that the service's loops poll, so a signal can land
anywhere (an import, a finaliser, code run by `exec`) without losing the stop or the exit status, and
the learner ends training after the update in progress with a checkpoint of that step."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from services_testlib import Services, learner_health, wait_for

from navi_learner.serving.checkpoint import load_checkpoint

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]


def test_a_signal_inside_exec_code_sets_stop_and_the_service_exits_0() -> None:
    """The signal lands while the body runs code compiled by `exec` (as dataclass methods are): an
    exception raised from the handler there would leave the body and make the interpreter exit by
    SIGINT (-2) even though the service catches it; the flag lets the body finish and return."""
    script = textwrap.dedent(
        """
        import os, signal
        from navi.commands.serve import run_service

        def body(stop):
            exec("os.kill(os.getpid(), signal.SIGTERM)\\nfor _ in range(200000): pass", {"os": os, "signal": signal})
            return "body finished, stop " + ("set" if stop.is_set() else "not set")

        print(run_service(body))
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().splitlines()[-1] == "body finished, stop set"


def test_sigterm_mid_training_ends_the_learner_with_a_checkpoint_of_its_last_update(
    services: Services,
) -> None:
    services.start("router", "serve", "router")
    actors, rollout = 4, 8
    api = services.reserve_port()
    learner = services.start("learner", "serve", "learner", "--env", "toy", "--actors", str(actors),
                             "--temporal-core", "gru", "--rollout-length", str(rollout), "--device", "cpu",
                             "--port", str(api), "--read-only", "--total-steps", "100000000",
                             "--checkpoint-every", "100000000")  # fmt: skip

    def training() -> bool:
        if not learner.alive():
            raise AssertionError(f"the learner exited:\n{learner.text()[-3000:]}")
        health = learner_health(api)
        return health is not None and health.get("phase") == "training" and int(health.get("step", 0)) > 0

    wait_for(training, 180.0, "the learner to log a training step")
    assert learner.stop(signal.SIGTERM, timeout_s=60.0) == 0, learner.text()[-3000:]
    summary = json.loads(learner.text().strip().splitlines()[-1])
    assert summary["interrupted"] is True
    steps = summary["steps"]
    assert steps > 0 and steps % (actors * rollout) == 0  # whole updates only
    checkpoint = load_checkpoint(Path(summary["checkpoint"]))
    assert checkpoint.meta.step_id == steps  # the final checkpoint holds the last update
    print(
        f"FAULT learner_sigterm_mid_training {json.dumps({'exit': 0, 'steps': steps, 'interrupted': True})}"
    )


def test_sigterm_while_the_learner_builds_its_corpus_stops_the_build_and_keeps_no_partial_corpus(
    services: Services, tmp_path: Path
) -> None:
    """The local build polls the stop flag between scenes: the service exits 0 at the next scene instead
    of compiling the rest and training, and the corpus folder gets nothing (the next start builds it)."""
    services.start("router", "serve", "router")
    corpus = tmp_path / "corpus"
    scenes = 12
    learner = services.start("learner", "serve", "learner", "--corpus", str(corpus), "--corpus-build", "local",
                             "--corpus-scenes", str(scenes), "--corpus-resolution", "96", "--actors", "4",
                             "--temporal-core", "gru", "--device", "cpu", "--port", "0", "--read-only",
                             "--total-steps", "100000000")  # fmt: skip
    learner.logged(r"corpus: \[1/\d+\]", 300.0)  # the build is under way
    t0 = time.monotonic()
    assert learner.stop(signal.SIGTERM, timeout_s=120.0) == 0, learner.text()[-3000:]
    stopped_s = time.monotonic() - t0
    log = learner.text()
    built = len(re.findall(r"corpus: \[\d+/\d+\] \S+: (?:pass|fail)", log))
    assert built < scenes, log[-3000:]  # the build stopped before its last scene
    assert json.loads(log.strip().splitlines()[-1]) == {"steps": 0, "interrupted": True}
    assert not (corpus / "manifest.json").exists()
    assert not [p for p in corpus.parent.iterdir() if p.name.startswith(f".{corpus.name}.")]  # no work folder
    print(
        f"FAULT learner_sigterm_in_corpus_build {json.dumps({'stopped_s': round(stopped_s, 1), 'scenes_built': built, 'of': scenes})}"
    )
