"""Faults, measured (docs/SERVICES.md "Faults" takes its numbers from these tests):

- kill -9 of a compile worker mid-job: the job goes to the other worker and finishes; no partial file;
- kill -9 of the learner while it writes a checkpoint or the registry: every .pt file in the run and
  registry folders loads with torch.load(weights_only=True), the registry index is consistent, and
  the next start brings the audit log and latest.pt back in line;
- random bytes and wrong-schema messages on every topic each running service subscribes to: no
  crash, each counted in navi_decode_errors_total{topic}, and the service still serves.
Each measured number is printed as `FAULT <name> <json>`.
"""

from __future__ import annotations

import json
import os
import random
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
from services_testlib import Service, Services, free_port, wait_for

from navi_contracts.codec import encode
from navi_contracts.models import (
    CompileJob,
    CompileResult,
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
    from navi_compiler.service import BUSY_PREFIX
    from navi_env.corpus.jobs import CorpusBuildConfig, compile_with_retries

    services.start("router", "serve", "router")
    workers = {
        name: services.start(name, "serve", "compiler", "--metrics-port", str(free_port()))
        for name in ("compiler-a", "compiler-b")
    }
    sess = services.session()
    wait_for(lambda: len(live_tokens(sess, "compiler", 0.5)) == 2, 60.0, "two compiler processes")
    pid_of = {t.instance: svc for t in live_tokens(sess, "compiler", 0.5) for svc in workers.values()
              if t.instance.endswith(f"-{svc.proc.pid}-w0")}  # fmt: skip
    assert len(pid_of) == 2
    src, out = source_mesh(tmp_path), tmp_path / "out" / "scene.gmdag"
    retries: list[tuple[float, str]] = []
    outcome: list[str] = []
    cfg = CorpusBuildConfig(out.parent, resolution=512, attempts=3, job_timeout_s=300.0)
    stop = threading.Event()

    def run() -> None:
        outcome.append(
            compile_with_retries(sess, src, out, cfg, stop, lambda e: retries.append((time.monotonic(), e)))
        )

    client = threading.Thread(target=run)
    t_start = time.monotonic()
    client.start()
    wait_for(lambda: bool(live_tokens(sess, "compiler", 0.5, prefix=BUSY_PREFIX)), 60.0, "a busy worker")
    busy = live_tokens(sess, "compiler", 0.5, prefix=BUSY_PREFIX)[0].instance
    victim = pid_of[busy]
    t_kill = time.monotonic()
    victim.stop(signal.SIGKILL)
    assert not out.exists()  # nothing was written by the killed worker
    client.join(300.0)
    assert not client.is_alive() and outcome == [""], outcome
    assert len(retries) == 1 and "died" in retries[0][1], retries
    detected_s = retries[0][0] - t_kill
    read_gmdag(out)  # the retried job's file is complete and valid
    assert sorted(p.name for p in out.parent.iterdir()) == ["scene.gmdag"]  # no partial or temp file
    survivor = next(svc for svc in workers.values() if svc is not victim)
    assert survivor.alive()
    record(
        "compile_worker_kill",
        {"retries": len(retries), "detected_after_s": round(detected_s, 2),
         "job_total_s": round(time.monotonic() - t_start, 1), "partial_files": 0},
    )  # fmt: skip
    assert detected_s < 10.0  # the client sees the worker's token vanish (WORKER_GONE_GRACE_S = 5 s)


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
    caught: list[dict[str, Any]] = []
    attempts = 0

    def mid_checkpoint() -> bool:
        return any(name.startswith(".ckpt_step_") for c in caught for name in c["partial"])

    def mid_registry() -> bool:
        return any(not name.startswith(".ckpt_step_") for c in caught for name in c["partial"])

    while attempts < 8 and not (mid_checkpoint() and mid_registry()):
        attempts += 1
        # Odd tries aim at a checkpoint write, even ones at a registry write (the promoter below).
        aim_checkpoint = attempts % 2 == 1 or mid_registry()
        aim_registry = not aim_checkpoint or mid_checkpoint()
        api = free_port()
        stale = set(temp_files(*runs.glob("*/checkpoints"), models))  # left by an earlier kill
        learner = services.start(
            f"learner{attempts}", "serve", "learner", "--env", "toy", "--actors", str(actors),
            "--temporal-core", "gru", "--rollout-length", str(rollout), "--total-steps", "100000000",
            "--checkpoint-every", str(actors * rollout), "--device", "cpu", "--port", str(api),
        )  # fmt: skip
        wait_for(lambda port=api: learner_up(port), 60.0, "the learner's control plane")  # type: ignore[misc]
        stop_promoting = threading.Event()
        promoter = threading.Thread(
            target=promote_forever, args=(api, token, runs, stop_promoting), daemon=True
        )
        promoter.start()
        wait_for(lambda: (models / "registry.json").is_file(), 30.0, "a first promotion")
        # Kill -9 the moment a temporary file of an atomic write exists (a checkpoint or a registry file).
        deadline = time.monotonic() + 30.0
        seen: list[Path] = []
        watched = [
            *(runs.glob("*/checkpoints") if aim_checkpoint else []),
            *([models] if aim_registry else []),
        ]
        while time.monotonic() < deadline and not seen:
            seen = [p for p in temp_files(*watched) if p not in stale]
            if not seen and aim_checkpoint:
                watched = [*runs.glob("*/checkpoints"), *([models] if aim_registry else [])]
        learner.proc.send_signal(signal.SIGKILL)
        learner.proc.wait(10)
        stop_promoting.set()
        promoter.join(10.0)
        left = [p for p in temp_files(*runs.glob("*/checkpoints"), models) if p not in stale]
        if left:  # the process died with the write unfinished: a true mid-write kill
            caught.append({"partial": sorted(p.name.split(".tmp")[0] for p in left)})
        # Whatever was caught, every file that is a checkpoint loads and the index holds.
        loaded = every_pt_loads(runs, models)
        counts = registry_consistent(models, settled=False) if (models / "registry.json").exists() else {}
        if left:
            caught[-1].update(loaded=loaded, **counts)
    assert mid_checkpoint() and mid_registry(), f"kills inside a checkpoint and a registry write: {caught}"
    # The next start recovers the registry: temporary files gone, audit and latest.pt agree with the index.
    api = free_port()
    learner = services.start("learner-after", "serve", "learner", "--env", "toy", "--actors", str(actors),
                             "--temporal-core", "gru", "--rollout-length", str(rollout), "--total-steps",
                             str(actors * rollout), "--device", "cpu", "--port", str(api))  # fmt: skip
    wait_for(lambda: learner_up(api), 60.0, "the learner after the kills")
    settled = registry_consistent(models, settled=True)
    loaded = every_pt_loads(runs, models)
    assert learner.stop(signal.SIGTERM) == 0
    record("learner_kill_mid_write", {"kills": attempts, "caught_mid_write": caught, "pt_files_loaded": loaded,
                                      "registry_versions": settled["versions"],
                                      "mid_registry_write": mid_registry()})  # fmt: skip


def learner_health(port: int) -> dict[str, Any] | None:
    """The learner's /healthz body, or None while it does not answer 200."""
    try:
        reply = httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1.0)
        return reply.json() if reply.status_code == 200 else None
    except (httpx.HTTPError, ValueError):
        return None


