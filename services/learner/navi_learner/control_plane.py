"""The learner's REST control plane (FastAPI): the model registry over HTTP, health and metrics.

    GET  /models              every version, with the aliases
    GET  /models/{version}    one version (vNNN) or alias (latest, champion, ...)
    POST /models/promote      register a checkpoint (or take a version) and move an alias to it
    POST /models/rollback     move an alias back to where it pointed before its last move
    GET  /healthz             liveness and whether mutations are enabled
    GET  /metrics             Prometheus text format (this exact path, no redirect)
    GET  /docs                OpenAPI documentation

Mutations need `Authorization: Bearer <NAVI_API_TOKEN>`: 401 without credentials, 403 with a wrong
token, 503 while the service runs without a token (mutations are never open). Every alias move is
appended to the registry's audit log and announced as a ModelPromoted message.

Layout after the FastAPI template: models, dependencies (Annotated), plain functions over the
registry, one router per resource, `create_app` wires them.
"""

from __future__ import annotations

import secrets
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Request, Response, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, Field

from navi_contracts.models import ModelPromoted
from navi_learner.registry import LATEST, ModelEntry, ModelRegistry, RegistryError
from navi_mesh import metrics

# ---------------------------------------------------------------------------------------------
# Models


class ModelPublic(BaseModel):
    """One registered model version as the API shows it."""

    version: str
    file: str
    step_id: int
    reward_ema: float
    temporal_core: str
    training_source: str
    run_id: str
    created_at: str
    promoted_at: str
    source: str
    sha256: str
    notes: str
    tags: list[str]
    aliases: list[str] = Field(description="Aliases pointing at this version.")


class ModelsPublic(BaseModel):
    """Every version, oldest first, and the alias table."""

    data: list[ModelPublic]
    count: int
    aliases: dict[str, str]


