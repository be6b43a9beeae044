"""`navi serve ...` and `navi stack ...` (registered by navi.cli). Module-level imports: typer + stdlib.

Every service reads NaviSettings (NAVI_* variables and .env); options override single fields.
Other packages add their own long-running services to `serve_app` (e.g. `navi serve auditor`).
"""

from __future__ import annotations

import json
import logging
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

if TYPE_CHECKING:
    from navi_contracts.settings import NaviSettings
    from navi_mesh.session import SessionConfig

PANEL = "Services"

serve_app = typer.Typer(
    help="Run one service of the mesh in the foreground (Zenoh client of NAVI_ZENOH_CONNECT).",
    no_args_is_help=True,
)
stack_app = typer.Typer(
    help="The whole stack as local processes: router, compiler, env, learner, auditor.", no_args_is_help=True
)

ConnectOpt = Annotated[
    str | None, typer.Option("--connect", help="Zenoh endpoints to connect to (default: NAVI_ZENOH_CONNECT).")
]
ZenohConfigOpt = Annotated[
    Path | None,
    typer.Option("--zenoh-config", help="A Zenoh JSON5 config file (default: NAVI_ZENOH_CONFIG)."),
]
MetricsPortOpt = Annotated[
    int | None, typer.Option("--metrics-port", help="Port of GET /metrics (default: NAVI_METRICS_PORT).")
]
DeviceOpt = Annotated[str, typer.Option("--device", help="Torch device: auto, cpu, cuda, cuda:N.")]
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


def fail(message: str) -> typer.Exit:
    """Print a one-line error to stderr; the caller raises the returned Exit(2)."""
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(2)


def _settings() -> NaviSettings:
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


def _device(device: str) -> str:
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise fail(f"device {device} requested but CUDA is not available")
    if not (device == "cpu" or device.startswith("cuda")):
        raise fail(f"unknown device {device!r}; use auto, cpu, cuda or cuda:N")
    return device


def _logging() -> None:
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr
    )


def run_service(
    body: Callable[[threading.Event], Any], interrupt: bool = False, errors: tuple[type[Exception], ...] = ()
) -> Any:
    """Run body(stop) with SIGTERM/SIGINT setting `stop` (and raising KeyboardInterrupt when
    `interrupt`, so a training loop saves its checkpoint); clear errors exit 2."""
    from navi_mesh.session import MeshError, close_session

    _logging()
    stop = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        first = not stop.is_set()
        stop.set()
        if interrupt and first:
            raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        return body(stop)
    except KeyboardInterrupt:
        return None
    except (MeshError, OSError, ValueError) as err:
        raise fail(str(err)) from err
    except errors as err:
        raise fail(str(err)) from err
    finally:
        close_session()


@serve_app.command("router")
def serve_router(
    listen: Annotated[
        str | None, typer.Option("--listen", help="Endpoints to listen on (default: NAVI_ZENOH_LISTEN).")
    ] = None,
    zenoh_config: ZenohConfigOpt = None,
) -> None:
    """A Zenoh router in this process (for machines without zenohd)."""
    from navi_mesh.router import RouterConfig, run_router

    settings = _settings()
    endpoints = (
        tuple(e.strip() for e in listen.split(",") if e.strip())
        if listen
        else tuple(settings.listen_endpoints)
    )
    cfg = RouterConfig(listen=endpoints, config_file=zenoh_config or settings.zenoh_config)
    run_service(lambda stop: run_router(cfg, stop))


@serve_app.command("compiler")
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

    settings = _settings()
    cfg = CompilerServiceConfig(
        workers=workers,
        threads=threads,
        device=_device(device),
        metrics_port=metrics_port or settings.metrics_port,
        metrics_host=metrics_host,
        max_source_bytes=(
            settings.max_source_bytes if max_source_mb is None else max(1, int(max_source_mb * 2**20))
        ),
        session=_session_config(settings, connect, zenoh_config),
    )
    run_service(lambda stop: serve(cfg, stop))


