"""The learner's REST control plane (FastAPI): the model registry over HTTP, health and metrics.

    GET  /models              every version, with the aliases
    GET  /models/{version}    one version (vNNN) or alias (latest, champion, ...)
    POST /models/promote      register a checkpoint (or take a version) and move an alias to it
    POST /models/rollback     move an alias back to where it pointed before its last move
    GET  /healthz             liveness and whether mutations are enabled
    GET  /metrics             Prometheus text format (this exact path, no redirect)
    GET  /docs                OpenAPI documentation

Mutations need `Authorization: Bearer <NAVI_API_TOKEN>`: 401 without credentials, 403 with a wrong
token. The app refuses to be built with mutations enabled and no token (`ControlPlaneError`); a
read-only control plane (`read_only=True`, `navi serve learner --read-only`) starts without one and
answers every mutation 503. Every alias move is appended to the registry's audit log and announced as
a ModelPromoted message.

Bad input is a 4xx, never a 500: request bodies over `MAX_BODY_BYTES` get 413, a checkpoint that is
not a regular readable file (or whose path cannot exist: NUL, unpaired surrogates, over-long names)
gets 422, and the API reads arbitrary paths only to copy a valid checkpoint into the registry; it
writes nowhere else.

Layout after the FastAPI template: models, dependencies (Annotated), plain functions over the
registry, one router per resource, `create_app` wires them.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import stat
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Request, Response, status
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import AfterValidator, BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from navi_contracts.models import ModelPromoted
from navi_learner.serving.checkpoint import read_meta
from navi_learner.serving.registry import LATEST, ModelEntry, ModelRegistry, RegistryError
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


MAX_BODY_BYTES = 64 * 1024
"""Largest request body the control plane reads (413 beyond)."""
MAX_PATH_BYTES = 4096
"""Longest checkpoint path accepted (the Linux PATH_MAX)."""


def _path_text(value: str) -> str:
    """A string that can name a file: no NUL, encodable to bytes (no unpaired surrogates)."""
    if "\x00" in value:
        raise ValueError("must not contain a NUL character")
    try:
        encoded = os.fsencode(value)
    except UnicodeEncodeError as err:
        raise ValueError("must be valid Unicode (no unpaired surrogates)") from err
    if len(encoded) > MAX_PATH_BYTES:
        raise ValueError(f"must be at most {MAX_PATH_BYTES} bytes")
    return value


def _plain_text(value: str) -> str:
    """Text stored in the registry and the audit log: valid Unicode, no NUL."""
    if "\x00" in value:
        raise ValueError("must not contain a NUL character")
    try:
        value.encode()
    except UnicodeEncodeError as err:
        raise ValueError("must be valid Unicode (no unpaired surrogates)") from err
    return value


PathText = Annotated[str, AfterValidator(_path_text)]
PlainText = Annotated[str, AfterValidator(_plain_text)]
Tag = Annotated[str, Field(min_length=1, max_length=64), AfterValidator(_plain_text)]
Alias = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")]


class PromoteRequest(BaseModel):
    """Move `alias` to a checkpoint file (registered as a new immutable version) or to a version."""

    checkpoint: PathText = Field(
        min_length=1, description="A checkpoint path (as the server sees it), a version (vNNN) or an alias."
    )
    alias: Alias = "champion"
    notes: PlainText = Field("", max_length=2000)
    tags: list[Tag] = Field(default_factory=list, max_length=32)


class RollbackRequest(BaseModel):
    """Move `alias` back to its previous version."""

    alias: Alias = "champion"


class AliasMove(BaseModel):
    """What a promotion or rollback did."""

    alias: str
    version: str
    previous_version: str | None
    model: ModelPublic


class CorpusProgress(BaseModel):
    """The corpus the service needs, while it is being built (and after)."""

    path: str
    state: str = Field(description="missing, waiting (for a compiler worker), building, ready or failed.")
    scenes_ready: int = Field(description="Scenes compiled and qualified so far.")
    scenes_total: int = Field(description="Scenes the build makes (0 when unknown).")
    rejected: int = Field(0, description="Scenes that failed qualification.")
    error: str = ""


class Health(BaseModel):
    """Service health; the learner adds what it is doing (phase) and its corpus build."""

    status: str
    service: str
    mutations_enabled: bool
    uptime_s: float
    phase: str = Field(
        "", description="starting, corpus, training, inference, done or failed ('' if unknown)."
    )
    run_id: str = ""
    actors: int = 0
    step: int = Field(0, description="Env steps of the run so far (at its newest log row), across resumes.")
    start_step: int = Field(0, description="Env steps the run resumed from (0: it started from scratch).")
    corpus: CorpusProgress | None = None


# ---------------------------------------------------------------------------------------------
# Configuration and dependencies


Announce = Callable[[ModelPromoted], None]
StatusSource = Callable[[], dict[str, Any]]
"""Extra /healthz fields of the running service (phase, run_id, actors, corpus)."""


class ControlPlaneError(ValueError):
    """The control plane cannot start as configured (mutations enabled without a token)."""


@dataclass(frozen=True)
class ControlPlaneConfig:
    """What the control plane serves."""

    registry_root: Path = Path("artifacts/models")
    """The model registry folder (registry.json, vNNN.pt, audit.jsonl)."""
    api_token: str = ""
    """Bearer token for mutations; required unless read_only."""
    service: str = "learner"
    """Name reported by /healthz."""
    read_only: bool = False
    """Serve the registry read-only: every mutation answers 503 and no token is needed."""

    def check(self) -> None:
        """ControlPlaneError when mutations are enabled without a token."""
        if not self.read_only and not self.api_token:
            raise ControlPlaneError(
                "refusing to start the control plane: mutations are enabled but NAVI_API_TOKEN is empty; "
                "set NAVI_API_TOKEN (e.g. in .env), or start read-only with --read-only"
            )


@dataclass
class AppState:
    """Per-app state reached through the dependencies."""

    config: ControlPlaneConfig
    registry: ModelRegistry
    announce: Announce | None
    started: float
    status: StatusSource | None = None


bearer = HTTPBearer(auto_error=False, description="NAVI_API_TOKEN")


def get_state(request: Request) -> AppState:
    state: AppState = request.app.state.navi
    return state


StateDep = Annotated[AppState, Depends(get_state)]


def require_token(
    state: StateDep, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
) -> None:
    """401 without a bearer token, 403 with a wrong one, 503 on a read-only control plane."""
    token = state.config.api_token
    if state.config.read_only or not token:
        raise HTTPException(
            status.HTTP_503_SERVICE_UNAVAILABLE, "mutations are disabled: the control plane is read-only"
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


def checkpoint_source(registry: ModelRegistry, name: str) -> None:
    """422 unless `name` is a known version or alias, or a regular readable file that loads as a v3
    checkpoint (a FIFO, device or folder is refused before anything opens it; whatever way an
    arbitrary file fails to unpickle, it is the request that is wrong)."""
    if name in registry.aliases() or any(e.version == name for e in registry.list()):
        return
    try:
        info = os.stat(name)
    except (OSError, ValueError) as err:
        raise HTTPException(
            422, f"{name!r} is neither a model version nor a readable checkpoint file: {err}"
        ) from err
    if not stat.S_ISREG(info.st_mode) or not os.access(name, os.R_OK):
        raise HTTPException(
            422, f"{name!r} is neither a model version nor a regular readable checkpoint file"
        )
    try:
        read_meta(Path(name))
    except Exception as err:  # untrusted bytes: any failure to load them is the request's fault
        raise HTTPException(422, f"{name!r} is not a loadable checkpoint: {type(err).__name__}") from err


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

    checkpoint_source(state.registry, body.checkpoint)

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
    """The service is up; says whether mutations are enabled, what the service is doing (phase) and how
    far the build of its corpus is."""
    extra = state.status() if state.status is not None else {}
    return Health(
        status="ok",
        service=state.config.service,
        mutations_enabled=bool(state.config.api_token) and not state.config.read_only,
        uptime_s=time.time() - state.started,
        **extra,
    )


@ops_router.get("/metrics", response_class=Response)
def prometheus_metrics() -> Response:
    """Prometheus text exposition of the learner's metrics (training, promotions, corpus, the mesh)."""
    body, content_type = metrics.exposition("learner")
    return Response(content=body, media_type=content_type)


