"""The procedural default corpus built over compile jobs: the path `navi compile --remote` takes.

`build_corpus_over_jobs` generates the procedural sources (navi_compiler.ingest.procedural) into a folder beside
the target, sends one CompileJob per scene to the live compiler workers (as many at once as there
are workers), qualifies each compiled scene here (navi_env.space.qualify, on this process's device) and
swaps the finished corpus folder in with its manifest, as `navi corpus build` does: until then the
target holds no manifest, and a failed build leaves no partial corpus. Progress goes to a callback
after every scene. A job whose worker died (kill -9, lost host) is sent again to a live worker, up
to `attempts` times; a job that fails (bad source) fails the build with the worker's error. Paths in
the jobs are absolute: the workers must see the corpus folder at the same path (same machine, or the
same volume mounted at the same place, as in docker-compose.yml).
"""

from __future__ import annotations

import json
import logging
import os
import queue
import shutil
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:
    import zenoh

    from navi_env.corpus.folder import CorpusManifest

log = logging.getLogger("navi_env.corpus.jobs")

BuildState = Literal["missing", "waiting", "building", "ready", "failed"]


class CorpusBuildError(RuntimeError):
    """The corpus could not be built; the message names the scene and the reason."""


@dataclass(frozen=True)
class CorpusBuildConfig:
    """One build of the procedural default corpus over compile jobs."""

    out: Path
    """The corpus folder to create (manifest.json + <name>.gmdag)."""
    count: int = 16
    """Procedural scenes to generate."""
    resolution: int = 512
    """Compile resolution (cells per cube edge)."""
    seed: int = 0
    """Seed of the procedural generator (the same seed makes the same scenes)."""
    device: str = "cpu"
    """Torch device of the qualification probes (the learner's device)."""
    job_timeout_s: float = 3600.0
    """Longest wait for one compile job."""
    attempts: int = 3
    """Tries per scene when its worker dies mid-job."""
    worker_poll_s: float = 1.0
    """How often to look for a compiler worker while none is alive."""


@dataclass(frozen=True)
class BuildProgress:
    """Where a build stands (the learner shows it in /healthz, metrics and telemetry)."""

    state: BuildState
    scenes_ready: int = 0
    """Scenes compiled and qualified."""
    scenes_total: int = 0
    rejected: int = 0
    """Scenes compiled but rejected by qualification."""
    retries: int = 0
    """Jobs sent again because their worker died."""
    error: str = ""


@dataclass
class _Done:
    index: int
    path: Path | None
    error: str = ""


def _wait_for_workers(sess: zenoh.Session, stop: threading.Event, poll_s: float) -> int:
    """The number of live compiler workers, waiting while there are none (0 when stopped)."""
    from navi_mesh.liveliness import live_tokens

    next_note = time.monotonic()
    while not stop.is_set():
        live = live_tokens(sess, "compiler", timeout_s=1.0)
        if live:
            return len(live)
        if time.monotonic() >= next_note:
            log.info(
                "waiting for a compiler worker to build the corpus (start `navi serve compiler`, or build "
                "it in this process with --corpus-build local)"
            )
            next_note = time.monotonic() + 30.0
        stop.wait(poll_s)
    return 0


def compile_with_retries(
    sess: zenoh.Session,
    source: Path,
    out: Path,
    cfg: CorpusBuildConfig,
    stop: threading.Event,
    on_retry: Callable[[str], None],
) -> str:
    """Run one compile job on a live worker; '' on success, else the error. When the worker dies
    before answering (RequestError), on_retry(error) is called and the job goes to a live worker
    again, up to cfg.attempts tries. A job the worker answers with an error is not retried."""
    from navi_compiler.service import submit_compile_job
    from navi_contracts.models import CompileJob
    from navi_mesh.pubsub import RequestError

    job = CompileJob(
        job_id=f"corpus-{out.stem}-{uuid.uuid4().hex[:8]}",
        source=str(source),
        output=str(out),
        resolution=cfg.resolution,
    )
    last = ""
    for attempt in range(cfg.attempts):
        if attempt:
            on_retry(last)
        if _wait_for_workers(sess, stop, cfg.worker_poll_s) == 0:
            return "stopped"
        try:
            result = submit_compile_job(job, cfg.job_timeout_s, sess=sess)
        except RequestError as err:  # the worker died, or went away before answering: try another
            last = str(err)
            continue
        if result.ok:
            return ""
        return f"{result.error_type}: {result.error}"
    return f"no worker finished the job after {cfg.attempts} tries: {last}"


def _write_manifest(folder: Path, manifest: CorpusManifest) -> None:
    from navi_env.corpus.folder import MANIFEST

    path = folder / MANIFEST
    with path.open("w") as f:
        json.dump(manifest.to_json(), f, indent=1)
        f.flush()
        os.fsync(f.fileno())


