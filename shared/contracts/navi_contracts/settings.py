"""Settings from `NAVI_*` environment variables and a `.env` file in the working directory."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict


class NaviSettings(BaseSettings):
    """Every field reads `NAVI_<FIELD NAME>` (e.g. `NAVI_AZIMUTH_BINS=256`)."""

    model_config = SettingsConfigDict(env_prefix="NAVI_", env_file=".env", extra="ignore", frozen=True)

    azimuth_bins: int = Field(256, gt=0, description="Observation azimuth bins (360 degrees).")
    elevation_bins: int = Field(48, gt=0, description="Observation elevation bins (pole to pole).")
    max_distance: float = Field(100.0, gt=0, description="Sensor horizon in meters (depth normalisation).")
    gmdag_resolution: int = Field(
        512, ge=8, le=4096, description="Default compile resolution (cells per axis)."
    )
    max_steps_per_episode: int = Field(2000, gt=0, description="Hard truncation of an episode.")
    scene_episodes_per_scene: int = Field(
        16, gt=0, description="Episodes an actor flies in a scene before rotating."
    )
    zenoh_connect: str = Field(
        "tcp/127.0.0.1:7447", description="Comma-separated Zenoh endpoints to connect to."
    )
    zenoh_listen: str = Field(
        "tcp/127.0.0.1:7447",
        description="Comma-separated endpoints the router listens on (tcp/0.0.0.0:7447 for other hosts).",
    )
    zenoh_config: Path | None = Field(None, description="A Zenoh JSON5 config file; overrides the endpoints.")
    api_token: SecretStr = Field(SecretStr(""), description="Bearer token for control-plane mutations.")
    api_port: int = Field(8000, gt=0, lt=65536, description="Control plane (FastAPI) port.")
    auditor_port: int = Field(8080, gt=0, lt=65536, description="Web dashboard port.")
    metrics_port: int = Field(
        9100, gt=0, lt=65536, description="Prometheus port of services without an HTTP API."
    )
    max_source_bytes: int = Field(
        256 * 2**20,
        gt=0,
        description="Largest scene source file or archive member a compile reads (checked before reading).",
    )
    artifacts_dir: Path = Field(
        Path("artifacts"), description="Root of runs, models, corpora and recordings."
    )

    @property
    def connect_endpoints(self) -> list[str]:
        return [e.strip() for e in self.zenoh_connect.split(",") if e.strip()]

    @property
    def listen_endpoints(self) -> list[str]:
        return [e.strip() for e in self.zenoh_listen.split(",") if e.strip()]