class BodyLimit:
    """ASGI middleware: 413 for a request body over `limit` bytes (declared or streamed), read no further."""

    def __init__(self, app: ASGIApp, limit: int = MAX_BODY_BYTES) -> None:
        self.app, self.limit = app, limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > self.limit):
            await self._refuse(send)
            return
        seen, too_large, started = 0, False, False

        async def counted() -> Message:
            nonlocal seen, too_large
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    too_large = True
                    raise _TooLarge
            return message

        async def guarded(message: Message) -> None:
            # The app may catch _TooLarge while parsing the body (FastAPI answers 400 then): once the
            # limit is passed, its response is dropped and the 413 goes out instead.
            nonlocal started
            if too_large:
                return
            started = True
            await send(message)

        with contextlib.suppress(_TooLarge):  # raised through an app that does not catch it
            await self.app(scope, counted, guarded)
        if too_large and not started:
            await self._refuse(send)

    async def _refuse(self, send: Send) -> None:
        body = f'{{"detail":"request body over {self.limit} bytes"}}'.encode()
        await send(
            {
                "type": "http.response.start",
                "status": 413,
                "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode()),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})


class _TooLarge(Exception):
    pass


class CountRefusals:
    """ASGI middleware (outermost): every 4xx answer counted in navi_refused_requests_total{status}, the
    body limit's 413 included."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def counting(message: Message) -> None:
            if message["type"] == "http.response.start" and 400 <= int(message["status"]) < 500:
                metrics.REFUSED_REQUESTS.labels(str(message["status"])).inc()
            await send(message)

        await self.app(scope, receive, counting)


def _plain(value: Any) -> Any:
    """Echoed request input made JSON-safe: bytes (a body that is not UTF-8) become escaped text."""
    if isinstance(value, bytes | bytearray):
        return bytes(value).decode("utf-8", "backslashreplace")
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def _ascii_json(status_code: int, body: Any, headers: dict[str, str] | None = None) -> Response:
    """A JSON response with every non-ASCII character escaped: an echoed input holding an unpaired
    surrogate (valid JSON, not valid UTF-8) or raw bytes cannot break the encoding of the error reply."""
    text = json.dumps(jsonable_encoder(_plain(body)), ensure_ascii=True, default=repr, separators=(",", ":"))
    return Response(text, status_code, headers=headers, media_type="application/json")


async def _invalid_request(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, RequestValidationError)
    return _ascii_json(422, {"detail": exc.errors()})


async def _http_error(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, StarletteHTTPException)
    return _ascii_json(exc.status_code, {"detail": exc.detail}, getattr(exc, "headers", None))


def create_app(
    config: ControlPlaneConfig, announce: Announce | None = None, status_source: StatusSource | None = None
) -> FastAPI:
    """The FastAPI app over the registry at config.registry_root.

    Raises ControlPlaneError when mutations are enabled without a token (see ControlPlaneConfig.check).
    `status_source` adds the service's phase, run and corpus progress to /healthz."""
    config.check()
    app = FastAPI(
        title="Navi control plane",
        description="Model registry, health and metrics of the Navi learner service.",
        version="1",
        redirect_slashes=False,
    )
    app.state.navi = AppState(
        config, ModelRegistry(config.registry_root), announce, time.time(), status_source
    )
    app.include_router(models_router)
    app.include_router(ops_router)
    app.add_exception_handler(RequestValidationError, _invalid_request)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_middleware(BodyLimit, limit=MAX_BODY_BYTES)
    app.add_middleware(CountRefusals)  # added last: outermost, it sees the body limit's answers too
    return app


__all__ = ["LATEST", "ControlPlaneConfig", "ControlPlaneError", "create_app"]
