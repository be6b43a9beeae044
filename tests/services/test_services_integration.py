"""Real processes, real Zenoh on loopback: router + compiler + learner (CPU, tiny) + env + this test as
the subscriber/client. Every service is started with the same `navi serve ...` command the stack uses."""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import torch
import zenoh
from prometheus_client.parser import text_string_to_metric_families
from services_testlib import HoldPoint, Services, connected_routers, matched, wait_for

from navi_contracts.codec import encode
from navi_contracts.models import CompileJob, CompileResult, Message, ModelPromoted, StepRequest, StepResult
from navi_contracts.topics import ACTIONS, COMPILE_JOBS, MODEL_PROMOTED, OBSERVATIONS, STEP, TELEMETRY
from navi_mesh.liveliness import live_tokens
from navi_mesh.pubsub import RequestError, request, subscribe

pytestmark = pytest.mark.integration


def client(services: Services) -> zenoh.Session:
    sess: zenoh.Session = services.session()
    return sess


def router(services: Services, name: str = "router") -> None:
    services.start(name, "serve", "router")


def scrape(port: int) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def alive(sess: zenoh.Session, service: str) -> list[str]:
    return [t.instance for t in live_tokens(sess, service, timeout_s=0.5)]


def source_mesh(tmp: Path) -> Path:
    from navi_compiler.ingest.procedural import generate_corpus

    return generate_corpus(tmp / "sources", 1, 0)[0]


def raw_query(sess: zenoh.Session, key: str, payload: bytes) -> str:
    """Send raw bytes to a queryable; the text of its error reply ('' when it answered ok)."""
    for reply in sess.get(key, payload=payload, timeout=60.0):
        if reply.err is not None:
            return reply.err.payload.to_bytes().decode()
    return ""


