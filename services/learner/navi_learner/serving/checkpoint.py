"""Checkpoint format v3: weights, optimizer, counters, lineage and the full config in one file.

Written atomically (temporary file in the same folder, fsync, os.replace, fsync of the folder) and
loadable with torch.load(weights_only=True): it holds only tensors, dicts, lists, str, int, float,
bool and None. Any other format_version fails fast with CheckpointError.

`meta.sha256` is a SHA-256 over the whole payload (every tensor's dtype, shape and bytes, and every
other value) with that field blank; `load_checkpoint` recomputes it, so a flipped byte that torch's
loader reads without complaint fails as a CheckpointError naming the file. Checkpoints written before
the checksum have it blank and load unverified.
"""

from __future__ import annotations

import hashlib
import logging
import os
import pickle
import struct
import subprocess
import tempfile
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Any

import torch

FORMAT_VERSION = 3
log = logging.getLogger(__name__)


class CheckpointError(ValueError):
    """A file that is not a loadable v3 checkpoint."""


@dataclass
class CheckpointMeta:
    """Everything in a checkpoint except the weights and optimizer state."""

    step_id: int
    """Env steps (actor-steps) trained so far, across resumes."""
    episode_count: int
    """Finished episodes so far, across resumes."""
    reward_ema: float
    """EMA of the mean extrinsic reward per actor-step (higher is better; the registry ranks by it)."""
    wall_time_hours: float
    """Training wall time so far, across resumes."""
    temporal_core: str
    """mamba2, gru or mambapy."""
    run_id: str
    """The run that wrote this checkpoint."""
    config: dict[str, Any]
    """TrainConfig.to_dict() of that run."""
    obs_shape: list[int]
    """(3, Az, El) the policy was built for."""
    parent_checkpoint: str | None = None
    """The checkpoint this run resumed from (lineage), or None."""
    training_source: str = "rl"
    """rl or bc."""
    corpus_summary: dict[str, Any] = field(default_factory=dict)
    """What the run trained on (paths, scene count, ...), plain values only."""
    code_version: str = ""
    """navi-learner version and git commit."""
    created_at: str = ""
    """UTC ISO-8601 time of writing."""
    sha256: str = ""
    """SHA-256 of the payload with this field blank (payload_sha256); blank in older checkpoints."""


@dataclass
class Checkpoint:
    """A loaded checkpoint."""

    model: dict[str, torch.Tensor]
    optimizer: dict[str, Any] | None
    meta: CheckpointMeta


def code_version() -> str:
    """'navi-learner <version> (<commit>)'; the commit is 'unknown' outside a git checkout."""
    try:
        version = metadata.version("navi-learner")
    except metadata.PackageNotFoundError:
        version = "0+local"
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short=12", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
            check=True,
        )
        commit = out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        commit = "unknown"
    return f"navi-learner {version} ({commit})"


def utc_now() -> str:
    """Current UTC time, ISO-8601 with seconds."""
    return datetime.now(UTC).isoformat(timespec="seconds")


def fsync_dir(folder: Path) -> None:
    """Make a rename in folder durable."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(path: Path, write: Any) -> None:
    """Call write(file) on a temporary file next to path, fsync it, then os.replace it onto path.

    A crash at any point leaves either the old file or the new one, never a half-written file; the
    temporary file is removed when any step fails (the write, the flush, the fsync, the rename: a full
    disk raises OSError ENOSPC at any of them), and the old file stays as it was.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        try:
            f = os.fdopen(fd, "wb")
        except BaseException:
            os.close(fd)
            raise
        with f:
            os.fchmod(fd, 0o644)  # mkstemp makes 0600; a scene/model file is meant to be shared
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)


def os_reason(err: OSError) -> str:
    """An OSError without its file name, for a log line: '[Errno 28] No space left on device'."""
    return f"[Errno {err.errno}] {err.strerror}" if err.errno and err.strerror else str(err)


def count_write_error(what: str) -> None:
    """navi_write_errors_total{what} += 1 where the service mesh is installed (the learner service);
    the training core alone has no Prometheus metrics and counts nothing."""
    try:
        from navi_mesh.metrics import WRITE_ERRORS
    except ImportError:
        return
    WRITE_ERRORS.labels(what).inc()


def moved_aside(path: Path) -> Path:
    """Rename a bad file (or folder) to `<name>.corrupt-<UTC time>` next to it, never over another file;
    returns the new path."""
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    dest = path.with_name(f"{path.name}.corrupt-{stamp}")
    n = 1
    while dest.exists():
        n += 1
        dest = path.with_name(f"{path.name}.corrupt-{stamp}-{n}")
    os.rename(path, dest)
    fsync_dir(path.parent)
    return dest