class PromoteRequest(BaseModel):
    """Move `alias` to a checkpoint file (registered as a new immutable version) or to a version."""

    checkpoint: str = Field(min_length=1, description="A checkpoint path, a version (vNNN) or an alias.")
    alias: str = Field("champion", min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    notes: str = Field("", max_length=2000)
    tags: list[str] = Field(default_factory=list, max_length=32)


class RollbackRequest(BaseModel):
    """Move `alias` back to its previous version."""

    alias: str = Field("champion", min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")


class AliasMove(BaseModel):
    """What a promotion or rollback did."""

    alias: str
    version: str
    previous_version: str | None
    model: ModelPublic


class Health(BaseModel):
    """Service health."""

    status: str
    service: str
    mutations_enabled: bool
    uptime_s: float


# ---------------------------------------------------------------------------------------------
# Configuration and dependencies


Announce = Callable[[ModelPromoted], None]


@dataclass(frozen=True)
class ControlPlaneConfig:
    """What the control plane serves."""

    registry_root: Path = Path("artifacts/models")
    """The model registry folder (registry.json, vNNN.pt, audit.jsonl)."""
    api_token: str = ""
    """Bearer token for mutations; empty disables them (503)."""
    service: str = "learner"
    """Name reported by /healthz."""


@dataclass
class AppState:
    """Per-app state reached through the dependencies."""

    config: ControlPlaneConfig
    registry: ModelRegistry
    announce: Announce | None
    started: float


bearer = HTTPBearer(auto_error=False, description="NAVI_API_TOKEN")


def get_state(request: Request) -> AppState:
    state: AppState = request.app.state.navi
    return state


StateDep = Annotated[AppState, Depends(get_state)]


def require_token(
    state: StateDep, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
) -> None:
    """401 without a bearer token, 403 with a wrong one, 503 when the service has no token."""
    token = state.config.api_token
    if not token:
        raise HTTPException(
            status.HTTP_503_SERVICE_UNAVAILABLE, "mutations are disabled: NAVI_API_TOKEN is empty"
        )
    if credentials is None:
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED, "missing bearer token", headers={"WWW-Authenticate": "Bearer"}
        )
    if not secrets.compare_digest(credentials.credentials.encode(), token.encode()):
        raise HTTPException(status.HTTP_403_FORBIDDEN, "wrong bearer token")


Authorized = Annotated[None, Depends(require_token)]


# ---------------------------------------------------------------------------------------------
# Plain functions over the registry


def model_public(entry: ModelEntry, aliases: dict[str, str]) -> ModelPublic:
    """The API view of a registry entry."""
    raw = asdict(entry)
    raw["tags"] = list(entry.tags)
    return ModelPublic(**raw, aliases=sorted(a for a, v in aliases.items() if v == entry.version))


def list_models(registry: ModelRegistry) -> ModelsPublic:
    aliases = registry.aliases()
    data = [model_public(e, aliases) for e in registry.list()]
    return ModelsPublic(data=data, count=len(data), aliases=aliases)


def move_alias(
    state: AppState, alias: str, move: Callable[[], ModelEntry], action: str, notes: str, tags: list[str]
) -> AliasMove:
    """Run a registry alias move, count it and announce where the alias now points."""
    registry = state.registry
    before = registry.aliases().get(alias)
    try:
        move()
    except RegistryError as err:
        raise HTTPException(422, str(err)) from err
    aliases = registry.aliases()
    version = aliases[alias]
    entry = registry.get(version)
    metrics.PROMOTIONS.labels(action).inc()
    if state.announce is not None:
        state.announce(
            ModelPromoted(
                alias=alias,
                version=version,
                previous_version=before,
                checkpoint=str(registry.path(version).resolve()),
                notes=notes,
                tags=tuple(tags),
                timestamp=time.time(),
            )
        )
    return AliasMove(
        alias=alias, version=version, previous_version=before, model=model_public(entry, aliases)
    )


# ---------------------------------------------------------------------------------------------
# Routers

models_router = APIRouter(prefix="/models", tags=["models"])


@models_router.get("", response_model=ModelsPublic)
def read_models(state: StateDep) -> ModelsPublic:
    """Every registered version, oldest first, and the alias table."""
    return list_models(state.registry)


@models_router.get("/{version}", response_model=ModelPublic)
def read_model(version: str, state: StateDep) -> ModelPublic:
    """One version (vNNN) or alias."""
    try:
        entry = state.registry.get(version)
    except RegistryError as err:
        raise HTTPException(status.HTTP_404_NOT_FOUND, str(err)) from err
    return model_public(entry, state.registry.aliases())


@models_router.post("/promote", response_model=AliasMove)
def promote(body: PromoteRequest, state: StateDep, _: Authorized) -> AliasMove:
    """Register a checkpoint (or take an existing version) and point the alias at it."""

    def run() -> ModelEntry:
        return state.registry.promote(body.checkpoint, body.alias, body.notes, body.tags)

    return move_alias(state, body.alias, run, "promote", body.notes, body.tags)


@models_router.post("/rollback", response_model=AliasMove)
def rollback(body: RollbackRequest, state: StateDep, _: Authorized) -> AliasMove:
    """Point the alias back at its previous version."""

    def run() -> ModelEntry:
        return state.registry.rollback(body.alias)

    return move_alias(state, body.alias, run, "rollback", f"rollback of {body.alias}", [])


ops_router = APIRouter(tags=["operations"])


@ops_router.get("/healthz", response_model=Health)
def healthz(state: StateDep) -> Health:
    """The service is up; says whether mutations are enabled."""
    return Health(
        status="ok",
        service=state.config.service,
        mutations_enabled=bool(state.config.api_token),
        uptime_s=time.time() - state.started,
    )


@ops_router.get("/metrics", response_class=Response)
def prometheus_metrics() -> Response:
    """Prometheus text exposition of this process's navi_* metrics."""
    body, content_type = metrics.exposition()
    return Response(content=body, media_type=content_type)


def create_app(config: ControlPlaneConfig, announce: Announce | None = None) -> FastAPI:
    """The FastAPI app over the registry at config.registry_root."""
    app = FastAPI(
        title="Navi control plane",
        description="Model registry, health and metrics of the Navi learner service.",
        version="1",
        redirect_slashes=False,
    )
    app.state.navi = AppState(config, ModelRegistry(config.registry_root), announce, time.time())
    app.include_router(models_router)
    app.include_router(ops_router)
    return app


__all__ = ["LATEST", "ControlPlaneConfig", "create_app"]
