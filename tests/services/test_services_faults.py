"""Faults, measured (docs/SERVICES.md "Faults" takes its numbers from these tests):

- kill -9 of a compile worker mid-job: the job goes to the other worker and finishes; no partial file;
- kill -9 of the learner while it writes a checkpoint or the registry: every .pt file in the run and
  registry folders loads with torch.load(weights_only=True), the registry index is consistent, and
  the next start brings the audit log and latest.pt back in line;
  (each kill lands at a chosen point of the job or write: the process stops there (holdpoint.py) until
  the test kills it, so the fault is the same on a fast or a loaded machine;)
- random bytes and wrong-schema messages on every topic each running service subscribes to: no
  crash, each counted in navi_decode_errors_total{topic}, and the service still serves.
Each measured number is printed as `FAULT <name> <json>`.
"""

from __future__ import annotations

import json
import os
import random
import re
import signal
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
from services_testlib import HoldPoint, Service, Services, learner_health, matched, wait_for

from navi_contracts.codec import encode
from navi_contracts.models import (
    CompileJob,
    CompileResult,
    Message,
    RobotPose,
    StepRequest,
    StepResult,
    TelemetryEvent,
)
from navi_contracts.topics import (
    COMPILE_JOBS,
    FLOOR_PLAN,
    MODEL_PROMOTED,
    OBSERVATIONS,
    POSES,
    STEP,
    TELEMETRY,
)
from navi_learner.config import EngineConfig, TrainConfig
from navi_learner.serving.checkpoint import CheckpointMeta, save_checkpoint
from navi_learner.serving.registry import LATEST, ModelRegistry, sha256_of
from navi_mesh.liveliness import live_tokens
from navi_mesh.pubsub import request

pytestmark = pytest.mark.integration


def record(name: str, numbers: dict[str, Any]) -> None:
    print(f"FAULT {name} {json.dumps(numbers, sort_keys=True)}")