@serve_app.command("env")
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

    settings = _settings()
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
        device=_device(device),
        seed=seed,
        observation_hz=observation_hz,
        metrics_port=metrics_port or settings.metrics_port,
        metrics_host=metrics_host,
        env=env,
        session=_session_config(settings, connect, zenoh_config),
    )
    from navi_env.corpus import CorpusError

    def body(stop: threading.Event) -> None:
        if wait_for_corpus(corpus, stop, cfg.metrics_port, cfg.metrics_host):
            serve(cfg, stop)

    run_service(body, errors=(CorpusError,))


def wait_for_corpus(corpus: Path, stop: threading.Event, metrics_port: int, metrics_host: str) -> bool:
    """Serve /metrics and wait until `corpus` has a manifest (True) or `stop` is set (False)."""
    from navi_mesh import metrics

    metrics.serve_metrics(metrics_port, metrics_host)
    manifest = corpus / "manifest.json"
    waited = 0.0
    while not manifest.is_file():
        if waited % 30.0 == 0.0:
            logging.getLogger("navi_mesh.cli").info(
                "waiting for the corpus %s (the learner builds the default corpus over compile jobs; "
                "or run `navi corpus build`)",
                corpus,
            )
        if stop.wait(1.0):
            return False
        waited += 1.0
    return True