def learner_up(port: int) -> bool:
    return learner_health(port) is not None


def promote_forever(port: int, token: str, runs: Path, stop: threading.Event) -> None:
    """Promote the newest checkpoint again and again (registry writes) until stopped or refused."""
    headers = {"Authorization": f"Bearer {token}"}
    while not stop.is_set():
        newest = sorted(runs.glob("*/checkpoints/ckpt_step_*.pt"))
        if not newest:
            time.sleep(0.01)
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


def wrong_schema(topic_model: type) -> list[bytes]:
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
    ports = {name: free_port() for name in ("compiler", "env", "learner", "auditor")}
    svc: dict[str, Service] = {
        "compiler": services.start("compiler", "serve", "compiler", "--metrics-port", str(ports["compiler"])),
        "env": services.start("env", "serve", "env", "--corpus", str(corpus), "--actors", "2", "--device", "cpu",
                              "--metrics-port", str(ports["env"])),
        "learner": services.start("learner", "serve", "learner", "--mode", "infer", "--env", "toy", "--actors", "2",
                                  "--model", str(model), "--device", "cpu", "--port", str(ports["learner"])),
        "auditor": services.start("auditor", "serve", "auditor", "--port", str(ports["auditor"])),
    }  # fmt: skip
    sess = services.session()
    wait_for(lambda: {t.service for t in live_tokens(sess, timeout_s=0.5)} >= set(svc), 90.0, "every service")
    metrics_url = {
        "compiler": f"http://127.0.0.1:{ports['compiler']}/metrics",
        "env": f"http://127.0.0.1:{ports['env']}/metrics",
        "learner": f"http://127.0.0.1:{ports['learner']}/metrics",
        "auditor": f"http://127.0.0.1:{ports['auditor']}/metrics",
    }
    # the learner's promotion subscriber exists once /healthz says "inference" (its token comes earlier)
    wait_for(
        lambda: (learner_health(ports["learner"]) or {}).get("phase") == "inference",
        90.0,
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
            payloads = garbage(seed * 10 + k) + wrong_schema(topic.payload)
            for payload in payloads:
                if queryable:
                    for reply in sess.get(key, payload=payload, timeout=5.0):
                        assert (
                            reply.err is not None and "ContractError" in reply.err.payload.to_bytes().decode()
                        )
                        error_replies += 1
                else:
                    sess.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
                    time.sleep(0.005)
            sent[topic.key] = len(payloads)

    def counted(name: str) -> dict[str, float]:
        samples = scrape(metrics_url[name])
        return {dict(labels)["topic"]: v for (metric, labels), v in samples.items()
                if metric == "navi_decode_errors_total"}  # fmt: skip

    for name, topics in subscribed.items():
        want = {topic.key: float(sent[topic.key]) for topic, _, _ in topics}
        wait_for(
            lambda n=name, w=want: {k: counted(n).get(k) for k in w} == w, 15.0, f"{name}'s decode errors"
        )  # type: ignore[misc]
    # Nothing crashed, and every service still does its job.
    assert all(s.alive() for s in svc.values())
    job = CompileJob(job_id="after", source=str(source_mesh(tmp_path)), output=str(tmp_path / "after.gmdag"),
                     resolution=64)  # fmt: skip
    assert request(sess, f"{COMPILE_JOBS.key}/{worker}", job, CompileResult, 60.0).ok
    step = StepRequest(
        request_id="after", env_ids=np.array([0, 1], np.int32), actions=np.zeros((2, 4), np.float32)
    )
    assert request(sess, STEP.key, step, StepResult, 30.0).step_id == 1
    second = train(ToyEnv(2, seed=1), cfg, run_dir=tmp_path / "run2", progress=False).final_checkpoint
    promoted = httpx.post(f"http://127.0.0.1:{ports['learner']}/models/promote", json={"checkpoint": str(second)},
                          headers={"Authorization": f"Bearer {token}"})  # fmt: skip
    assert promoted.status_code == 200
    wait_for(lambda: "champion -> v001" in svc["learner"].text(), 30.0, "the learner to follow the promotion")

    def shows_a_valid_event() -> bool:
        """Telemetry is best effort (drop-oldest under load): send again on every poll."""
        sess.put(
            TELEMETRY.key,
            encode(TelemetryEvent(key="actor.training.actors", value=7.0, step=1, timestamp=time.time())),
        )
        return bool(httpx.get(f"http://127.0.0.1:{ports['auditor']}/api/state").json()["actors"] == 7)

    wait_for(shows_a_valid_event, 30.0, "the dashboard to show a valid event after the garbage")
    assert all(s.alive() for s in svc.values())
    record("garbage", {"per_topic": sent, "topics": len(sent), "error_replies": error_replies,
                       "crashes": 0})  # fmt: skip
