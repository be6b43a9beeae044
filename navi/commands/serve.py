"""`navi serve router|compiler|env|learner|auditor`: one service of the mesh in the foreground. Each is a
thin shell that opens the Zenoh session, then runs the service's in-process core from its own package.
Module-level imports: typer and the standard library.

Every service reads NaviSettings (NAVI_* variables and .env); options override single fields.
"""

from __future__ import annotations

import json
import logging
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from navi.commands.common import DeviceOpt, EnvOpt, ResumeOpt, fail, pick_device
from navi.commands.learner import COMMAND_DEVICE
from navi.commands.options import Settings, config_options
from navi_learner.config import TrainConfig

if TYPE_CHECKING:
    from navi_contracts.settings import NaviSettings
    from navi_mesh.session import SessionConfig

app = typer.Typer(
    help="Run one service of the mesh in the foreground (Zenoh client of NAVI_ZENOH_CONNECT).",
    no_args_is_help=True,
)

ConnectOpt = Annotated[
    str | None, typer.Option("--connect", help="Zenoh endpoints to connect to (default: NAVI_ZENOH_CONNECT).")
]
ZenohConfigOpt = Annotated[
    Path | None,
    typer.Option("--zenoh-config", help="A Zenoh JSON5 config file (default: NAVI_ZENOH_CONFIG)."),
]
MetricsPortOpt = Annotated[
    int | None,
    typer.Option(
        "--metrics-port",
        help="Port of GET /metrics (default: NAVI_METRICS_PORT; 0: one the OS picks, logged).",
    ),
]
CorpusOpt = Annotated[
    Path, typer.Option("--corpus", help="Corpus folder (the default corpus is built when empty).")
]
SeedOpt = Annotated[int, typer.Option("--seed", help="Seed of the environment (and of training).")]
MetricsHostOpt = Annotated[
    str,
    typer.Option(
        "--metrics-host", help="Interface of GET /metrics (127.0.0.1: this machine only; 0.0.0.0: all)."
    ),
]


def load_settings() -> NaviSettings:
    """NaviSettings from NAVI_* variables and .env, or a one-line error naming the bad setting."""
    from pydantic import ValidationError

    from navi_contracts.settings import NaviSettings

    try:
        return NaviSettings()
    except ValidationError as err:
        raise fail(f"invalid NAVI_* setting: {err.errors()[0]['loc']}: {err.errors()[0]['msg']}") from err


def _session_config(settings: NaviSettings, connect: str | None, zenoh_config: Path | None) -> SessionConfig:
    from dataclasses import replace

    from navi_mesh.session import config_from_settings

    cfg = config_from_settings(settings)
    if connect is not None:
        cfg = replace(cfg, connect=tuple(e.strip() for e in connect.split(",") if e.strip()))
    if zenoh_config is not None:
        cfg = replace(cfg, config_file=zenoh_config)
    return cfg


def _logging() -> None:
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr
    )


def run_service(body: Callable[[threading.Event], Any], errors: tuple[type[Exception], ...] = ()) -> Any:
    """Run body(stop); clear errors exit 2.

    The first SIGTERM or SIGINT only sets `stop`: every loop polls it at a point where stopping is safe
    (training after the update in progress, with its checkpoint). No exception is raised into whatever
    the main thread runs then: a KeyboardInterrupt landing inside an import, a finaliser or a string
    `exec` is lost or corrupts the exit status. Later signals change nothing (torchrun and a terminal
    may each pass one to a rank)."""
    from navi_mesh.session import MeshError, close_session

    _logging()
    stop = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        return body(stop)
    except (MeshError, OSError, ValueError) as err:
        raise fail(str(err)) from err
    except errors as err:
        raise fail(str(err)) from err
    finally:
        close_session()


