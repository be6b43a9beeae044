"""Typed publishers, subscribers, queryables and requests over the navi_contracts codec.

- `Publisher`: sends in the caller's thread with the topic's QoS (reliable + block for compile jobs,
  step requests and promotions).
- `QueuedPublisher`: best-effort streams (telemetry, observations, actions). `publish` only appends
  to a bounded drop-oldest queue; a daemon thread encodes and sends, so the caller never waits on
  the network. Every dropped message is counted.
- `subscribe`: decodes every sample; a payload that fails to decode is dropped, counted
  (navi_decode_errors_total) and logged, and the subscriber keeps running.
- `RequestQueue` (a queryable feeding a queue the service drains at its own pace) and `request`
  (the client side). A reply carries attachment `result`, `progress` (a TelemetryEvent) or is an
  error reply.
"""

from __future__ import annotations

import collections
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

import zenoh

from navi_contracts.codec import ContractError, decode, encode
from navi_contracts.models import Message, TelemetryEvent
from navi_contracts.topics import Topic
from navi_mesh import metrics

log = logging.getLogger("navi_mesh")

M = TypeVar("M", bound=Message)
R = TypeVar("R", bound=Message)

RESULT = b"result"
PROGRESS = b"progress"

LOG_FIRST_ERRORS = 10
"""Decode errors logged one by one per topic; after that, one line every LOG_EVERY_ERRORS."""
LOG_EVERY_ERRORS = 100


def _qos(topic: Topic) -> tuple[zenoh.Reliability, zenoh.CongestionControl]:
    reliability = (
        zenoh.Reliability.RELIABLE if topic.reliability == "reliable" else zenoh.Reliability.BEST_EFFORT
    )
    congestion = (
        zenoh.CongestionControl.BLOCK if topic.congestion == "block" else zenoh.CongestionControl.DROP
    )
    return reliability, congestion


class _ErrorLog:
    """Counts decode errors per topic and logs them without flooding the log."""

    def __init__(self) -> None:
        self.counts: collections.Counter[str] = collections.Counter()
        self.lock = threading.Lock()

    def __call__(self, topic: str, err: Exception) -> None:
        metrics.DECODE_ERRORS.labels(topic).inc()
        with self.lock:
            self.counts[topic] += 1
            n = self.counts[topic]
        if n <= LOG_FIRST_ERRORS or n % LOG_EVERY_ERRORS == 0:
            log.warning("dropped an undecodable payload on %s (%d so far): %s", topic, n, err)


decode_error = _ErrorLog()


class Publisher(Generic[M]):
    """Sends messages of one topic from the caller's thread with the topic's reliability and congestion."""

    def __init__(self, sess: zenoh.Session, topic: Topic, key: str | None = None) -> None:
        reliability, congestion = _qos(topic)
        self.topic = topic
        self.key = key or topic.key
        self._pub = sess.declare_publisher(self.key, reliability=reliability, congestion_control=congestion)

    def publish(self, message: M) -> None:
        """Encode and send (may wait for the network when the topic blocks on congestion)."""
        if not isinstance(message, self.topic.payload):
            raise TypeError(f"{self.key} carries {self.topic.payload.__name__}, got {type(message).__name__}")
        self._pub.put(encode(message))
        metrics.PUBLISHED_MESSAGES.labels(self.topic.key).inc()

    def close(self) -> None:
        self._pub.undeclare()


