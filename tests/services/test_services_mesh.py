"""navi_mesh over a real Zenoh router on loopback (in this process): QoS, decode errors, requests, liveliness."""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

import numpy as np
import pytest
import zenoh
from services_testlib import (
    ReservedPort,
    Service,
    client_session,
    connected_routers,
    loopback_router,
    matched,
    wait_for,
)

from navi_contracts.codec import encode
from navi_contracts.models import CompileJob, CompileResult, Message, StepRequest, TelemetryEvent
from navi_contracts.topics import ALL_TOPICS, COMPILE_JOBS, STEP, TELEMETRY, Topic
from navi_mesh import metrics
from navi_mesh.liveliness import declare_alive, live_tokens, parse_token
from navi_mesh.messages import telemetry
from navi_mesh.pubsub import NoReplyError, QueuedPublisher, RequestError, RequestQueue, request, subscribe
from navi_mesh.session import (
    MeshError,
    SessionConfig,
    config_json,
    open_new_session,
    router_locators,
    zenoh_config,
)

R = TypeVar("R")

pytestmark = pytest.mark.integration


@pytest.fixture
def mesh() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    """A router on a port the OS picks (read back from its admin space) and two client sessions to it."""
    with loopback_router() as endpoint:
        a, b = client_session(endpoint), client_session(endpoint)
        try:
            yield a, b
        finally:
            for s in (a, b):
                s.close()


def counter(metric: object, topic: str) -> float:
    value = metrics.REGISTRY.get_sample_value(f"{metric}_total", {"topic": topic})
    return 0.0 if value is None else value


def test_client_config_is_explicit_and_waits_for_the_router() -> None:
    cfg = config_json(SessionConfig(connect=("tcp/10.0.0.1:7447",)))
    assert cfg["mode"] == "client"
    assert cfg["scouting"] == {"multicast": {"enabled": False}, "gossip": {"enabled": False}}
    connect = cfg["connect"]
    assert isinstance(connect, dict)
    assert connect["endpoints"] == ["tcp/10.0.0.1:7447"] and connect["timeout_ms"] == -1
    assert connect["exit_on_failure"] is False
    zenoh_config(SessionConfig())  # a valid zenoh.Config


def test_json5_file_is_used_as_is(tmp_path: Path) -> None:
    path = tmp_path / "z.json5"
    path.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7999"] } }')
    cfg = zenoh_config(SessionConfig(config_file=path))
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7999"]
    with pytest.raises(MeshError):
        zenoh_config(SessionConfig(config_file=tmp_path / "missing.json5"))


def test_a_router_on_port_0_listens_where_it_says(tmp_path: Path) -> None:
    """`tcp/127.0.0.1:0`: the OS picks the port; the router's admin space names it and a client reaches
    it there. `navi serve router` logs the bound endpoint, not the `:0` it was given."""
    router = open_new_session(SessionConfig(mode="router", connect=(), listen=("tcp/127.0.0.1:0",)))
    try:
        (endpoint,) = router_locators(router)
        assert re.fullmatch(r"tcp/127\.0\.0\.1:[1-9]\d*", endpoint), endpoint
        client = open_new_session(SessionConfig(connect=(endpoint,), connect_timeout_s=30.0))
        assert connected_routers(client) == 1
        client.close()
    finally:
        router.close()
    served = Service("router", ["serve", "router", "--listen", "tcp/127.0.0.1:0"], tmp_path, dict(os.environ))
    try:
        logged = served.logged(r"zenoh router \w+ listening on (tcp/127\.0\.0\.1:\d+)")[1]
        assert not logged.endswith(":0"), f"the router logged {logged}, not the port it bound"
        client = open_new_session(SessionConfig(connect=(logged,), connect_timeout_s=30.0))
        assert connected_routers(client) == 1
        client.close()
    finally:
        served.stop(signal.SIGKILL)


def test_no_router_before_the_deadline_is_a_mesh_error() -> None:
    with ReservedPort() as nobody, ThreadPoolExecutor(1) as pool:  # bound, never listening: refused
        attempt = pool.submit(
            open_new_session, SessionConfig(connect=(f"tcp/127.0.0.1:{nobody.port}",), connect_timeout_s=0.5)
        )
        with pytest.raises(MeshError):
            attempt.result(timeout=120.0)  # a hang bound: the deadline is 0.5 s


