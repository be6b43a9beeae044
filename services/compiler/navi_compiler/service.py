"""`navi serve compiler`: compile workers behind Zenoh queryables, and the client that submits jobs.

Each worker thread declares a queryable at `navi/compiler/jobs/<worker id>` and the liveliness token
`navi/alive/compiler/<worker id>`; while it compiles it also holds `navi/busy/compiler/<worker id>`.
A client lists the live workers, prefers an idle one, sends the CompileJob and waits for the
CompileResult, receiving progress replies (TelemetryEvents `compiler.progress.<stage>`) on the way.
Any number of workers, in one process (`--workers N`) or in many, share the jobs this way.

A failing job (bad source, bad options) becomes a CompileResult with ok=False, error_type and
error; the worker keeps serving. A source file or archive member over `max_source_bytes` fails with
SourceTooLargeError before it is read, so no job can make a worker inflate an archive bomb. The output is written with `write_gmdag` (temp file + fsync +
rename), so a job killed half-way never leaves a partial .gmdag behind.
"""

from __future__ import annotations

import logging
import random
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import zenoh

from navi_contracts.models import CompileJob, CompileResult, TelemetryEvent
from navi_contracts.topics import COMPILE_JOBS, alive_key
from navi_mesh import metrics
from navi_mesh.liveliness import declare_alive, instance_id, live_tokens
from navi_mesh.pubsub import Incoming, NoReplyError, RequestError, RequestQueue, request
from navi_mesh.session import SessionConfig, session

log = logging.getLogger("navi_compiler.service")

SERVICE = "compiler"
BUSY_PREFIX = "navi/busy"
"""Liveliness prefix of workers that are compiling: navi/busy/compiler/<worker id>."""
WORKER_GONE_GRACE_S = 5.0
"""After a job's query ended without a reply: how long the client waits for the worker's token to go."""

Progress = Callable[[str, float], None]  # (stage, fraction of the compile done)


@dataclass(frozen=True)
class CompilerServiceConfig:
    """One `navi serve compiler` process."""

    workers: int = 1
    """Worker threads in this process; each takes one job at a time."""
    threads: int = 0
    """C++ threads per job (0: all cores)."""
    device: str = "cpu"
    """cpu: the C++ core; cuda or cuda:N: the GPU (torch) engine, same output format."""
    metrics_port: int = 9100
    """Port of GET /metrics (Prometheus)."""
    metrics_host: str = "127.0.0.1"
    """Interface of the metrics endpoint."""
    max_source_bytes: int = 256 * 2**20
    """Largest source file or archive member a job may read (checked before reading)."""
    session: SessionConfig = field(default_factory=SessionConfig)
    """How to reach the Zenoh router."""


def _stats_dict(stats: object) -> dict[str, float]:
    out: dict[str, float] = {}
    for name, value in vars(stats).items():
        if isinstance(value, bool | int | float):
            out[name] = float(value)
    return out


def run_compile_job(
    job: CompileJob,
    worker_id: str = "",
    progress: Progress | None = None,
    threads: int = 0,
    device: str = "cpu",
    max_source_bytes: int = 256 * 2**20,
) -> CompileResult:
    """Load, compile and atomically write one job's scene; any failure becomes an error result.

    The source (or its archive member) is size-checked against max_source_bytes before it is read."""
    from navi_compiler.compile import compile_scene
    from navi_compiler.gmdag import write_gmdag
    from navi_compiler.ingest import load_scene

    t0 = time.perf_counter()
    try:
        scene = load_scene(
            job.source,
            map_name=job.map_name,
            scale=job.scale,
            repair=job.repair,
            seeds=list(job.seeds),
            max_bytes=max_source_bytes,
        )
        engine: Literal["cpp", "torch"] = "torch" if device.startswith("cuda") else "cpp"
        gmdag, stats = compile_scene(
            scene, resolution=job.resolution, threads=threads, progress=progress, engine=engine, device=device
        )
        out = Path(job.output)
        out.parent.mkdir(parents=True, exist_ok=True)
        write_gmdag(gmdag, out)
    except Exception as err:  # the job boundary: every failure is reported to the client, the worker lives on
        duration = time.perf_counter() - t0
        metrics.COMPILE_JOBS.labels("error").inc()
        metrics.COMPILE_DURATION.observe(duration)
        log.warning("job %s failed: %s: %s", job.job_id, type(err).__name__, err)
        return CompileResult(
            job_id=job.job_id,
            ok=False,
            error_type=type(err).__name__,
            error=str(err) or repr(err),
            duration_s=duration,
            worker_id=worker_id,
        )
    duration = time.perf_counter() - t0
    metrics.COMPILE_JOBS.labels("ok").inc()
    metrics.COMPILE_DURATION.observe(duration)
    log.info("job %s -> %s in %.2f s", job.job_id, job.output, duration)
    return CompileResult(
        job_id=job.job_id,
        ok=True,
        output=str(job.output),
        stats=_stats_dict(stats),
        duration_s=duration,
        worker_id=worker_id,
    )