def test_compiler_service(services: Services, tmp_path: Path) -> None:
    from navi_compiler.gmdag import read_gmdag
    from navi_compiler.service import BUSY_PREFIX, submit_compile_job

    src = source_mesh(tmp_path)
    out = tmp_path / "out"
    # A copy of the scene for the long job below: its worker stops as it opens it, until killed.
    long_src = src.with_name("long.obj")
    shutil.copyfile(src, long_src)
    shutil.copyfile(src.with_suffix(".scene.json"), long_src.with_suffix(".scene.json"))
    hold = HoldPoint("open", re.escape(str(long_src)) + "$", tmp_path / "held-compiler")
    router(services)
    compiler = services.start(
        "compiler", "serve", "compiler", "--workers", "2", "--metrics-port", "0", hold=hold
    )
    metrics_port = compiler.metrics_port("compiler")
    sess = client(services)
    wait_for(lambda: len(alive(sess, "compiler")) == 2, 120.0, "two compiler workers")

    stages: list[tuple[str, float]] = []
    job = CompileJob(job_id="good", source=str(src), output=str(out / "good.gmdag"), resolution=64)
    result = submit_compile_job(job, 60.0, lambda s, f: stages.append((s, f)), sess=sess)
    assert result.ok, result.error
    read_gmdag(out / "good.gmdag")  # validates the whole file (magic, counts, references, checksum)
    assert (
        result.stats["resolution"] == 64 and result.stats["file_bytes"] == (out / "good.gmdag").stat().st_size
    )
    assert stages and stages[-1][1] == 1.0 and [f for _, f in stages] == sorted(f for _, f in stages)

    # The same through the command line: `navi compile --remote` waits for a worker's result.
    cli = subprocess.run(
        [sys.executable, "-m", "navi", "compile", str(src), "-o", str(out / "cli.gmdag"), "--resolution", "64",
         "--remote", "--timeout", "60", "--json"],
        cwd=services.cwd, env=services.env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert cli.returncode == 0, cli.stderr
    assert json.loads(cli.stdout)["output"] == str(out / "cli.gmdag")
    assert (out / "cli.gmdag").read_bytes() == (out / "good.gmdag").read_bytes()
    missing = subprocess.run(
        [sys.executable, "-m", "navi", "compile", str(tmp_path / "nope.obj"), "-o", str(out / "x.gmdag"),
         "--remote", "--timeout", "60"],
        cwd=services.cwd, env=services.env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert missing.returncode == 2 and "IngestError" in missing.stderr and "Traceback" not in missing.stderr

    bad = submit_compile_job(
        CompileJob(
            job_id="bad", source=str(tmp_path / "missing.obj"), output=str(out / "bad.gmdag"), resolution=64
        ),
        60.0,
        sess=sess,
    )
    assert not bad.ok and bad.error_type == "IngestError" and "not found" in (bad.error or "")
    assert not (out / "bad.gmdag").exists()

    # Garbage to a worker: an error reply, counted; the worker keeps serving.
    worker = alive(sess, "compiler")[0]
    assert "ContractError" in raw_query(sess, f"{COMPILE_JOBS.key}/{worker}", b"\x00not msgpack")
    after = [
        submit_compile_job(
            CompileJob(
                job_id=f"again{i}", source=str(src), output=str(out / f"again{i}.gmdag"), resolution=64
            ),
            60.0,
            sess=sess,
        )
        for i in range(2)
    ]
    assert all(r.ok for r in after)
    samples = scrape(metrics_port)
    assert samples[("navi_decode_errors_total", (("topic", COMPILE_JOBS.key),))] == 1.0
    assert (
        samples[("navi_compile_jobs_total", (("outcome", "ok"),))] == 4.0
    )  # good, the CLI job, two after the garbage
    assert (
        samples[("navi_compile_jobs_total", (("outcome", "error"),))] == 2.0
    )  # the missing source, twice (API and CLI)
    assert samples[("navi_compile_duration_seconds_count", ())] == 6.0

    # Load sharing: while one worker is busy with a long job, the next job goes to the other one.
    long_job = CompileJob(job_id="long", source=str(long_src), output=str(out / "long.gmdag"), resolution=64)
    results: list[CompileResult | RequestError] = []

    def run_long() -> None:
        try:
            results.append(submit_compile_job(long_job, 120.0, sess=sess))
        except RequestError as err:
            results.append(err)

    runner = threading.Thread(target=run_long)
    runner.start()
    assert hold.reached() == compiler.proc.pid  # a worker took the long job and stays inside it
    wait_for(lambda: bool(live_tokens(sess, "compiler", 0.5, prefix=BUSY_PREFIX)), 60.0, "a busy worker")
    busy = live_tokens(sess, "compiler", 0.5, prefix=BUSY_PREFIX)[0].instance
    short = submit_compile_job(
        CompileJob(job_id="short", source=str(src), output=str(out / "short.gmdag"), resolution=64),
        60.0,
        sess=sess,
    )
    assert short.ok and short.worker_id != busy

    # Killed half-way: no partial .gmdag is left behind, and the client gets a clear error.
    assert runner.is_alive() and not results
    compiler.stop(signal.SIGKILL)
    runner.join(120.0)
    assert not runner.is_alive(), "the client must notice that its worker died"
    assert isinstance(results[0], RequestError) and "died" in str(results[0])
    assert not (out / "long.gmdag").exists()
    finished = ["again0.gmdag", "again1.gmdag", "cli.gmdag", "good.gmdag", "short.gmdag"]
    assert sorted(p.name for p in out.glob("*.gmdag")) == finished


def test_learner_service_telemetry_control_plane_and_router_restart(
    services: Services, tmp_path: Path
) -> None:
    from navi_learner.config import TrainConfig
    from navi_learner.serving.checkpoint import CheckpointMeta, save_checkpoint

    token = "integration-token"
    services.env["NAVI_API_TOKEN"] = token
    router(services)
    sess = client(services)
    received: dict[str, list[Any]] = {
        TELEMETRY.key: [],
        OBSERVATIONS.key: [],
        ACTIONS.key: [],
        MODEL_PROMOTED.key: [],
    }
    subs = [
        subscribe(sess, t, received[t.key].append) for t in (TELEMETRY, OBSERVATIONS, ACTIONS, MODEL_PROMOTED)
    ]
    api = services.reserve_port()
    actors, rollout, updates = 4, 32, 96
    total = actors * rollout * updates
    learner = services.start(
        "learner",
        "serve",
        "learner",
        "--env",
        "toy",
        "--actors",
        str(actors),
        "--temporal-core",
        "gru",
        "--rollout-length",
        str(rollout),
        "--total-steps",
        str(total),
        "--device",
        "cpu",
        "--host",
        "127.0.0.1",
        "--port",
        str(api),
    )

    def training_steps() -> list[int]:
        return [e.step for e in received[TELEMETRY.key] if getattr(e, "key", "") == "actor.training.sps"]

    wait_for(lambda: len(training_steps()) >= 3, 180.0, "training telemetry")
    keys = {e.key for e in received[TELEMETRY.key] if hasattr(e, "key")}
    assert {"actor.training.sps", "actor.training.reward_ema", "actor.training.policy_loss"} <= keys
    wait_for(lambda: bool(received[OBSERVATIONS.key]) and bool(received[ACTIONS.key]), 60.0, "observations")
    obs = received[OBSERVATIONS.key][-1]
    assert obs.depth.shape == (1, 16, 8) and list(obs.env_ids) == [0]
    assert received[ACTIONS.key][-1].command.shape == (actors, 4)

    # The router dies mid-training and comes back: training goes on, the session reconnects.
    before = max(training_steps())
    services.started[0].stop(signal.SIGKILL)
    wait_for(lambda: connected_routers(sess) == 0, 60.0, "the clients to lose the router")
    router(services, "router2")
    t_restart = time.monotonic()
    wait_for(lambda: max(training_steps()) > before + actors * rollout, 120.0, "telemetry after the restart")
    resumed_s = time.monotonic() - t_restart
    wait_for(
        lambda: max(training_steps()) > before + 2 * actors * rollout, 120.0, "telemetry after the restart"
    )
    assert learner.alive()
    wait_for(
        lambda: "learner" in [t.service for t in live_tokens(sess, timeout_s=0.5)], 60.0, "learner token back"
    )

    # Control plane: 401 without the token, 200 with it, and ModelPromoted on the mesh.
    wait_for(lambda: _up(api), 60.0, "the control plane")
    ckpt = save_checkpoint(
        tmp_path / "external.pt",
        {"w": torch.ones(1)},
        None,
        CheckpointMeta(1, 0, 0.5, 0.0, "gru", "ext", TrainConfig().to_dict(), [3, 16, 8]),
    )
    body = {"checkpoint": str(ckpt), "alias": "champion", "notes": "integration"}
    url = f"http://127.0.0.1:{api}"
    assert httpx.post(f"{url}/models/promote", json=body, timeout=60.0).status_code == 401
    matched(client(services), MODEL_PROMOTED.key)  # the router knows this test's subscriber again
    ok = httpx.post(
        f"{url}/models/promote", json=body, headers={"Authorization": f"Bearer {token}"}, timeout=60.0
    )
    assert ok.status_code == 200, ok.text
    wait_for(lambda: bool(received[MODEL_PROMOTED.key]), 60.0, "ModelPromoted")
    promoted = received[MODEL_PROMOTED.key][0]
    assert (
        isinstance(promoted, ModelPromoted)
        and promoted.alias == "champion"
        and promoted.version == ok.json()["version"]
    )
    metrics = httpx.get(f"{url}/metrics")
    families = {f.name: f for f in text_string_to_metric_families(metrics.text)}
    assert families["navi_steps"].samples[0].value > 0
    assert "navi_steps_per_second" in families and "navi_promotions" in families

    # The run completes every step; its metrics log has one row per update, none lost.
    wait_for(
        lambda: (
            any(getattr(e, "key", "") == "actor.training.done" for e in received[TELEMETRY.key])
            or not learner.alive()
        ),
        600.0,
        "the end of training",
    )
    assert learner.stop(signal.SIGTERM) == 0
    summary = json.loads(learner.text().strip().splitlines()[-1])
    assert summary["steps"] == total and summary["interrupted"] is False
    rows = [
        json.loads(line)
        for line in Path(
            services.env["NAVI_ARTIFACTS_DIR"], "runs", summary["run_id"], "metrics", "metrics.jsonl"
        )
        .read_text()
        .splitlines()
    ]
    assert [r["step"] for r in rows] == [float(actors * rollout * (i + 1)) for i in range(updates)]
    steps_lost = total - summary["steps"]
    assert steps_lost == 0  # the router outage cost training nothing
    telemetry_rows_seen = len(set(training_steps()))
    print(
        "FAULT router_restart "
        + json.dumps(
            {"steps_lost": steps_lost, "updates": updates, "update_rows_logged": len(rows),
             "telemetry_rows_missed": updates - telemetry_rows_seen, "telemetry_resumed_after_s": round(resumed_s, 1)}
        )
    )  # fmt: skip
    for s in subs:
        s.undeclare()


def _up(port: int) -> bool:
    try:
        return httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1.0).status_code == 200
    except httpx.HTTPError:
        return False


def test_env_service_answers_step_requests(services: Services, tmp_path: Path) -> None:
    from navi_env.corpus.folder import build_corpus

    corpus = tmp_path / "corpus"
    build_corpus([source_mesh(tmp_path)], corpus, resolution=64)
    services.env.update({"NAVI_AZIMUTH_BINS": "32", "NAVI_ELEVATION_BINS": "8"})
    router(services)
    env_service = services.start(
        "env",
        "serve",
        "env",
        "--corpus",
        str(corpus),
        "--actors",
        "3",
        "--device",
        "cpu",
        "--metrics-port",
        "0",
    )
    port = env_service.metrics_port("env")
    sess = client(services)
    observations: list[Message] = []
    sub = subscribe(sess, OBSERVATIONS, observations.append)
    wait_for(lambda: bool(alive(sess, "env")), 120.0, "the env service")
    matched(sess, STEP.key, queryable=True)

    def step(ids: list[int], actions: np.ndarray, reset: bool = False) -> StepResult:
        req = StepRequest(
            request_id=f"r{time.monotonic_ns()}",
            env_ids=np.array(ids, np.int32),
            actions=actions.astype(np.float32),
            reset=reset,
        )
        return request(sess, STEP.key, req, StepResult, 60.0)

    first = step([0, 1, 2], np.zeros((3, 4)), reset=True)
    assert first.step_id == 0 and first.observation is not None
    assert first.observation.depth.shape == (3, 32, 8)
    assert float(first.observation.depth.min()) >= 0.0 and float(first.observation.depth.max()) <= 1.0
    results = [step([2, 0], np.array([[1.0, 0, 0, 0], [0.5, 0, 0, 0.5]])) for _ in range(5)]
    assert [r.step_id for r in results] == [1, 2, 3, 4, 5]
    last = results[-1]
    assert list(last.env_ids) == [2, 0] and last.reward.shape == (2,) and np.isfinite(last.reward).all()
    assert last.observation is not None and last.observation.depth.shape == (2, 32, 8)
    with pytest.raises(RequestError, match="StepError"):
        step([7], np.zeros((1, 4)))
    # `navi infer --remote` flies the same drones with a checkpoint, through the same queryable.
    from navi_learner.config import EngineConfig, TrainConfig
    from navi_learner.envs.toy import ToyEnv
    from navi_learner.ppo.train import train

    cfg = TrainConfig(n_actors=2, rollout_length=8, total_steps=16, device="cpu", seed=0,
                      engine=EngineConfig(temporal_core="gru"))  # fmt: skip
    ckpt = train(ToyEnv(2, az=32, el=8), cfg, run_dir=tmp_path / "run", progress=False).final_checkpoint
    infer = subprocess.run(
        [sys.executable, "-m", "navi", "infer", "--checkpoint", str(ckpt), "--remote", "--actors", "3",
         "--total-steps", "4", "--device", "cpu", "--json"],
        cwd=services.cwd, env=services.env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert infer.returncode == 0, infer.stderr
    (flown,) = json.loads(infer.stdout)["results"]  # 4 batched steps of the env service's 3 drones
    assert (flown["steps"], flown["actors"]) == (4, 3) and np.isfinite(flown["reward_per_step"])
    after_infer = step([0], np.zeros((1, 4)))
    assert after_infer.step_id == 5  # the remote run reset the env (0) and stepped it 4 times; this is 5
    assert "ContractError" in raw_query(
        sess, STEP.key, encode(CompileJob(job_id="x", source="s", output="o"))
    )
    assert step([1], np.zeros((1, 4))).step_id == 6  # still serving
    wait_for(lambda: bool(observations), 60.0, "a published observation")
    samples = scrape(port)
    assert samples[("navi_decode_errors_total", (("topic", STEP.key),))] == 1.0
    assert (
        samples[("navi_step_requests_total", (("outcome", "ok"),))] == 13.0
    )  # 1 reset + 5 steps, the remote run (1 reset + 4 steps), 2 more
    assert samples[("navi_steps_total", (("mode", "env"),))] == 3.0 * 11  # 11 steps of 3 actors
    sub.undeclare()


def test_inference_follows_promotions(services: Services, tmp_path: Path) -> None:
    from navi_learner.config import EngineConfig, TrainConfig
    from navi_learner.envs.toy import ToyEnv
    from navi_learner.ppo.train import train

    def trained(seed: int) -> Path:
        cfg = TrainConfig(
            n_actors=2,
            rollout_length=16,
            total_steps=32,
            device="cpu",
            seed=seed,
            engine=EngineConfig(temporal_core="gru"),
        )
        return train(
            ToyEnv(2, seed=seed), cfg, run_dir=tmp_path / f"run{seed}", progress=False
        ).final_checkpoint

    first, second = trained(0), trained(1)
    token = "infer-token"
    services.env["NAVI_API_TOKEN"] = token
    router(services)
    sess = client(services)
    events: list[Message] = []
    sub = subscribe(sess, TELEMETRY, events.append)
    api = services.reserve_port()
    learner = services.start(
        "learner",
        "serve",
        "learner",
        "--mode",
        "infer",
        "--env",
        "toy",
        "--actors",
        "2",
        "--model",
        str(first),
        "--follow-alias",
        "champion",
        "--device",
        "cpu",
        "--host",
        "127.0.0.1",
        "--port",
        str(api),
    )

    def keys() -> set[str]:
        return {getattr(e, "key", "") for e in events}

    wait_for(lambda: "actor.inference.sps" in keys(), 120.0, "inference telemetry")
    assert not any(k.startswith("actor.training.") for k in keys())
    wait_for(lambda: _up(api), 60.0, "the control plane")
    body = {"checkpoint": str(second), "alias": "champion"}
    r = httpx.post(
        f"http://127.0.0.1:{api}/models/promote",
        json=body,
        headers={"Authorization": f"Bearer {token}"},
        timeout=60.0,
    )
    assert r.status_code == 200, r.text
    wait_for(lambda: "actor.inference.model_reloaded" in keys(), 120.0, "the model reload")
    assert learner.alive()
    assert learner.stop(signal.SIGTERM) == 0
    assert "loaded" in learner.text() and f"champion -> {r.json()['version']}" in learner.text()
    sub.undeclare()
