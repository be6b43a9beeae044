"""Model registry on disk: immutable vNNN.pt copies, aliases, an append-only audit log.

Layout under `root` (default artifacts/models):
  registry.json   {"versions": [ModelEntry...], "aliases": {alias: version}, "history": {alias: [versions]}}
  vNNN.pt         immutable copies of promoted checkpoints
  latest.pt       a copy of the version the `latest` alias points at (the best reward_ema)
  audit.jsonl     one line per alias move: when, action, alias, from, to, notes
Every file is written atomically; a lock file serialises writers (the REST control plane shares this API).
A move writes the new index first and appends its audit line after, so registry.json is the truth: a
writer killed at any instant leaves an index whose every version file is complete, and at most one
audit line or the latest.pt copy behind it. `recover()` (run by the learner service at start) brings
those back in line and removes temporary files of interrupted writes.
"""

from __future__ import annotations

import builtins
import fcntl
import hashlib
import json
import shutil
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from navi_learner.serving.checkpoint import CheckpointError, atomic_write, read_meta, utc_now

LATEST = "latest"


class RegistryError(ValueError):
    """An unknown version or alias, or a bad checkpoint."""


@dataclass(frozen=True)
class ModelEntry:
    """One registered model version."""

    version: str
    """vNNN."""
    file: str
    """File name inside the registry root (vNNN.pt)."""
    step_id: int
    reward_ema: float
    temporal_core: str
    training_source: str
    run_id: str
    created_at: str
    """When the checkpoint was written."""
    promoted_at: str
    """When it entered the registry."""
    source: str
    """The path it was promoted from."""
    sha256: str
    notes: str = ""
    tags: tuple[str, ...] = ()


@dataclass(frozen=True)
class AuditRecord:
    """One alias move."""

    when: str
    action: str
    alias: str
    from_version: str | None
    to_version: str
    notes: str


def sha256_of(path: Path) -> str:
    """Hex SHA-256 of a file."""
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