def _stage_key(stage: str) -> str:
    slug = "".join(c if c.isalnum() else "_" for c in stage.lower()).strip("_") or "stage"
    return f"compiler.progress.{slug}"


def _progress_sender(item: Incoming[CompileJob]) -> Progress:
    def send(stage: str, fraction: float) -> None:
        event = TelemetryEvent(
            key=_stage_key(stage),
            value=float(fraction),
            step=0,
            run_id=item.message.job_id,
            timestamp=time.time(),
        )
        try:
            item.progress(event)
        except zenoh.ZError as err:
            log.info("progress of job %s not delivered: %s", item.message.job_id, err)

    return send


def serve_worker(
    sess: zenoh.Session, worker_id: str, cfg: CompilerServiceConfig, stop: threading.Event
) -> None:
    """Serve jobs at navi/compiler/jobs/<worker_id> until `stop` is set."""
    token = declare_alive(sess, SERVICE, worker_id)
    jobs: RequestQueue[CompileJob] = RequestQueue(sess, COMPILE_JOBS, key=f"{COMPILE_JOBS.key}/{worker_id}")
    log.info("compiler worker %s ready", worker_id)
    try:
        while not stop.is_set():
            item = jobs.get(0.2)
            if item is None:
                continue
            busy = sess.liveliness().declare_token(f"{BUSY_PREFIX}/{SERVICE}/{worker_id}")
            try:
                result = run_compile_job(
                    item.message,
                    worker_id,
                    _progress_sender(item),
                    cfg.threads,
                    cfg.device,
                    cfg.max_source_bytes,
                )
                item.reply(result)
            except zenoh.ZError as err:
                log.warning("reply to job %s not delivered: %s", item.message.job_id, err)
            finally:
                busy.undeclare()
    finally:
        jobs.close()
        token.undeclare()


def serve_compiler(cfg: CompilerServiceConfig, stop: threading.Event) -> None:
    """Run `cfg.workers` worker threads over the process's session until `stop` is set."""
    if cfg.workers < 1:
        raise ValueError("workers must be >= 1")
    metrics.serve_metrics(cfg.metrics_port, "compiler", cfg.metrics_host)
    sess = session(cfg.session)
    base = instance_id()
    workers = [
        threading.Thread(
            target=serve_worker,
            args=(sess, f"{base}-w{i}", cfg, stop),
            name=f"compiler w{i}",
            daemon=True,
        )
        for i in range(cfg.workers)
    ]
    for w in workers:
        w.start()
    stop.wait()
    for w in workers:
        w.join(timeout=5.0)


def pick_worker(sess: zenoh.Session, timeout_s: float = 2.0) -> str:
    """A live compiler worker, idle ones first (random among equals)."""
    deadline = time.monotonic() + timeout_s
    while True:
        live = [t.instance for t in live_tokens(sess, SERVICE, timeout_s=min(1.0, timeout_s))]
        if live:
            busy = {t.instance for t in live_tokens(sess, SERVICE, timeout_s=0.5, prefix=BUSY_PREFIX)}
            idle = [w for w in live if w not in busy]
            return random.choice(idle or live)
        if time.monotonic() >= deadline:
            raise RequestError("no compiler worker is alive (start one with `navi serve compiler`)")
        time.sleep(0.2)


def submit_compile_job(
    job: CompileJob,
    timeout_s: float = 3600.0,
    on_progress: Progress | None = None,
    sess: zenoh.Session | None = None,
) -> CompileResult:
    """Send a job to a compiler worker over Zenoh and wait for its result.

    on_progress(stage, fraction) sees the worker's progress. Raises RequestError when no worker is
    alive or none answers within timeout_s. Without `sess` the process's session is opened from
    NaviSettings (NAVI_ZENOH_CONNECT).
    """
    if sess is None:
        from navi_contracts.settings import NaviSettings
        from navi_mesh.session import config_from_settings

        sess = session(config_from_settings(NaviSettings()))

    def relay(event: TelemetryEvent) -> None:
        if on_progress is not None:
            on_progress(event.key.removeprefix("compiler.progress."), event.value)

    worker = pick_worker(sess)
    died = zenoh.CancellationToken()

    def on_token(sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            died.cancel()

    watch = sess.liveliness().declare_subscriber(alive_key(SERVICE, worker), on_token)
    try:
        return request(sess, f"{COMPILE_JOBS.key}/{worker}", job, CompileResult, timeout_s, relay, died)
    except NoReplyError as err:
        if _worker_gone(sess, worker, died, WORKER_GONE_GRACE_S):
            raise RequestError(f"compiler worker {worker} died before answering job {job.job_id}") from err
        raise
    finally:
        watch.undeclare()


def _worker_gone(sess: zenoh.Session, worker: str, died: zenoh.CancellationToken, grace_s: float) -> bool:
    """Whether the worker's liveliness token is gone, waiting up to grace_s for the router to notice
    (a killed process's query can end before its token is withdrawn)."""
    deadline = time.monotonic() + grace_s
    while not died.is_cancelled:
        if worker not in {t.instance for t in live_tokens(sess, SERVICE, timeout_s=0.5)}:
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.1)
    return True