@serve_app.command("learner")
def serve_learner(
    mode: Annotated[str, typer.Option("--mode", help="train (PPO) or infer (run a model).")] = "train",
    corpus: CorpusOpt = Path("artifacts/corpus/default"),
    env_kind: Annotated[
        str, typer.Option("--env", help="Environment: sdfdag (the drone env) or toy (tests).")
    ] = "sdfdag",
    actors: Annotated[
        int, typer.Option("--actors", min=0, help="Parallel actors (0: 4 on CPU, 4096 on CUDA).")
    ] = 0,
    temporal_core: Annotated[str, typer.Option("--temporal-core", help="mamba2, gru or mambapy.")] = "mamba2",
    rollout_length: Annotated[
        int, typer.Option("--rollout-length", min=0, help="Steps per rollout (0: default).")
    ] = 0,
    total_steps: Annotated[
        int, typer.Option("--total-steps", min=1, help="train: env-step budget.")
    ] = 1_000_000,
    checkpoint_every: Annotated[
        int, typer.Option("--checkpoint-every", min=1, help="train: env steps between checkpoints.")
    ] = 25_000,
    checkpoint: Annotated[
        Path | None, typer.Option("--checkpoint", help="train: resume from this checkpoint.")
    ] = None,
    model: Annotated[
        str, typer.Option("--model", help="infer: checkpoint path, registry version or alias.")
    ] = "latest",
    follow_alias: Annotated[
        str, typer.Option("--follow-alias", help="infer: reload when this alias is promoted ('' never).")
    ] = "champion",
    infer_steps: Annotated[
        int, typer.Option("--infer-steps", min=0, help="infer: batched steps (0: forever).")
    ] = 0,
    device: DeviceOpt = "auto",
    seed: SeedOpt = 0,
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
    from navi_learner import dist
    from navi_learner.cli import train_config
    from navi_learner.service import LearnerServiceConfig
    from navi_learner.service import serve_learner as serve

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
    settings = _settings()
    try:
        rank, dev = dist.setup(_device(device))
    except ValueError as err:
        raise fail(str(err)) from err
    train = train_config(
        actors, temporal_core, rollout_length, 1, 5e-4, total_steps, checkpoint_every, dev, seed
    )
    cfg = LearnerServiceConfig(
        mode="train" if mode == "train" else "infer",
        corpus=corpus,
        corpus_build="local" if corpus_build == "local" else "jobs",
        corpus_scenes=corpus_scenes,
        corpus_resolution=corpus_resolution or settings.gmdag_resolution,
        env_kind="toy" if env_kind == "toy" else "sdfdag",
        train=train,
        resume_from=checkpoint,
        model=model,
        follow_alias=follow_alias,
        infer_steps=infer_steps,
        models_dir=settings.artifacts_dir / "models",
        runs_dir=settings.artifacts_dir / "runs",
        observation_hz=observation_hz,
        api_host=host,
        api_port=settings.api_port if port is None else port,
        api_token=settings.api_token.get_secret_value(),
        api_read_only=read_only,
        exit_when_done=exit_when_done,
        session=_session_config(settings, connect, zenoh_config),
    )
    from navi_env.corpus import CorpusError
    from navi_learner.envs import EnvUnavailable
    from navi_mesh.corpus_jobs import CorpusBuildError

    try:
        summary = run_service(
            lambda stop: serve(cfg, stop, rank),
            interrupt=not rank.active,  # ranks stop together after an update, never mid-collective
            errors=(EnvUnavailable, CorpusBuildError, CorpusError, dist.DistError),
        )
    finally:
        dist.shutdown(rank)
    if summary is not None and rank.main:
        typer.echo(json.dumps(summary, default=str))


@serve_app.command("auditor")
def serve_auditor(
    host: Annotated[
        str, typer.Option("--host", help="Dashboard interface (127.0.0.1: this machine only; 0.0.0.0: all).")
    ] = "127.0.0.1",
    port: Annotated[
        int | None, typer.Option("--port", help="Dashboard port (default NAVI_AUDITOR_PORT).")
    ] = None,
) -> None:
    """The auditor's live web dashboard (passive: it only subscribes)."""
    try:
        from navi_auditor.server import serve
    except ImportError as err:
        raise fail(f"the auditor is not installed: {err}") from err
    settings = _settings()
    _logging()
    serve(host, settings.auditor_port if port is None else port, settings)


def _print_status(cfg_root: Path, connect: tuple[str, ...], as_json: bool, timeout_s: float) -> None:
    from navi_mesh.liveliness import live_tokens
    from navi_mesh.session import MeshError, SessionConfig, open_new_session
    from navi_mesh.stack import learner_health, read_states

    states = read_states(cfg_root)
    health = learner_health(cfg_root) if any(s.name == "learner" and s.running for s in states) else None
    tokens: list[str] = []
    error = ""
    try:
        sess = open_new_session(SessionConfig(connect=connect, connect_timeout_s=timeout_s))
    except MeshError as err:
        error = str(err)
    else:
        try:
            tokens = [t.key for t in live_tokens(sess, timeout_s=timeout_s)]
        finally:
            sess.close()
    if as_json:
        typer.echo(
            json.dumps(
                {
                    "processes": [
                        {"name": s.name, "pid": s.pid, "running": s.running, "log": s.log} for s in states
                    ],
                    "alive": tokens,
                    "router_error": error,
                    "learner": health,
                }
            )
        )
        return
    if not states:
        typer.echo(f"no stack processes under {cfg_root}")
    for s in states:
        since = time.strftime("%H:%M:%S", time.localtime(s.started_at))
        typer.echo(
            f"{s.name:<9} pid {s.pid:<8} {'running' if s.running else 'stopped':<8} since {since}  {s.log}"
        )
    if health is not None:
        corpus = health.get("corpus")
        line = f"learner: {health.get('phase') or '?'}"
        if isinstance(corpus, dict):
            line += (
                f"; corpus {corpus.get('state')}: {corpus.get('scenes_ready')}/{corpus.get('scenes_total')} "
                f"scenes ready, {corpus.get('rejected')} rejected"
            )
            if corpus.get("error"):
                line += f" ({corpus['error']})"
        typer.echo(line)
    typer.echo(f"live tokens ({len(tokens)}):" if not error else f"router unreachable: {error}")
    for key in tokens:
        typer.echo(f"  {key}")


@stack_app.command("up")
def stack_up(
    corpus: CorpusOpt = Path("artifacts/corpus/default"),
    actors: Annotated[int, typer.Option("--actors", min=1, help="Learner actors (per rank).")] = 4,
    nproc: Annotated[
        int, typer.Option("--nproc", min=1, help="Learner data-parallel ranks, one per GPU (DD-PPO).")
    ] = 1,
    env_actors: Annotated[int, typer.Option("--env-actors", min=1, help="Env-service actors.")] = 2,
    device: Annotated[
        str,
        typer.Option(
            "--device",
            help="Torch device of learner, env and compiler (auto: CUDA and the GPU compile engine when present).",
        ),
    ] = "auto",
    host: Annotated[
        str,
        typer.Option(
            "--host",
            help="Interface every service binds: 127.0.0.1 (this machine only) or 0.0.0.0 (all; then set "
            "NAVI_API_TOKEN yourself and mind your firewall).",
        ),
    ] = "127.0.0.1",
    router_port: Annotated[int, typer.Option("--router-port", help="Zenoh router port.")] = 7447,
    api_port: Annotated[
        int | None, typer.Option("--api-port", help="Control plane port (NAVI_API_PORT).")
    ] = None,
    auditor: Annotated[
        bool, typer.Option("--auditor/--no-auditor", help="Start the auditor dashboard.")
    ] = True,
    corpus_scenes: Annotated[
        int, typer.Option("--corpus-scenes", min=1, help="Scenes of the default corpus when it is built.")
    ] = 16,
    corpus_resolution: Annotated[
        int | None,
        typer.Option("--corpus-resolution", min=8, help="Its resolution (default NAVI_GMDAG_RESOLUTION)."),
    ] = None,
    compiler_workers: Annotated[
        int, typer.Option("--compiler-workers", min=1, help="Compile worker threads.")
    ] = 1,
    wait_s: Annotated[
        float, typer.Option("--wait", min=0.0, help="Seconds to wait for every service's health check.")
    ] = 60.0,
) -> None:
    """Start router, compiler, env, learner (and auditor) at once as local processes (pid files in
    artifacts/stack); returns when each answers its health check. A missing corpus is built in the
    background over compile jobs; training starts when it is ready (`navi stack status` shows progress)."""
    from navi_mesh.stack import STACK_DIR, StackConfig, StackError, probe_host, up

    settings = _settings()
    cfg = StackConfig(
        root=STACK_DIR,
        host=host,
        router_port=router_port,
        api_port=api_port or settings.api_port,
        auditor_port=settings.auditor_port,
        corpus=corpus,
        corpus_scenes=corpus_scenes,
        corpus_resolution=corpus_resolution or settings.gmdag_resolution,
        compiler_workers=compiler_workers,
        actors=actors,
        nproc=nproc,
        env_actors=env_actors,
        device=device,
        auditor=auditor,
    )
    try:
        up(cfg, wait_s, lambda line: typer.echo(line, err=True), typer.echo)
    except StackError as err:
        raise fail(str(err)) from err
    _print_status(cfg.root, (f"tcp/{probe_host(host)}:{router_port}",), False, 2.0)


@stack_app.command("down")
def stack_down(
    grace_s: Annotated[
        float, typer.Option("--grace", min=0.0, help="Seconds between SIGTERM and SIGKILL.")
    ] = 30.0,
) -> None:
    """Stop every stack process (SIGTERM, then SIGKILL after the grace period)."""
    from navi_mesh.stack import STACK_DIR, stop_all

    states = stop_all(STACK_DIR, grace_s)
    if not states:
        typer.echo("no stack processes")
    for s in states:
        typer.echo(f"{s.name:<9} pid {s.pid:<8} {'STILL RUNNING' if s.running else 'stopped'}")


@stack_app.command("status")
def stack_status(
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    timeout_s: Annotated[
        float, typer.Option("--timeout", min=0.1, help="Seconds to wait for the router.")
    ] = 2.0,
) -> None:
    """Process states (pid files) and the live liveliness tokens (navi/alive/<service>/<id>)."""
    from navi_mesh.stack import STACK_DIR

    _print_status(STACK_DIR, tuple(_settings().connect_endpoints), as_json, timeout_s)


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add `serve` and `stack` to the root app."""
    app.add_typer(serve_app, name="serve", rich_help_panel=PANEL)
    app.add_typer(stack_app, name="stack", rich_help_panel=PANEL)