@app.command("router")
def serve_router(
    listen: Annotated[
        str | None, typer.Option("--listen", help="Endpoints to listen on (default: NAVI_ZENOH_LISTEN).")
    ] = None,
    zenoh_config: ZenohConfigOpt = None,
) -> None:
    """A Zenoh router in this process (for machines without zenohd)."""
    from navi_mesh.router import RouterConfig, run_router

    settings = load_settings()
    endpoints = (
        tuple(e.strip() for e in listen.split(",") if e.strip())
        if listen
        else tuple(settings.listen_endpoints)
    )
    cfg = RouterConfig(listen=endpoints, config_file=zenoh_config or settings.zenoh_config)
    run_service(lambda stop: run_router(cfg, stop))


@app.command("compiler")
def serve_compiler(
    workers: Annotated[
        int, typer.Option("--workers", min=1, help="Worker threads; each takes one job at a time.")
    ] = 1,
    threads: Annotated[int, typer.Option("--threads", min=0, help="C++ threads per job (0: all cores).")] = 0,
    device: Annotated[
        str, typer.Option("--device", help="cpu (C++ core) or cuda[:N] (GPU engine); auto picks.")
    ] = "cpu",
    max_source_mb: Annotated[
        float | None,
        typer.Option(
            "--max-source-mb",
            min=0.001,
            help="Largest source file or .pk3 member a job may read, MiB, checked before reading "
            "(default NAVI_MAX_SOURCE_BYTES, 256 MiB).",
        ),
    ] = None,
    metrics_port: MetricsPortOpt = None,
    metrics_host: MetricsHostOpt = "127.0.0.1",
    connect: ConnectOpt = None,
    zenoh_config: ZenohConfigOpt = None,
) -> None:
    """Compile workers answering CompileJobs on navi/compiler/jobs/<worker>."""
    from navi_compiler.service import CompilerServiceConfig
    from navi_compiler.service import serve_compiler as serve

    settings = load_settings()
    cfg = CompilerServiceConfig(
        workers=workers,
        threads=threads,
        device=pick_device(device),
        metrics_port=settings.metrics_port if metrics_port is None else metrics_port,
        metrics_host=metrics_host,
        max_source_bytes=(
            settings.max_source_bytes if max_source_mb is None else max(1, int(max_source_mb * 2**20))
        ),
        session=_session_config(settings, connect, zenoh_config),
    )
    run_service(lambda stop: serve(cfg, stop))


@app.command("env")
def serve_env(
    corpus: CorpusOpt = Path("artifacts/corpus/default"),
    actors: Annotated[int, typer.Option("--actors", min=1, help="Actors an external brain flies.")] = 4,
    device: DeviceOpt = "auto",
    seed: SeedOpt = 0,
    observation_hz: Annotated[
        float, typer.Option("--observation-hz", min=0.1, help="Rate of actor 0's published observation.")
    ] = 10.0,
    metrics_port: MetricsPortOpt = None,
    metrics_host: MetricsHostOpt = "127.0.0.1",
    connect: ConnectOpt = None,
    zenoh_config: ZenohConfigOpt = None,
) -> None:
    """The drone environment over Zenoh: StepRequest queryable, observations published.

    /metrics answers at once; while the corpus folder has no manifest the service waits for it (the
    learner builds the default corpus over compile jobs, or run `navi corpus build`), then serves."""
    from navi_env.config import EnvConfig
    from navi_env.service import EnvServiceConfig
    from navi_env.service import serve_env as serve

    settings = load_settings()
    env = EnvConfig(
        azimuth_bins=settings.azimuth_bins,
        elevation_bins=settings.elevation_bins,
        horizon=settings.max_distance,
        max_steps_per_episode=settings.max_steps_per_episode,
        episodes_per_scene=settings.scene_episodes_per_scene,
    )
    cfg = EnvServiceConfig(
        corpus=corpus,
        actors=actors,
        device=pick_device(device),
        seed=seed,
        observation_hz=observation_hz,
        metrics_port=settings.metrics_port if metrics_port is None else metrics_port,
        metrics_host=metrics_host,
        env=env,
        session=_session_config(settings, connect, zenoh_config),
    )
    from navi_env.corpus.folder import CorpusError

    def body(stop: threading.Event) -> None:
        if wait_for_corpus(corpus, stop, cfg.metrics_port, cfg.metrics_host):
            serve(cfg, stop)

    run_service(body, errors=(CorpusError,))