def test_malformed_payloads_on_every_topic_are_counted_and_dropped(
    mesh: tuple[zenoh.Session, zenoh.Session],
) -> None:
    pub, sub = mesh
    received: dict[str, list[Message]] = {t.key: [] for t in ALL_TOPICS}
    subscribers = []
    queues: list[RequestQueue[Message]] = []
    for topic in ALL_TOPICS:
        if topic.reply is None:
            subscribers.append(subscribe(sub, topic, received[topic.key].append))
        else:
            queues.append(RequestQueue(sub, topic))
    for topic in ALL_TOPICS:
        matched(pub, topic.key, queryable=topic.reply is not None)
    before = {t.key: counter("navi_decode_errors", t.key) for t in ALL_TOPICS}
    wrong_model = encode(TelemetryEvent(key="x", value=1.0, step=0, timestamp=1.0))
    for topic in ALL_TOPICS:
        bad = [b"\xc1garbage", b"", wrong_model if topic is not TELEMETRY else encode(_compile_job())]
        for payload in bad:
            if topic.reply is None:
                pub.put(topic.key, payload)
            else:
                with pytest.raises(RequestError, match="ContractError"):
                    request_raw(pub, topic, payload)
    # A valid telemetry event after the garbage still arrives: the subscriber lives on.
    good = telemetry("actor.training.sps", 12.5, 7)
    pub.put(TELEMETRY.key, encode(good))
    wait_for(lambda: len(received[TELEMETRY.key]) == 1, 60.0, "the valid telemetry event")
    wait_for(
        lambda: all(counter("navi_decode_errors", t.key) - before[t.key] == 3 for t in ALL_TOPICS),
        60.0,
        "three decode errors counted per topic",
    )
    assert received[TELEMETRY.key][0] == good
    assert all(not v for k, v in received.items() if k != TELEMETRY.key)
    assert all(q.pending() == 0 for q in queues)


def request_raw(sess: zenoh.Session, topic: Topic, payload: bytes) -> None:
    """Send raw bytes to a queryable; raise RequestError on an error reply."""
    for reply in sess.get(topic.key, payload=payload, timeout=60.0):
        if reply.err is not None:
            raise RequestError(reply.err.payload.to_bytes().decode())


def _compile_job(job_id: str = "j1") -> CompileJob:
    return CompileJob(job_id=job_id, source="scene.obj", output="out.gmdag", resolution=64)


def test_queued_publisher_never_waits_and_drops_the_oldest(mesh: tuple[zenoh.Session, zenoh.Session]) -> None:
    pub_sess, sub_sess = mesh
    got: list[TelemetryEvent] = []
    sub = subscribe(sub_sess, TELEMETRY, got.append)
    matched(pub_sess, TELEMETRY.key)
    pub: QueuedPublisher[TelemetryEvent] = QueuedPublisher(pub_sess, TELEMETRY, capacity=4)
    n = 5000
    # The queue's lock (re-entrant) held here stalls the sending thread: every publish() returns without
    # it, and only the newest `capacity` events are left when it may send again.
    with pub._cond:
        for i in range(n):
            pub.publish(telemetry("actor.training.step", float(i), i))
        assert (pub.sent, pub.dropped) == (0, n - 4)
    assert pub.flush(60.0)
    assert (pub.sent, pub.dropped) == (4, n - 4)
    wait_for(lambda: len(got) >= 4, 60.0, "the four newest events")
    assert [e.step for e in got] == list(range(n - 4, n))  # the newest kept, in order
    pub.close()
    sub.undeclare()


def test_request_reply_with_progress_and_typed_errors(mesh: tuple[zenoh.Session, zenoh.Session]) -> None:
    client, server = mesh
    jobs: RequestQueue[CompileJob] = RequestQueue(server, COMPILE_JOBS, key=f"{COMPILE_JOBS.key}/w1")
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            item = jobs.get(0.1)
            if item is None:
                continue
            for frac in (0.25, 0.5):
                item.progress(telemetry("compiler.progress.sdf", frac, 0, item.message.job_id))
            item.reply(
                CompileResult(job_id=item.message.job_id, ok=True, output="out.gmdag", stats={"x": 1.0})
            )

    worker = threading.Thread(target=serve, daemon=True)
    worker.start()
    seen: list[float] = []
    result = _once_heard(
        lambda: request(
            client,
            f"{COMPILE_JOBS.key}/w1",
            _compile_job(),
            CompileResult,
            60.0,
            lambda e: seen.append(e.value),
        )
    )
    assert result.ok and result.output == "out.gmdag" and result.stats == {"x": 1.0}
    assert seen == [0.25, 0.5]
    with pytest.raises(RequestError, match="without a reply"):
        request(client, f"{COMPILE_JOBS.key}/nobody", _compile_job(), CompileResult, 0.5)
    stop.set()
    worker.join(2.0)
    jobs.close()