def build_corpus_over_jobs(
    cfg: CorpusBuildConfig,
    sess: zenoh.Session,
    on_progress: Callable[[BuildProgress], None],
    stop: threading.Event | None = None,
) -> CorpusManifest:
    """Build the procedural default corpus at cfg.out with compile jobs (see the module docstring).

    Raises CorpusBuildError when a scene does not compile or none qualifies, InterruptedError when
    `stop` is set first. The target is untouched unless the whole build succeeds."""
    import torch

    from navi_compiler.ingest.procedural import generate_corpus
    from navi_env.corpus.folder import CorpusManifest, SceneEntry, replace_directory
    from navi_env.space.qualify import qualify_scene
    from navi_env.tracer.scene import load_corpus

    stop = stop or threading.Event()
    target = cfg.out.resolve()
    target.parent.mkdir(parents=True, exist_ok=True)
    progress = BuildProgress("waiting", scenes_total=cfg.count)
    on_progress(progress)
    abort = threading.Event()
    sources_dir = Path(tempfile.mkdtemp(prefix=f".{target.name}.sources-", dir=target.parent))
    work = Path(tempfile.mkdtemp(prefix=f".{target.name}.build-", dir=target.parent))
    try:
        sources = generate_corpus(sources_dir, cfg.count, cfg.seed)
        workers = _wait_for_workers(sess, stop, cfg.worker_poll_s)
        if workers == 0:
            raise InterruptedError("stopped before a compiler worker appeared")
        progress = replace(progress, state="building")
        on_progress(progress)
        todo: queue.Queue[int] = queue.Queue()
        for i in range(len(sources)):
            todo.put(i)
        done: queue.Queue[_Done] = queue.Queue()
        retries = [0]
        lock = threading.Lock()

        def count_retry(error: str) -> None:
            log.warning("sending a compile job again: %s", error)
            with lock:
                retries[0] += 1

        def client() -> None:  # one per worker: as many jobs in flight as there are workers
            while not (stop.is_set() or abort.is_set()):
                try:
                    i = todo.get_nowait()
                except queue.Empty:
                    return
                out = work / f"{sources[i].stem}.gmdag"
                try:
                    error = compile_with_retries(sess, sources[i], out, cfg, abort, count_retry)
                except Exception as err:  # reported as the scene's failure, never lost in a thread
                    error = f"{type(err).__name__}: {err}"
                done.put(_Done(i, None if error else out, error))

        for k in range(max(1, min(workers, len(sources)))):
            threading.Thread(target=client, name=f"corpus job client {k}", daemon=True).start()
        entries: dict[int, SceneEntry] = {}
        rejected: dict[int, dict[str, str]] = {}
        device = torch.device(cfg.device)
        for _ in sources:
            item = None
            while item is None:
                if stop.is_set():
                    raise InterruptedError("stopped while building the corpus")
                try:
                    item = done.get(timeout=0.2)
                except queue.Empty:
                    continue
            if item.path is None:
                raise CorpusBuildError(f"{sources[item.index].name}: {item.error}")
            scenes = load_corpus([item.path], device)
            verdict = qualify_scene(scenes, 0)
            if verdict.passed:
                info = scenes.infos[0]
                entries[item.index] = SceneEntry(
                    name=item.path.stem,
                    file=item.path.name,
                    source=str(sources[item.index]),
                    resolution=info.resolution,
                    voxel_size=info.voxel_size,
                    bytes=item.path.stat().st_size,
                    qualification=verdict.to_json(),
                )
            else:
                rejected[item.index] = {"source": str(sources[item.index]), "reason": verdict.reason}
                item.path.unlink()
            progress = replace(
                progress, scenes_ready=len(entries), rejected=len(rejected), retries=retries[0]
            )
            on_progress(progress)
        if not entries:
            raise CorpusBuildError(
                f"no scene qualified ({len(rejected)} rejected); the corpus would be empty"
            )
        manifest = CorpusManifest(
            created_at=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            resolution=cfg.resolution,
            scenes=tuple(entries[i] for i in sorted(entries)),
            rejected=tuple(rejected[i] for i in sorted(rejected)),
        )
        _write_manifest(work, manifest)
        replace_directory(work, target)
        on_progress(replace(progress, state="ready"))
        return manifest
    except (CorpusBuildError, OSError, ValueError, RuntimeError) as err:
        on_progress(replace(progress, state="failed", error=str(err)))
        raise
    finally:
        abort.set()  # the job clients send nothing more (a job in flight finishes on its worker)
        shutil.rmtree(work, ignore_errors=True)
        shutil.rmtree(sources_dir, ignore_errors=True)