def wait_for_corpus(corpus: Path, stop: threading.Event, metrics_port: int, metrics_host: str) -> bool:
    """Serve /metrics and wait until `corpus` has a manifest (True) or `stop` is set (False)."""
    from navi_mesh import metrics

    metrics.serve_metrics(metrics_port, "env", metrics_host)
    manifest = corpus / "manifest.json"
    waited = 0.0
    while not manifest.is_file():
        if waited % 30.0 == 0.0:
            logging.getLogger("navi.commands.serve").info(
                "waiting for the corpus %s (the learner builds the default corpus over compile jobs; "
                "or run `navi corpus build`)",
                corpus,
            )
        if stop.wait(1.0):
            return False
        waited += 1.0
    return True


LEARNER_OPTIONS = (
    "n_actors",
    "temporal_core",
    "rollout_length",
    "total_steps",
    "checkpoint_every",
    "device",
    "seed",
)
"""The TrainConfig settings `navi serve learner` takes as options."""


@app.command("learner")
@config_options(TrainConfig(), LEARNER_OPTIONS, defaults=COMMAND_DEVICE)
def serve_learner(
    *,
    mode: Annotated[str, typer.Option("--mode", help="train (PPO) or infer (run a model).")] = "train",
    corpus: CorpusOpt = Path("artifacts/corpus/default"),
    env_kind: EnvOpt = "sdfdag",
    settings: Settings,
    checkpoint: ResumeOpt = None,
    resume_latest: Annotated[
        bool,
        typer.Option(
            "--resume-latest",
            help="train: without --checkpoint, resume from the newest checkpoint of the runs folder that "
            "loads (a restarted service goes on where it stopped, losing at most the steps since then).",
        ),
    ] = False,
    model: Annotated[
        str, typer.Option("--model", help="infer: checkpoint path, registry version or alias.")
    ] = "latest",
    follow_alias: Annotated[
        str, typer.Option("--follow-alias", help="infer: reload when this alias is promoted ('' never).")
    ] = "champion",
    infer_steps: Annotated[
        int, typer.Option("--infer-steps", min=0, help="infer: batched steps (0: forever).")
    ] = 0,
    host: Annotated[
        str,
        typer.Option("--host", help="Control plane interface (127.0.0.1: this machine only; 0.0.0.0: all)."),
    ] = "127.0.0.1",
    port: Annotated[
        int | None, typer.Option("--port", help="Control plane port (default NAVI_API_PORT; 0: none).")
    ] = None,
    read_only: Annotated[
        bool,
        typer.Option(
            "--read-only",
            help="Serve the model registry read-only (mutations answer 503). Without it the control plane "
            "refuses to start when NAVI_API_TOKEN is empty.",
        ),
    ] = False,
    corpus_build: Annotated[
        str,
        typer.Option(
            "--corpus-build",
            help="How a missing default corpus is built: jobs (on the compiler workers, over Zenoh) or "
            "local (in this process).",
        ),
    ] = "jobs",
    corpus_scenes: Annotated[
        int, typer.Option("--corpus-scenes", min=1, help="Procedural scenes of a default corpus built here.")
    ] = 16,
    corpus_resolution: Annotated[
        int | None,
        typer.Option(
            "--corpus-resolution",
            min=8,
            help="Resolution of a default corpus built here (NAVI_GMDAG_RESOLUTION).",
        ),
    ] = None,
    observation_hz: Annotated[
        float,
        typer.Option(
            "--observation-hz", min=0.1, max=1000.0, help="Rate of observations/actions on the mesh."
        ),
    ] = 10.0,
    exit_when_done: Annotated[
        bool, typer.Option("--exit-when-done", help="Exit after the run instead of serving until stopped.")
    ] = False,
    nproc: Annotated[
        int,
        typer.Option(
            "--nproc",
            min=1,
            help="train: data-parallel ranks on this machine, one per GPU (runs again through torchrun; "
            "rank 0 serves, every rank trains --actors actors).",
        ),
    ] = 1,
    connect: ConnectOpt = None,
    zenoh_config: ZenohConfigOpt = None,
) -> None:
    """Training or inference in-process, publishing telemetry, with the REST control plane."""
    from navi.commands.learner import train_config
    from navi_learner.ppo import dist
    from navi_learner.service.config import LearnerServiceConfig
    from navi_learner.service.shell import serve_learner as serve

    if mode not in ("train", "infer"):
        raise typer.BadParameter(f"--mode must be train or infer, got {mode!r}")
    if nproc > 1 and mode != "train":
        raise typer.BadParameter("--nproc > 1 needs --mode train (inference is one process)")
    if nproc > 1 and not dist.launched():
        raise typer.Exit(dist.relaunch(nproc, dist.strip_option(sys.argv[1:], "--nproc")))
    if env_kind not in ("sdfdag", "toy"):
        raise typer.BadParameter(f"--env must be sdfdag or toy, got {env_kind!r}")
    if corpus_build not in ("jobs", "local"):
        raise typer.BadParameter(f"--corpus-build must be jobs or local, got {corpus_build!r}")
    navi_settings = load_settings()
    try:
        rank, dev = dist.setup(pick_device(settings["device"]))
    except ValueError as err:
        raise fail(str(err)) from err
    train = train_config(settings, device=dev)
    cfg = LearnerServiceConfig(
        mode="train" if mode == "train" else "infer",
        corpus=corpus,
        corpus_build="local" if corpus_build == "local" else "jobs",
        corpus_scenes=corpus_scenes,
        corpus_resolution=corpus_resolution or navi_settings.gmdag_resolution,
        env_kind="toy" if env_kind == "toy" else "sdfdag",
        train=train,
        resume_from=checkpoint,
        resume_latest=resume_latest,
        model=model,
        follow_alias=follow_alias,
        infer_steps=infer_steps,
        models_dir=navi_settings.artifacts_dir / "models",
        runs_dir=navi_settings.artifacts_dir / "runs",
        observation_hz=observation_hz,
        api_host=host,
        api_port=navi_settings.api_port if port is None else port,
        api_token=navi_settings.api_token.get_secret_value(),
        api_read_only=read_only,
        exit_when_done=exit_when_done,
        session=_session_config(navi_settings, connect, zenoh_config),
    )
    from navi_env.corpus.folder import CorpusError
    from navi_env.corpus.jobs import CorpusBuildError
    from navi_learner.envs.factory import EnvUnavailable

    try:
        summary = run_service(
            lambda stop: serve(cfg, stop, rank),
            errors=(EnvUnavailable, CorpusBuildError, CorpusError, dist.DistError),
        )
    finally:
        dist.shutdown(rank)
    if summary is not None and rank.main:
        typer.echo(json.dumps(summary, default=str))


@app.command("auditor")
def serve_auditor(
    host: Annotated[
        str, typer.Option("--host", help="Dashboard interface (127.0.0.1: this machine only; 0.0.0.0: all).")
    ] = "127.0.0.1",
    port: Annotated[
        int | None,
        typer.Option(
            "--port", help="Dashboard port (default NAVI_AUDITOR_PORT; 0: one the OS picks, logged)."
        ),
    ] = None,
) -> None:
    """The auditor's live web dashboard (passive: it only subscribes)."""
    try:
        from navi_auditor.server import serve
    except ImportError as err:
        raise fail(f"the auditor is not installed: {err}") from err
    settings = load_settings()
    _logging()
    serve(host, settings.auditor_port if port is None else port, settings)