def _digest(h: Any, value: Any) -> None:
    """Feed a payload into a hash in a canonical order: tagged, length-prefixed, dict keys sorted."""
    if isinstance(value, torch.Tensor):
        t = value.detach().cpu().contiguous().reshape(-1)  # (numel,) any dtype
        h.update(f"T{t.dtype}:{tuple(value.shape)}:".encode())
        h.update(t.view(torch.uint8).numpy())  # (numel * itemsize,) uint8
    elif isinstance(value, dict):
        h.update(f"D{len(value)}:".encode())
        for key in sorted(value, key=lambda k: (type(k).__name__, str(k))):
            _digest(h, key)
            _digest(h, value[key])
    elif isinstance(value, list | tuple):
        h.update(f"L{len(value)}:".encode())
        for item in value:
            _digest(h, item)
    elif isinstance(value, str):
        raw = value.encode("utf-8", "surrogatepass")
        h.update(f"S{len(raw)}:".encode())
        h.update(raw)
    else:  # bool, int, float, None (repr is exact for each)
        h.update(f"{type(value).__name__}:{value!r};".encode())


def payload_sha256(payload: dict[str, Any]) -> str:
    """Hex SHA-256 of a checkpoint payload with meta.sha256 blank."""
    h = hashlib.sha256()
    _digest(h, {**payload, "meta": {**payload["meta"], "sha256": ""}})
    return h.hexdigest()


def save_checkpoint(
    path: Path, model: dict[str, torch.Tensor], optimizer: dict[str, Any] | None, meta: CheckpointMeta
) -> Path:
    """Write a v3 checkpoint atomically; returns path."""
    meta = CheckpointMeta(
        **{
            **asdict(meta),
            "created_at": meta.created_at or utc_now(),
            "code_version": meta.code_version or code_version(),
            "sha256": "",
        }
    )
    fields = asdict(meta)
    payload: dict[str, Any] = {
        "format_version": FORMAT_VERSION,
        "model": {k: v.detach().cpu() for k, v in model.items()},
        "optimizer": optimizer,
        "meta": fields,
    }
    fields["sha256"] = payload_sha256(payload)
    atomic_write(path, lambda f: torch.save(payload, f))
    return path


def load_checkpoint(path: Path, map_location: str | torch.device = "cpu") -> Checkpoint:
    """Load a v3 checkpoint with weights_only=True; CheckpointError for anything else."""
    if not Path(path).is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except (
        RuntimeError,
        EOFError,
        OSError,
        ValueError,
        IndexError,
        KeyError,
        pickle.UnpicklingError,
        struct.error,
    ) as err:  # torch's unpickler raises any of these on a file that is not a checkpoint
        reason = (str(err).strip().splitlines() or [type(err).__name__])[0]  # torch adds lines of advice
        raise CheckpointError(f"{path} is not a loadable checkpoint: {reason}") from err
    if not isinstance(payload, dict) or "format_version" not in payload:
        raise CheckpointError(
            f"{path} has no format_version; only v{FORMAT_VERSION} checkpoints are accepted"
        )
    if payload["format_version"] != FORMAT_VERSION:
        raise CheckpointError(
            f"{path} is checkpoint format v{payload['format_version']}; only v{FORMAT_VERSION} is accepted"
        )
    try:
        meta = CheckpointMeta(**payload["meta"])
    except TypeError as err:
        raise CheckpointError(f"{path} has malformed metadata: {err}") from err
    if meta.sha256 and payload_sha256(payload) != meta.sha256:
        raise CheckpointError(f"{path} fails its checksum: the file changed after it was written")
    return Checkpoint(model=payload["model"], optimizer=payload["optimizer"], meta=meta)


def read_meta(path: Path) -> CheckpointMeta:
    """The metadata of a checkpoint (loads the file on the CPU)."""
    return load_checkpoint(path).meta


def checkpoint_name(step_id: int) -> str:
    """File name of the checkpoint at a step: ckpt_step_0000123456.pt."""
    return f"ckpt_step_{step_id:010d}.pt"


RUN_CHECKPOINTS = "*/checkpoints/ckpt_step_*.pt"
"""Every run's checkpoints, relative to a runs folder."""


def newest_good_checkpoint(folder: Path, pattern: str = "ckpt_step_*.pt") -> Path | None:
    """The newest checkpoint (by step) matching `pattern` in a run folder (or its checkpoints/ folder)
    that loads and verifies; logs one line for each newer one it skips. None when none does. A runs
    folder takes RUN_CHECKPOINTS."""
    folder = Path(folder)
    if (folder / "checkpoints").is_dir():
        folder = folder / "checkpoints"
    for path in sorted(folder.glob(pattern), key=lambda p: (p.name, str(p)), reverse=True):
        try:
            load_checkpoint(path)
        except CheckpointError as err:
            log.error("%s (skipped: an older checkpoint is tried)", err)
            continue
        return path
    return None


def prune_checkpoints(folder: Path, keep: int) -> list[Path]:
    """Delete all but the newest `keep` ckpt_step_*.pt in folder (by step), and temp files that a killed
    save left behind (.ckpt_step_*.tmp; the folder has one writer); returns the deleted paths."""
    found = sorted(folder.glob("ckpt_step_*.pt"))
    doomed = found[: max(0, len(found) - keep)] + sorted(folder.glob(".ckpt_step_*.tmp"))
    for p in doomed:
        p.unlink(missing_ok=True)
    return doomed
