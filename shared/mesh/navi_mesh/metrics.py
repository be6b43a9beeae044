"""Prometheus metrics of the Navi services: `navi_*` names, base units, each family exported by the
service that owns it.

Every service exports the mesh families (messages published, received, dropped, undecodable, failed in
a handler; per topic) and its own (`OWNERS`): a compiler worker its compile jobs, the env service its
step requests, the learner training, promotion and corpus progress. `registry(service)` is what a
service's GET /metrics serves; `REGISTRY` holds every family, for readers inside one process (tests).

Counters end in `_total`, durations in `_seconds`, sizes in `_bytes`. Labels are low-cardinality
(topic, outcome, alias, loss name, memory kind): never an actor id.
"""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    disable_created_metrics,
    generate_latest,
    start_http_server,
)
from prometheus_client.platform_collector import PlatformCollector
from prometheus_client.process_collector import ProcessCollector

if TYPE_CHECKING:
    import torch

disable_created_metrics()
REGISTRY = CollectorRegistry()
"""Every family below (the union of the services' registries), for in-process readers."""
_served: dict[tuple[int, str], int] = {}
"""(requested /metrics port, service when the port is 0) -> the port bound for it (0: one the OS picks)."""
_served_lock = threading.Lock()

STEPS_PER_SECOND = Gauge(
    "navi_steps_per_second",
    "Environment steps (all actors) per second over the last window.",
    ["mode"],
    registry=REGISTRY,
)
STEPS = Counter("navi_steps", "Environment steps taken (actor-steps).", ["mode"], registry=REGISTRY)
EPISODES = Counter("navi_episodes", "Episodes finished.", ["mode"], registry=REGISTRY)
REWARD_EMA = Gauge(
    "navi_reward_ema", "Exponential moving average of the reward per actor-step.", registry=REGISTRY
)
LOSS = Gauge(
    "navi_loss",
    "Last PPO update's losses by name (policy, value, entropy, rnd, ...).",
    ["name"],
    registry=REGISTRY,
)
GPU_MEMORY = Gauge(
    "navi_gpu_memory_bytes",
    "CUDA memory of this process by kind (allocated, reserved).",
    ["kind"],
    registry=REGISTRY,
)
COMPILE_JOBS = Counter(
    "navi_compile_jobs", "Compile jobs finished by outcome (ok, error).", ["outcome"], registry=REGISTRY
)
COMPILE_DURATION = Histogram(
    "navi_compile_duration_seconds",
    "Wall time of compile jobs.",
    buckets=(0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0),
    registry=REGISTRY,
)
DECODE_ERRORS = Counter(
    "navi_decode_errors",
    "Payloads that failed to decode and were dropped, per topic.",
    ["topic"],
    registry=REGISTRY,
)
DROPPED_MESSAGES = Counter(
    "navi_dropped_messages", "Messages dropped by a publisher queue, per topic.", ["topic"], registry=REGISTRY
)
PUBLISHED_MESSAGES = Counter(
    "navi_published_messages", "Messages handed to Zenoh, per topic.", ["topic"], registry=REGISTRY
)
RECEIVED_MESSAGES = Counter(
    "navi_received_messages", "Messages received and decoded, per topic.", ["topic"], registry=REGISTRY
)
HANDLER_ERRORS = Counter(
    "navi_handler_errors", "Decoded messages whose handler raised, per topic.", ["topic"], registry=REGISTRY
)
PROMOTIONS = Counter(
    "navi_promotions",
    "Alias moves through the control plane (promote, rollback).",
    ["action"],
    registry=REGISTRY,
)
REFUSED_REQUESTS = Counter(
    "navi_refused_requests",
    "REST requests the control plane refused, by HTTP status (401, 403, 404, 409, 413, 422, ...).",
    ["status"],
    registry=REGISTRY,
)
STEP_REQUESTS = Counter(
    "navi_step_requests",
    "StepRequests answered by the env service by outcome.",
    ["outcome"],
    registry=REGISTRY,
)
PUBLISH_SECONDS = Counter(
    "navi_publish_seconds",
    "Time the training or inference loop spent handing messages to the publishers.",
    registry=REGISTRY,
)