class ModelRegistry:
    """The on-disk model store."""

    def __init__(self, root: Path = Path("artifacts/models")) -> None:
        self.root = Path(root)

    @property
    def index_path(self) -> Path:
        return self.root / "registry.json"

    @property
    def audit_path(self) -> Path:
        return self.root / "audit.jsonl"

    @property
    def latest_path(self) -> Path:
        return self.root / "latest.pt"

    @contextmanager
    def _locked(self) -> Iterator[None]:
        self.root.mkdir(parents=True, exist_ok=True)
        with (self.root / ".registry.lock").open("w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)

    def _read(self) -> dict[str, Any]:
        if not self.index_path.is_file():
            return {"versions": [], "aliases": {}, "history": {}}
        data: dict[str, Any] = json.loads(self.index_path.read_text())
        return data

    def _write(self, data: dict[str, Any]) -> None:
        text = json.dumps(data, indent=2, sort_keys=True).encode()
        atomic_write(self.index_path, lambda f: f.write(text))

    @staticmethod
    def _entry(raw: dict[str, Any]) -> ModelEntry:
        return ModelEntry(**{**raw, "tags": tuple(raw.get("tags", ()))})

    def list(self) -> list[ModelEntry]:
        """All versions, oldest first."""
        return [self._entry(v) for v in self._read()["versions"]]

    def aliases(self) -> dict[str, str]:
        """alias -> version."""
        return dict(self._read()["aliases"])

    def get(self, version: str) -> ModelEntry:
        """A version (vNNN) or an alias (latest, champion, ...)."""
        data = self._read()
        version = data["aliases"].get(version, version)
        for raw in data["versions"]:
            if raw["version"] == version:
                return self._entry(raw)
        raise RegistryError(f"no model version or alias {version!r} in {self.root}")

    def path(self, version: str) -> Path:
        """The file of a version or alias."""
        return self.root / self.get(version).file

    def best(self) -> ModelEntry | None:
        """The version with the highest reward_ema (the newest among ties), or None when empty."""
        entries = self.list()
        return max(reversed(entries), key=lambda e: e.reward_ema) if entries else None

    def audit(self) -> builtins.list[AuditRecord]:
        """The audit log, oldest first."""
        if not self.audit_path.is_file():
            return []
        return [AuditRecord(**json.loads(line)) for line in self.audit_path.read_text().splitlines() if line]

    def _log(self, action: str, alias: str, before: str | None, after: str, notes: str) -> None:
        record = AuditRecord(utc_now(), action, alias, before, after, notes)
        with self.audit_path.open("a") as f:
            f.write(json.dumps(asdict(record)) + "\n")
            f.flush()

    def _point(
        self, data: dict[str, Any], alias: str, version: str, action: str, notes: str
    ) -> tuple[str, str, str | None, str, str] | None:
        """Move the alias in `data`; returns the audit record to append once the index is written."""
        before = data["aliases"].get(alias)
        if before == version:
            return None
        data["aliases"][alias] = version
        if action != "rollback" and before is not None:
            data["history"].setdefault(alias, []).append(before)
        return (action, alias, before, version, notes)

    def _commit(self, data: dict[str, Any], move: tuple[str, str, str | None, str, str] | None) -> None:
        """Write the index, then the audit line of the move, then the latest.pt copy."""
        self._write(data)
        if move is not None:
            self._log(*move)
        self._sync_latest(data)

    def recover(self) -> builtins.list[str]:
        """After a writer was killed: remove temporary files of interrupted writes, add the audit line of
        a move the index holds but the log lacks, re-copy latest.pt when it is not the latest version.
        Returns what it did (empty when the registry was consistent)."""
        if not self.root.is_dir():
            return []
        done: builtins.list[str] = []
        with self._locked():
            for tmp in sorted(self.root.glob(".*.tmp")):
                tmp.unlink(missing_ok=True)
                done.append(f"removed {tmp.name}")
            data = self._read()
            logged: dict[str, str] = {}
            for record in self.audit():
                logged[record.alias] = record.to_version
            for alias, version in sorted(data["aliases"].items()):
                if logged.get(alias) != version:
                    self._log(
                        "recover", alias, logged.get(alias), version, "audit line of an interrupted move"
                    )
                    done.append(f"audit line for {alias} -> {version}")
            latest = data["aliases"].get(LATEST)
            if latest is not None:
                want = next(v["sha256"] for v in data["versions"] if v["version"] == latest)
                if not self.latest_path.is_file() or sha256_of(self.latest_path) != want:
                    self._sync_latest(data)
                    done.append(f"latest.pt re-copied from {latest}")
        return done

    def _sync_latest(self, data: dict[str, Any]) -> None:
        version = data["aliases"].get(LATEST)
        if version is None:
            return
        src = self.root / f"{version}.pt"

        def copy(f: Any) -> None:
            with src.open("rb") as s:
                shutil.copyfileobj(s, f)

        atomic_write(self.latest_path, copy)

    def _register(self, data: dict[str, Any], checkpoint: Path, notes: str, tags: Sequence[str]) -> str:
        try:
            meta = read_meta(checkpoint)
        except CheckpointError as err:
            raise RegistryError(str(err)) from err
        number = 1 + max((int(v["version"][1:]) for v in data["versions"]), default=0)
        version = f"v{number:03d}"
        dest = self.root / f"{version}.pt"

        def copy(f: Any) -> None:
            with checkpoint.open("rb") as s:
                shutil.copyfileobj(s, f)

        atomic_write(dest, copy)
        entry = ModelEntry(
            version=version,
            file=dest.name,
            step_id=meta.step_id,
            reward_ema=meta.reward_ema,
            temporal_core=meta.temporal_core,
            training_source=meta.training_source,
            run_id=meta.run_id,
            created_at=meta.created_at,
            promoted_at=utc_now(),
            source=str(checkpoint),
            sha256=sha256_of(dest),
            notes=notes,
            tags=tuple(tags),
        )
        data["versions"].append({**asdict(entry), "tags": list(entry.tags)})
        return version

    def promote(
        self, checkpoint: Path | str, alias: str = LATEST, notes: str = "", tags: Sequence[str] = ()
    ) -> ModelEntry:
        """Register a checkpoint file as a new immutable version (or take an existing vNNN/alias) and
        point `alias` at it. `latest` always ends on the best reward_ema of all versions; any other
        alias points exactly at the promoted version. Returns the promoted entry."""
        with self._locked():
            data = self._read()
            known = {v["version"] for v in data["versions"]}
            name = data["aliases"].get(str(checkpoint), str(checkpoint))
            version = name if name in known else self._register(data, Path(checkpoint), notes, tags)
            if alias == LATEST:
                best = max(reversed(data["versions"]), key=lambda v: v["reward_ema"])["version"]
                move = self._point(data, LATEST, best, "promote", notes)
            else:
                move = self._point(data, alias, version, "promote", notes)
            self._commit(data, move)
            return self.get(version)

    def maybe_promote(self, checkpoint: Path, notes: str = "", tags: Sequence[str] = ()) -> ModelEntry | None:
        """Promote only when the checkpoint's reward_ema beats the current best (auto-promote)."""
        best = self.best()
        if best is not None and read_meta(checkpoint).reward_ema <= best.reward_ema:
            return None
        return self.promote(checkpoint, LATEST, notes, tags)

    def rollback(self, alias: str = LATEST) -> ModelEntry:
        """Point alias back at the version it pointed at before its last move."""
        with self._locked():
            data = self._read()
            history = data["history"].get(alias, [])
            if not history:
                raise RegistryError(f"alias {alias!r} has no previous version to roll back to")
            previous = history.pop()
            move = self._point(data, alias, previous, "rollback", f"rollback of {alias}")
            self._commit(data, move)
            return self.get(previous)
