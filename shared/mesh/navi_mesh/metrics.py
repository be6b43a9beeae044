"""Prometheus metrics of every Navi service: one registry, `navi_*` names, base units.

Counters end in `_total`, durations in `_seconds`, sizes in `_bytes`. Labels are low-cardinality
(topic, outcome, alias, loss name, memory kind): never an actor id.
"""

from __future__ import annotations

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
ProcessCollector(registry=REGISTRY)
PlatformCollector(registry=REGISTRY)

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


def record_gpu_memory(device: torch.device) -> None:
    """Set navi_gpu_memory_bytes from torch's allocator counters (no device synchronisation)."""
    import torch

    if device.type != "cuda":
        return
    GPU_MEMORY.labels("allocated").set(torch.cuda.memory_allocated(device))
    GPU_MEMORY.labels("reserved").set(torch.cuda.memory_reserved(device))


def exposition() -> tuple[bytes, str]:
    """The registry in the Prometheus text format and its content type."""
    return generate_latest(REGISTRY), CONTENT_TYPE_LATEST


_served: set[int] = set()
_served_lock = threading.Lock()


def serve_metrics(port: int, host: str = "127.0.0.1") -> None:
    """Expose GET /metrics on `port` from a daemon thread (services without their own HTTP API)."""
    with _served_lock:
        if port in _served:
            return
        start_http_server(port, addr=host, registry=REGISTRY)
        _served.add(port)
