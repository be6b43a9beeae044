"""The service's bring-up: its status for /healthz (phase, run, actors, corpus build), the corpus
made ready (read, or built over compile jobs), its progress reported, and the heartbeat that tells
dashboards the mode and the actor count once a second."""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zenoh

from navi_contracts import telemetry_keys as keys
from navi_env.corpus.jobs import BuildProgress, CorpusBuildConfig, build_corpus_over_jobs
from navi_learner.service.config import LearnerServiceConfig
from navi_learner.service.publishers import MeshPublishers
from navi_mesh import metrics
from navi_mesh.messages import telemetry

if TYPE_CHECKING:
    from navi_learner.service import TelemetryTap

log = logging.getLogger(__name__)


class ServiceStatus:
    """What /healthz says beyond liveness: phase, run, actors and the corpus build (thread-safe)."""

    def __init__(self, corpus: Path | None) -> None:
        self._lock = threading.Lock()
        self.phase = "starting"
        self.step = 0  # step id of the newest training log row
        self.start_step = 0  # step id the run resumed from (0: from scratch)
        self.run_id = ""
        self.actors = 0
        self.corpus_path = str(corpus) if corpus is not None else ""
        self.corpus: BuildProgress | None = BuildProgress("missing") if corpus is not None else None

    def update(self, **fields: Any) -> None:
        with self._lock:
            for name, value in fields.items():
                setattr(self, name, value)

    def __call__(self) -> dict[str, Any]:
        with self._lock:
            corpus = None
            if self.corpus is not None:
                c = self.corpus
                corpus = {
                    "path": self.corpus_path,
                    "state": c.state,
                    "scenes_ready": c.scenes_ready,
                    "scenes_total": c.scenes_total,
                    "rejected": c.rejected,
                    "error": c.error,
                }
            return {
                "phase": self.phase,
                "run_id": self.run_id,
                "actors": self.actors,
                "step": self.step,
                "start_step": self.start_step,
                "corpus": corpus,
            }


class CorpusReporter:
    """Turns corpus build progress into /healthz status, navi_corpus_* gauges and `corpus.*` telemetry."""

    def __init__(self, status: ServiceStatus, pubs: MeshPublishers) -> None:
        self.status, self.pubs = status, pubs

    def __call__(self, progress: BuildProgress) -> None:
        self.status.update(corpus=progress)
        metrics.CORPUS_SCENES_READY.set(progress.scenes_ready)
        metrics.CORPUS_SCENES_PLANNED.set(progress.scenes_total)
        metrics.CORPUS_SCENES_REJECTED.set(progress.rejected)
        metrics.CORPUS_READY.set(1.0 if progress.state == "ready" else 0.0)
        self.publish(progress)
        log.info(
            "corpus %s: %d/%d scenes ready, %d rejected%s",
            progress.state,
            progress.scenes_ready,
            progress.scenes_total,
            progress.rejected,
            f" ({progress.error})" if progress.error else "",
        )

    def publish(self, progress: BuildProgress) -> None:
        for key, value in (
            (keys.CORPUS_SCENES_READY, progress.scenes_ready),
            (keys.CORPUS_SCENES_PLANNED, progress.scenes_total),
            (keys.CORPUS_SCENES_REJECTED, progress.rejected),
            (keys.CORPUS_READY, 1.0 if progress.state == "ready" else 0.0),
        ):
            self.pubs.telemetry.publish(telemetry(key, float(value), 0))


def prepare_corpus(
    cfg: LearnerServiceConfig,
    sess: zenoh.Session,
    reporter: CorpusReporter,
    stop: threading.Event,
) -> None:
    """Make sure the sdfdag corpus exists: read its manifest, or build the procedural default corpus
    (over compile jobs, or in this process with corpus_build="local"). A set `stop` ends either build
    with InterruptedError (a local one at the next scene; the corpus folder is left as it was)."""
    if cfg.env_kind != "sdfdag":
        return
    from navi_env.corpus.folder import MANIFEST, CorpusError, build_default_corpus, read_manifest

    if not (cfg.corpus / MANIFEST).is_file():
        reporter.status.update(phase="corpus")
        if cfg.corpus_build == "local":
            log.info("building the procedural default corpus into %s in this process", cfg.corpus)
            reporter(BuildProgress("building", scenes_total=cfg.corpus_scenes))

            def progress(line: str) -> None:  # between scenes: the build stops there when a signal came
                log.info("corpus: %s", line)
                if stop.is_set():
                    raise InterruptedError("stopped while the corpus was built (nothing of it is kept)")

            build_default_corpus(
                cfg.corpus,
                cfg.corpus_resolution,
                cfg.corpus_scenes,
                cfg.train.seed,
                cfg.train.device,
                progress=progress,
            )
        else:
            log.info(
                "building the procedural default corpus into %s over compile jobs (%d scenes at %d^3)",
                cfg.corpus,
                cfg.corpus_scenes,
                cfg.corpus_resolution,
            )
            build = CorpusBuildConfig(
                cfg.corpus, cfg.corpus_scenes, cfg.corpus_resolution, cfg.train.seed, cfg.train.device
            )
            build_corpus_over_jobs(build, sess, reporter, stop)
    try:
        manifest = read_manifest(cfg.corpus)
    except CorpusError as err:
        reporter(BuildProgress("failed", error=str(err)))
        raise
    total = len(manifest.scenes) + len(manifest.rejected)
    reporter(BuildProgress("ready", len(manifest.scenes), total, len(manifest.rejected)))


class Heartbeat:
    """Once a second: `actor.<mode>.actors` while the loop runs (mode and actor count for dashboards),
    and the corpus progress again while it is built (for dashboards that connect late)."""

    def __init__(self, status: ServiceStatus, pubs: MeshPublishers, reporter: CorpusReporter) -> None:
        self.status, self.pubs, self.reporter = status, pubs, reporter
        self.tap: TelemetryTap | None = None  # set once the environment exists (its step count)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="navi-heartbeat", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(1.0):
            phase, actors, run_id = self.status.phase, self.status.actors, self.status.run_id
            if phase in ("training", "inference") and actors > 0:
                prefix = keys.TRAINING if phase == "training" else keys.INFERENCE
                step = self.status.step
                if phase == "inference" and self.tap is not None:
                    step = self.tap.steps * self.tap.n_actors
                self.pubs.telemetry.publish(telemetry(prefix + keys.ACTORS, actors, step, run_id))
            corpus = self.status.corpus
            if phase == "corpus" and corpus is not None:
                self.reporter.publish(corpus)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