def test_step_request_queue_refuses_when_full(mesh: tuple[zenoh.Session, zenoh.Session]) -> None:
    client, server = mesh
    steps: RequestQueue[StepRequest] = RequestQueue(server, STEP, capacity=1)
    req = StepRequest(request_id="r", env_ids=np.zeros(1, np.int32), actions=np.zeros((1, 4), np.float32))
    first = threading.Thread(target=lambda: _swallow(client, req), daemon=True)
    first.start()
    wait_for(lambda: steps.pending() == 1, 30.0, "the first request queued")  # a loaded 2-core host
    with pytest.raises(RequestError, match="Busy"):
        request(client, STEP.key, req, CompileResult, 60.0)
    item = steps.get(1.0)
    assert item is not None and item.message.request_id == "r"
    item.fail("StepError: test")
    first.join(30.0)
    steps.close()


def _swallow(sess: zenoh.Session, req: StepRequest) -> None:
    """Sends `req` and expects the error the test answers it with (its timeout outlasts the test's waits)."""
    with pytest.raises(RequestError, match="StepError"):
        _once_heard(lambda: request(sess, STEP.key, req, CompileResult, 60.0))


def _once_heard(send: Callable[[], R], timeout_s: float = 30.0) -> R:
    """`send()` again while its query ends at once without a reply: the router has not yet told the client
    of the queryable just declared (a race on a loaded host), so the query matched nobody."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return send()
        except NoReplyError as e:
            if "without a reply" not in str(e) or time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def test_liveliness_tokens_come_and_go(mesh: tuple[zenoh.Session, zenoh.Session]) -> None:
    a, b = mesh
    token = declare_alive(a, "compiler", "host-1")
    wait_for(
        lambda: [t.key for t in live_tokens(b, timeout_s=0.5)] == ["navi/alive/compiler/host-1"],
        60.0,
        "token",
    )
    token.undeclare()
    wait_for(lambda: not live_tokens(b, timeout_s=0.5), 60.0, "the token to disappear")
    assert parse_token("navi/alive/env/x") is not None and parse_token("navi/alive/env") is None


def test_metrics_on_port_0_are_served_on_the_port_logged(caplog: pytest.LogCaptureFixture) -> None:
    """`--metrics-port 0`: the OS picks the port, the service logs it, and GET /metrics answers there."""
    with caplog.at_level(logging.INFO, logger="navi_mesh.metrics"):
        port = metrics.serve_metrics(0, "auditor")
    assert port > 0 and f"GET /metrics of auditor on http://127.0.0.1:{port}/metrics" in caplog.text
    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=60).read().decode()
    assert "navi_decode_errors_total" in text and "navi_compile_jobs_total" not in text  # the auditor's page
    assert metrics.serve_metrics(0, "auditor") == port  # served once


def test_each_service_exports_the_mesh_families_and_its_own_only() -> None:
    """A service's /metrics holds the mesh families (every service talks on the mesh) and the families it
    owns, none of another service's: no learner gauge reads 0 on a compiler's page."""
    from prometheus_client.parser import text_string_to_metric_families

    def families(collectors: tuple[object, ...]) -> set[str]:
        return {f.name for c in collectors for f in c.describe()}  # type: ignore[attr-defined]

    mesh_families = families(metrics.MESH)
    assert mesh_families == {
        "navi_published_messages", "navi_received_messages", "navi_decode_errors", "navi_dropped_messages",
        "navi_handler_errors",
    }  # fmt: skip
    every = set()
    for service, owned in metrics.OWNERS.items():
        text = metrics.exposition(service)[0].decode()
        served = {f.name for f in text_string_to_metric_families(text) if f.name.startswith("navi_")}
        assert served == mesh_families | families(owned), service
        assert "process_cpu_seconds" in text  # and its own process
        every |= served
    assert every == {f.name for f in metrics.REGISTRY.collect() if f.name.startswith("navi_")}
    for learner_only in ("navi_reward_ema", "navi_corpus_scenes_ready", "navi_loss", "navi_promotions"):
        owners = [s for s in metrics.OWNERS if learner_only in families(metrics.OWNERS[s])]
        assert owners == ["learner"], learner_only
    with pytest.raises(ValueError, match="unknown service"):
        metrics.registry("router")