CORPUS_SCENES_READY = Gauge(
    "navi_corpus_scenes_ready",
    "Scenes of the service's corpus compiled and qualified (all of them once the corpus is ready).",
    registry=REGISTRY,
)
CORPUS_SCENES_PLANNED = Gauge(
    "navi_corpus_scenes_planned",
    "Scenes the corpus build makes (the corpus size once it is ready; 0 while unknown).",
    registry=REGISTRY,
)
CORPUS_SCENES_REJECTED = Gauge(
    "navi_corpus_scenes_rejected",
    "Scenes of the corpus build rejected by spawn qualification.",
    registry=REGISTRY,
)
CORPUS_READY = Gauge(
    "navi_corpus_ready", "1 once the service's corpus is built and loaded, else 0.", registry=REGISTRY
)
WRITE_ERRORS = Counter(
    "navi_write_errors",
    "Writes that failed (a full disk, an I/O error) and left the last good file in place, by what was "
    "written (checkpoint, registry, recording).",
    ["what"],
    registry=REGISTRY,
)


MESH: tuple[Counter, ...] = (
    PUBLISHED_MESSAGES,
    RECEIVED_MESSAGES,
    DECODE_ERRORS,
    DROPPED_MESSAGES,
    HANDLER_ERRORS,
)
"""The families every service exports: its traffic on the mesh."""
OWNERS: dict[str, tuple[Counter | Gauge | Histogram, ...]] = {
    "compiler": (COMPILE_JOBS, COMPILE_DURATION),
    "env": (STEPS, EPISODES, STEP_REQUESTS),
    "learner": (
        STEPS_PER_SECOND,
        STEPS,
        EPISODES,
        REWARD_EMA,
        LOSS,
        GPU_MEMORY,
        PUBLISH_SECONDS,
        PROMOTIONS,
        REFUSED_REQUESTS,
        CORPUS_SCENES_READY,
        CORPUS_SCENES_PLANNED,
        CORPUS_SCENES_REJECTED,
        CORPUS_READY,
        WRITE_ERRORS,
    ),
    "auditor": (WRITE_ERRORS,),
}
"""The families each service owns, besides MESH."""
_registries: dict[str, CollectorRegistry] = {}


def registry(service: str) -> CollectorRegistry:
    """The registry a service's GET /metrics serves: its process, the mesh families and its own."""
    if service not in OWNERS:
        raise ValueError(f"unknown service {service!r}; one of {', '.join(OWNERS)}")
    with _served_lock:
        if service not in _registries:
            reg = CollectorRegistry()
            ProcessCollector(registry=reg)
            PlatformCollector(registry=reg)
            for family in (*MESH, *OWNERS[service]):
                reg.register(family)
            _registries[service] = reg
        return _registries[service]


def record_gpu_memory(device: torch.device) -> None:
    """Set navi_gpu_memory_bytes from torch's allocator counters (no device synchronisation)."""
    import torch

    if device.type != "cuda":
        return
    GPU_MEMORY.labels("allocated").set(torch.cuda.memory_allocated(device))
    GPU_MEMORY.labels("reserved").set(torch.cuda.memory_reserved(device))


def exposition(service: str) -> tuple[bytes, str]:
    """A service's registry in the Prometheus text format, and its content type."""
    return generate_latest(registry(service)), CONTENT_TYPE_LATEST


def serve_metrics(port: int, service: str, host: str = "127.0.0.1") -> int:
    """Expose a service's GET /metrics on `port` (0: one the OS picks) from a daemon thread (services
    without an HTTP API); logs the address and returns the bound port. A second call for the same
    requested port (and service, for port 0) serves nothing more and returns the same bound port."""
    served = registry(service)
    key = (port, service if port == 0 else "")
    with _served_lock:
        if key not in _served:
            server, _ = start_http_server(port, addr=host, registry=served)
            _served[key] = int(server.server_address[1])
            logging.getLogger("navi_mesh.metrics").info(
                "GET /metrics of %s on http://%s:%d/metrics", service, host, _served[key]
            )
        return _served[key]
