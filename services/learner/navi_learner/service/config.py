"""One `navi serve learner` process's settings (LearnerServiceConfig) and the service's name."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from navi_learner.config import TrainConfig
from navi_learner.envs.factory import EnvKind
from navi_mesh.session import SessionConfig

SERVICE = "learner"
Mode = Literal["train", "infer"]


@dataclass(frozen=True)
class LearnerServiceConfig:
    """One `navi serve learner` process."""

    mode: Mode = "train"
    """train (PPO) or infer (run a model, follow promotions)."""
    corpus: Path = Path("artifacts/corpus/default")
    """Corpus folder; the procedural default corpus is built there when it has no manifest."""
    corpus_build: Literal["jobs", "local"] = "jobs"
    """How a missing default corpus is built: compile jobs on the compiler workers, or in this process."""
    corpus_scenes: int = 16
    """Procedural scenes of a default corpus built here."""
    corpus_resolution: int = 512
    """Compile resolution of a default corpus built here."""
    env_kind: EnvKind = "sdfdag"
    """sdfdag (the drone env) or toy (tests)."""
    train: TrainConfig = field(default_factory=TrainConfig)
    """The training run (actors, budget, device, seed, engine, PPO)."""
    resume_from: Path | None = None
    """train: checkpoint to resume from."""
    resume_latest: bool = False
    """train: without resume_from, resume from the newest checkpoint under runs_dir that loads (a
    restarted service goes on where it stopped, losing at most the steps since that checkpoint)."""
    model: str = "latest"
    """infer: a checkpoint path, or a registry version or alias."""
    follow_alias: str = "champion"
    """infer: reload the model when this alias is promoted (empty: never)."""
    action_noise: float | None = None
    """infer: the actions sampled with this many times the policy's learned std (0: its mean action); None:
    as its task flies wherever Navi evaluates it (navi_learner.evaluation.evaluate.ACTION_NOISE)."""
    infer_steps: int = 0
    """infer: batched steps to run (0: until stopped)."""
    models_dir: Path = Path("artifacts/models")
    """The model registry."""
    runs_dir: Path = Path("artifacts/runs")
    """Run folders."""
    observation_hz: float = 10.0
    """Rate of actor 0's observation and of the actions on the mesh (5-10 Hz for dashboards)."""
    telemetry_capacity: int = 1024
    """Telemetry queue length (drop-oldest beyond it)."""
    api_host: str = "127.0.0.1"
    """Control plane interface."""
    api_port: int = 8000
    """Control plane port (0: no control plane)."""
    api_token: str = ""
    """Bearer token for mutations (required unless api_read_only)."""
    api_read_only: bool = False
    """Serve the registry read-only (mutations answer 503); the only way to run without a token."""
    exit_when_done: bool = False
    """Exit after the run instead of keeping the control plane up until stopped."""
    session: SessionConfig = field(default_factory=SessionConfig)
    """How to reach the Zenoh router."""