class QueuedPublisher(Generic[M]):
    """Best-effort publisher: a bounded drop-oldest queue drained by a daemon thread.

    `publish` costs one lock and a deque append; when the queue is full the oldest message is dropped
    and counted in navi_dropped_messages_total{topic}.
    """

    def __init__(
        self, sess: zenoh.Session, topic: Topic, capacity: int = 256, key: str | None = None
    ) -> None:
        if capacity < 1:
            raise ValueError("capacity must be >= 1")
        self.topic = topic
        self.key = key or topic.key
        self.capacity = capacity
        self.dropped = 0
        self.sent = 0
        self._items: collections.deque[M] = collections.deque()
        self._cond = threading.Condition()
        self._closed = False
        self._busy = False
        reliability, congestion = _qos(topic)
        self._pub = sess.declare_publisher(self.key, reliability=reliability, congestion_control=congestion)
        self._thread = threading.Thread(target=self._drain, name=f"publish {self.key}", daemon=True)
        self._thread.start()

    def publish(self, message: M) -> None:
        """Queue a message; never waits on the network."""
        with self._cond:
            if self._closed:
                return
            if len(self._items) >= self.capacity:
                self._items.popleft()
                self.dropped += 1
                metrics.DROPPED_MESSAGES.labels(self.topic.key).inc()
            self._items.append(message)
            self._cond.notify()

    def _drain(self) -> None:
        while True:
            with self._cond:
                while not self._items and not self._closed:
                    self._cond.wait()
                if not self._items:
                    return
                message = self._items.popleft()
                self._busy = True
            try:
                self._pub.put(encode(message))
                self.sent += 1
                metrics.PUBLISHED_MESSAGES.labels(self.topic.key).inc()
            except (ContractError, zenoh.ZError) as err:
                self.dropped += 1
                metrics.DROPPED_MESSAGES.labels(self.topic.key).inc()
                log.warning("could not publish on %s: %s", self.key, err)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def flush(self, timeout_s: float = 5.0) -> bool:
        """Wait until the queue is empty and the last message was handed to Zenoh."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._items or self._busy:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def close(self, timeout_s: float = 2.0) -> None:
        """Send what is queued (up to timeout_s), stop the thread, undeclare."""
        self.flush(timeout_s)
        with self._cond:
            self._closed = True
            self._items.clear()
            self._cond.notify_all()
        self._thread.join(timeout_s)
        self._pub.undeclare()


def subscribe(
    sess: zenoh.Session, topic: Topic, handler: Callable[[M], None], key: str | None = None
) -> zenoh.Subscriber[None]:
    """Call `handler(message)` for every valid message on the topic (in a Zenoh thread; keep it short).

    Undecodable payloads are dropped and counted; a handler that raises is logged and counted.
    """
    label = topic.key
    model: type[Message] = topic.payload

    def on_sample(sample: zenoh.Sample) -> None:
        try:
            message = decode(sample.payload.to_bytes(), model)
        except ContractError as err:
            decode_error(label, err)
            return
        metrics.RECEIVED_MESSAGES.labels(label).inc()
        try:
            handler(message)  # type: ignore[arg-type]
        except Exception:  # a faulty handler must not take the subscriber down
            metrics.HANDLER_ERRORS.labels(label).inc()
            log.exception("handler of %s failed", label)

    return sess.declare_subscriber(key or topic.key, on_sample)


@dataclass
class Incoming(Generic[M]):
    """A decoded request waiting for its reply."""

    message: M
    query: zenoh.Query
    received_at: float

    def progress(self, event: TelemetryEvent) -> None:
        """An intermediate reply (the client's on_progress sees it)."""
        self.query.reply(self.query.key_expr, encode(event), attachment=PROGRESS)

    def reply(self, message: Message) -> None:
        """The final reply; ends the request."""
        self.query.reply(self.query.key_expr, encode(message), attachment=RESULT)
        self.query.drop()

    def fail(self, error: str) -> None:
        """An error reply (the request could not be handled at all); ends the request."""
        self.query.reply_err(error.encode())
        self.query.drop()


class RequestQueue(Generic[M]):
    """A queryable whose valid requests wait in a bounded queue for the service loop.

    Undecodable requests get an error reply right away and are counted; when the queue is full the
    request is refused with an error reply (the client can try another worker).
    """

    def __init__(self, sess: zenoh.Session, topic: Topic, key: str | None = None, capacity: int = 64) -> None:
        self.topic = topic
        self.key = key or topic.key
        self._queue: queue.Queue[Incoming[M]] = queue.Queue(capacity)
        self._queryable = sess.declare_queryable(self.key, self._on_query, complete=True)

    def _on_query(self, query: zenoh.Query) -> None:
        payload = query.payload
        try:
            message = decode(payload.to_bytes() if payload is not None else b"", self.topic.payload)
        except ContractError as err:
            decode_error(self.topic.key, err)
            query.reply_err(f"ContractError: {err}".encode())
            query.drop()
            return
        metrics.RECEIVED_MESSAGES.labels(self.topic.key).inc()
        try:
            self._queue.put_nowait(Incoming(message, query, time.time()))  # type: ignore[arg-type]
        except queue.Full:
            metrics.DROPPED_MESSAGES.labels(self.topic.key).inc()
            query.reply_err(b"Busy: the request queue is full")
            query.drop()

    def get(self, timeout_s: float) -> Incoming[M] | None:
        """The next request, or None after timeout_s."""
        try:
            return self._queue.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def pending(self) -> int:
        return self._queue.qsize()

    def close(self) -> None:
        self._queryable.undeclare()


class RequestError(RuntimeError):
    """The service answered with an error reply, or nobody answered in time."""


class NoReplyError(RequestError):
    """No final reply came: the service went away, the request was cancelled, or it timed out."""


def request(
    sess: zenoh.Session,
    key: str,
    message: Message,
    reply_type: type[R],
    timeout_s: float,
    on_progress: Callable[[TelemetryEvent], None] | None = None,
    cancel: zenoh.CancellationToken | None = None,
) -> R:
    """Send `message` to the queryable at `key` and return its final reply as `reply_type`.

    Progress replies go to `on_progress`. Raises RequestError on an error reply or when no final
    reply arrives within timeout_s (or `cancel` fired first), ContractError when the reply does not
    decode.
    """
    replies = sess.get(
        key,
        payload=encode(message),
        timeout=timeout_s,
        target=zenoh.QueryTarget.BEST_MATCHING,
        consolidation=zenoh.ConsolidationMode.NONE,
        congestion_control=zenoh.CongestionControl.BLOCK,
        cancellation_token=cancel,
    )
    result: R | None = None
    t0 = time.monotonic()
    for reply in replies:
        if reply.err is not None:
            raise RequestError(f"{key}: {reply.err.payload.to_bytes().decode(errors='replace')}")
        sample = reply.ok
        if sample is None:
            continue
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else RESULT
        if attachment == PROGRESS:
            if on_progress is not None:
                on_progress(decode(sample.payload.to_bytes(), TelemetryEvent))
        elif result is None:
            result = decode(sample.payload.to_bytes(), reply_type)
    if result is None and cancel is not None and cancel.is_cancelled:
        raise NoReplyError(f"{key}: cancelled before the reply")
    if result is None and time.monotonic() - t0 < timeout_s * 0.9:
        raise NoReplyError(f"{key}: the request ended without a reply (the service went away)")
    if result is None:
        raise NoReplyError(f"{key}: no reply within {timeout_s:g} s (is the service running?)")
    return result