def scrape(url: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    text = urllib.request.urlopen(url, timeout=5).read().decode()
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def source_mesh(tmp: Path) -> Path:
    from navi_compiler.ingest.procedural import generate_corpus

    return generate_corpus(tmp / "sources", 1, 0)[0]


# ---------------------------------------------------------------------------------------------------
# kill -9 of a compile worker mid-job


def test_compile_worker_killed_mid_job_is_retried_on_another_worker(
    services: Services, tmp_path: Path
) -> None:
    from navi_compiler.gmdag import read_gmdag
    from navi_env.corpus.jobs import CorpusBuildConfig, compile_with_retries

    src, out = source_mesh(tmp_path), tmp_path / "out" / "scene.gmdag"
    # the worker that takes the job first stops as it opens the source; the other one goes through
    hold = HoldPoint("open", re.escape(str(src)) + "$", tmp_path / "held-compiler")
    services.start("router", "serve", "router")
    workers = {
        name: services.start(name, "serve", "compiler", "--metrics-port", "0", hold=hold)
        for name in ("compiler-a", "compiler-b")
    }
    sess = services.session()
    wait_for(lambda: len(live_tokens(sess, "compiler", 0.5)) == 2, 120.0, "two compiler processes")
    retries: list[tuple[float, str]] = []
    outcome: list[str] = []
    cfg = CorpusBuildConfig(out.parent, resolution=64, attempts=3, job_timeout_s=300.0)
    stop = threading.Event()

    def run() -> None:
        outcome.append(
            compile_with_retries(sess, src, out, cfg, stop, lambda e: retries.append((time.monotonic(), e)))
        )

    client = threading.Thread(target=run)
    t_start = time.monotonic()
    client.start()
    victim = next(svc for svc in workers.values() if svc.proc.pid == hold.reached())
    assert client.is_alive() and not retries  # the job is in the stopped worker's hands
    t_kill = time.monotonic()
    victim.stop(signal.SIGKILL)
    assert not out.exists()  # nothing was written by the killed worker
    client.join(300.0)
    assert not client.is_alive() and outcome == [""], outcome
    assert len(retries) == 1 and "died" in retries[0][1], retries
    read_gmdag(out)  # the retried job's file is complete and valid
    assert sorted(p.name for p in out.parent.iterdir()) == ["scene.gmdag"]  # no partial or temp file
    survivor = next(svc for svc in workers.values() if svc is not victim)
    assert survivor.alive() and f"-> {out} in " in survivor.text()  # the survivor compiled it
    record(
        "compile_worker_kill",
        {"retries": len(retries), "detected_after_s": round(retries[0][0] - t_kill, 2),
         "job_total_s": round(time.monotonic() - t_start, 1), "partial_files": 0},
    )  # fmt: skip


# ---------------------------------------------------------------------------------------------------
# kill -9 of the learner during a checkpoint (or registry) write


def temp_files(*folders: Path) -> list[Path]:
    found = []
    for folder in folders:
        try:
            found += [
                Path(e.path) for e in os.scandir(folder) if e.name.startswith(".") and e.name.endswith(".tmp")
            ]
        except FileNotFoundError:
            continue
    return found


def registry_consistent(root: Path, settled: bool) -> dict[str, int]:
    """Assert the registry's invariants; returns counts. `settled`: after recovery (audit and latest.pt
    agree with the index too); before it, one move may lack its audit line."""
    index = json.loads((root / "registry.json").read_text())
    versions = {v["version"]: v for v in index["versions"]}
    for v in versions.values():
        path = root / v["file"]
        assert path.is_file() and sha256_of(path) == v["sha256"], v["version"]
    assert set(index["aliases"].values()) <= set(versions)
    assert all(h in versions for hist in index["history"].values() for h in hist)
    replay: dict[str, str] = {}
    for line in (root / "audit.jsonl").read_text().splitlines():
        entry = json.loads(line)
        replay[entry["alias"]] = entry["to_version"]
    missing = {a for a, v in index["aliases"].items() if replay.get(a) != v}
    assert len(missing) <= (0 if settled else 1), (missing, replay, index["aliases"])
    if settled and LATEST in index["aliases"]:
        assert sha256_of(root / "latest.pt") == versions[index["aliases"][LATEST]]["sha256"]
    if settled:
        assert not temp_files(root)
    return {"versions": len(versions), "audit_lines_missing": len(missing)}


def every_pt_loads(*folders: Path) -> int:
    """torch.load(weights_only=True) of every *.pt file under the folders; returns how many."""
    count = 0
    for folder in folders:
        for path in sorted(folder.rglob("*.pt")):
            payload = torch.load(path, map_location="cpu", weights_only=True)
            assert payload["format_version"] == 3, path
            count += 1
    return count


def test_learner_killed_while_writing_a_checkpoint_leaves_loadable_files(
    services: Services, tmp_path: Path
) -> None:
    token = "kill-token"
    services.env["NAVI_API_TOKEN"] = token
    services.start("router", "serve", "router")
    artifacts = Path(services.env["NAVI_ARTIFACTS_DIR"])
    runs, models = artifacts / "runs", artifacts / "models"
    actors, rollout = 4, 8
    api = services.reserve_port()  # the control plane of every learner start below
    learner_args = ("serve", "learner", "--env", "toy", "--actors", str(actors), "--temporal-core", "gru",
                    "--rollout-length", str(rollout), "--device", "cpu", "--port", str(api))  # fmt: skip
    kills = {
        # a REST promotion replacing the registry index (the second one: the first makes the index)
        "registry": HoldPoint("os.rename", r"/models/\.registry\.json\.[^/]*\.tmp$", tmp_path / "held-registry", 1),
        # a checkpoint written and not yet renamed into place
        "checkpoint": HoldPoint("os.rename", r"/checkpoints/\.ckpt_step_\d+\.pt\.[^/]*\.tmp$", tmp_path / "held-ckpt"),
    }  # fmt: skip
    caught: dict[str, dict[str, Any]] = {}
    for what, hold in kills.items():
        stale = set(temp_files(*runs.glob("*/checkpoints"), models))  # left by the kill before
        learner = services.start(f"learner-{what}", *learner_args, "--total-steps", "100000000",
                                 "--checkpoint-every", str(actors * rollout), hold=hold)  # fmt: skip
        wait_for(lambda: learner_up(api), 120.0, "the learner's control plane")
        stop_promoting = threading.Event()
        promoter = threading.Thread(
            target=promote_forever, args=(api, token, runs, stop_promoting), daemon=True
        )
        if what == "registry":
            promoter.start()
        assert hold.reached() == learner.proc.pid
        learner.proc.send_signal(signal.SIGKILL)  # kill -9 with the write cut where the point is
        learner.proc.wait(30)
        stop_promoting.set()
        if promoter.is_alive():
            promoter.join(30.0)
        left = [p for p in temp_files(*runs.glob("*/checkpoints"), models) if p not in stale]
        cut = re.compile(hold.path)
        assert any(cut.search(str(p)) for p in left), (what, left)  # the write was cut: its temp file stays
        # every file that is a checkpoint loads, and the index holds
        caught[what] = {
            "partial": sorted(p.name.split(".tmp")[0] for p in left),
            "loaded": every_pt_loads(runs, models),
        }
        caught[what].update(registry_consistent(models, settled=False))
    # The next start recovers the registry: temporary files gone, audit and latest.pt agree with the index.
    learner = services.start("learner-after", *learner_args, "--total-steps", str(actors * rollout))
    wait_for(lambda: learner_up(api), 120.0, "the learner after the kills")
    settled = registry_consistent(models, settled=True)
    loaded = every_pt_loads(runs, models)
    assert learner.stop(signal.SIGTERM) == 0
    record("learner_kill_mid_write", {"kills": len(kills), "caught_mid_write": caught, "pt_files_loaded": loaded,
                                      "registry_versions": settled["versions"]})  # fmt: skip


def learner_up(port: int) -> bool:
    return learner_health(port) is not None


def promote_forever(port: int, token: str, runs: Path, stop: threading.Event) -> None:
    """Promote the newest checkpoint again and again (registry writes) until stopped or refused."""
    headers = {"Authorization": f"Bearer {token}"}
    while not stop.is_set():
        newest = sorted(runs.glob("*/checkpoints/ckpt_step_*.pt"))
        if not newest:
            stop.wait(0.01)
            continue
        try:
            httpx.post(f"http://127.0.0.1:{port}/models/promote", headers=headers, timeout=5.0,
                       json={"checkpoint": str(newest[-1]), "alias": "champion"})  # fmt: skip
        except httpx.HTTPError:
            return


def test_registry_recover_repairs_what_an_interrupted_writer_leaves(tmp_path: Path) -> None:
    meta = CheckpointMeta(10, 0, 0.5, 0.0, "gru", "r", TrainConfig().to_dict(), [3, 16, 8])
    ckpt = save_checkpoint(tmp_path / "c.pt", {"w": torch.ones(2)}, None, meta)
    reg = ModelRegistry(tmp_path / "models")
    reg.promote(ckpt, LATEST)
    assert reg.recover() == []  # a consistent registry is left alone
    (reg.root / ".v002.pt.abc123.tmp").write_bytes(b"half a checkpoint")
    reg.latest_path.write_bytes(b"stale copy")
    reg.audit_path.write_text("")  # the audit line of the last move never made it
    done = reg.recover()
    assert done == [
        "removed .v002.pt.abc123.tmp",
        "audit line for latest -> v001",
        "latest.pt re-copied from v001",
    ]
    registry_consistent(reg.root, settled=True)
    assert reg.recover() == []


# ---------------------------------------------------------------------------------------------------
# Garbage on every topic each service subscribes to


def wrong_schema(topic_model: type[Message]) -> list[bytes]:
    """Valid msgpack envelopes that are not a valid message of the topic's model."""
    telemetry = TelemetryEvent(key="x", value=1.0, step=0, timestamp=1.0)
    other = (
        encode(telemetry)
        if topic_model is not TelemetryEvent
        else encode(RobotPose(env_id=0, x=0, y=0, z=0, roll=0, pitch=0, yaw=0, timestamp=0))
    )
    import msgpack

    name = topic_model.__name__
    bad_version = msgpack.packb({"type": name, "v": 999, "data": {}})
    missing_fields = msgpack.packb({"type": name, "v": topic_model.schema_version_of(), "data": {}})
    return [other, bad_version, missing_fields]


GARBAGE = 20
"""Random byte payloads per topic (seeded), on top of the three wrong-schema messages."""


def garbage(seed: int) -> list[bytes]:
    rng = random.Random(seed)
    return [bytes(rng.randrange(256) for _ in range(rng.randrange(1, 512))) for _ in range(GARBAGE)]


def test_garbage_on_every_subscribed_topic_is_counted_and_nothing_crashes(
    services: Services, tmp_path: Path
) -> None:
    from navi_env.corpus.folder import build_corpus
    from navi_learner.envs.toy import ToyEnv
    from navi_learner.ppo.train import train

    corpus = tmp_path / "corpus"
    build_corpus([source_mesh(tmp_path)], corpus, resolution=64)
    cfg = TrainConfig(n_actors=2, rollout_length=8, total_steps=16, device="cpu", seed=0,
                      engine=EngineConfig(temporal_core="gru"))  # fmt: skip
    model = train(ToyEnv(2), cfg, run_dir=tmp_path / "run", progress=False).final_checkpoint
    token = "garbage-token"
    services.env.update({"NAVI_API_TOKEN": token, "NAVI_AZIMUTH_BINS": "32", "NAVI_ELEVATION_BINS": "8"})
    services.start("router", "serve", "router")
    learner_port = services.reserve_port()  # `--port 0` means no control plane to the learner
    svc: dict[str, Service] = {
        "compiler": services.start("compiler", "serve", "compiler", "--metrics-port", "0"),
        "env": services.start("env", "serve", "env", "--corpus", str(corpus), "--actors", "2", "--device", "cpu",
                              "--metrics-port", "0"),
        "learner": services.start("learner", "serve", "learner", "--mode", "infer", "--env", "toy", "--actors", "2",
                                  "--model", str(model), "--device", "cpu", "--port", str(learner_port)),
        "auditor": services.start("auditor", "serve", "auditor", "--port", "0"),
    }  # fmt: skip
    ports = {
        "compiler": svc["compiler"].metrics_port("compiler"),
        "env": svc["env"].metrics_port("env"),
        "learner": learner_port,
        "auditor": int(svc["auditor"].logged(r"auditor dashboard listening on http://127\.0\.0\.1:(\d+)")[1]),
    }
    sess = services.session()
    wait_for(
        lambda: {t.service for t in live_tokens(sess, timeout_s=0.5)} >= set(svc), 180.0, "every service"
    )
    metrics_url = {name: f"http://127.0.0.1:{port}/metrics" for name, port in ports.items()}
    # the learner's promotion subscriber exists once /healthz says "inference" (its token comes earlier)
    wait_for(
        lambda: (learner_health(ports["learner"]) or {}).get("phase") == "inference",
        180.0,
        "the learner's inference phase",
    )
    worker = live_tokens(sess, "compiler", 0.5)[0].instance
    subscribed = {  # service -> (topic, key it listens on, queryable?)
        "compiler": [(COMPILE_JOBS, f"{COMPILE_JOBS.key}/{worker}", True)],
        "env": [(STEP, STEP.key, True)],
        "learner": [(MODEL_PROMOTED, MODEL_PROMOTED.key, False)],
        "auditor": [(t, t.key, False) for t in (TELEMETRY, OBSERVATIONS, POSES, FLOOR_PLAN)],
    }
    sent: dict[str, int] = {}
    error_replies = 0
    for seed, topics in enumerate(subscribed.values()):
        for k, (topic, key, queryable) in enumerate(topics):
            matched(sess, key, queryable)  # the service's subscriber (queryable) is known on this path
            payloads = garbage(seed * 10 + k) + wrong_schema(topic.payload)
            for payload in payloads:
                if queryable:
                    replies = list(sess.get(key, payload=payload, timeout=60.0))
                    assert len(replies) == 1 and replies[0].err is not None, replies
                    assert "ContractError" in replies[0].err.payload.to_bytes().decode()
                    error_replies += 1
                else:
                    sess.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
            sent[topic.key] = len(payloads)

    def counted(name: str) -> dict[str, float]:
        samples = scrape(metrics_url[name])
        return {dict(labels)["topic"]: v for (metric, labels), v in samples.items()
                if metric == "navi_decode_errors_total"}  # fmt: skip

    for name, topics in subscribed.items():
        want = {topic.key: float(sent[topic.key]) for topic, _, _ in topics}
        wait_for(
            lambda n=name, w=want: {k: counted(n).get(k) for k in w} == w, 120.0, f"{name}'s decode errors"
        )
    # Nothing crashed, and every service still does its job.
    assert all(s.alive() for s in svc.values())
    job = CompileJob(job_id="after", source=str(source_mesh(tmp_path)), output=str(tmp_path / "after.gmdag"),
                     resolution=64)  # fmt: skip
    assert request(sess, f"{COMPILE_JOBS.key}/{worker}", job, CompileResult, 60.0).ok
    step = StepRequest(
        request_id="after", env_ids=np.array([0, 1], np.int32), actions=np.zeros((2, 4), np.float32)
    )
    assert request(sess, STEP.key, step, StepResult, 60.0).step_id == 1
    second = train(ToyEnv(2, seed=1), cfg, run_dir=tmp_path / "run2", progress=False).final_checkpoint
    promoted = httpx.post(f"http://127.0.0.1:{ports['learner']}/models/promote", json={"checkpoint": str(second)},
                          headers={"Authorization": f"Bearer {token}"}, timeout=60.0)  # fmt: skip
    assert promoted.status_code == 200
    wait_for(
        lambda: "champion -> v001" in svc["learner"].text(), 120.0, "the learner to follow the promotion"
    )

    def shows_a_valid_event() -> bool:
        """Telemetry is best effort (drop-oldest under load): send again on every poll."""
        sess.put(
            TELEMETRY.key,
            encode(TelemetryEvent(key="actor.training.actors", value=7.0, step=1, timestamp=time.time())),
        )
        return bool(httpx.get(f"http://127.0.0.1:{ports['auditor']}/api/state").json()["actors"] == 7)

    wait_for(shows_a_valid_event, 120.0, "the dashboard to show a valid event after the garbage")
    assert all(s.alive() for s in svc.values())
    record("garbage", {"per_topic": sent, "topics": len(sent), "error_replies": error_replies,
                       "crashes": 0})  # fmt: skip
