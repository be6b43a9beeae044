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

A write that fails (OSError: a full disk) leaves the last good state: no temporary file, no version
file the index does not list, no torn audit line. Damaged files found by `recover()` are renamed to
`<name>.corrupt-<UTC time>`, never deleted or overwritten: an unreadable registry.json is rebuilt
from the version files (their checkpoint metadata) and the audit log (aliases and their history); a
version file whose SHA-256 differs from the recorded one leaves the index, and an alias on it moves to
the best good version (latest) or its previous good one (others), with an audit line.
"""

from __future__ import annotations

import builtins
import fcntl
import hashlib
import json
import os
import re
import shutil
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from navi_learner.serving.checkpoint import (
    CheckpointError,
    CheckpointMeta,
    atomic_write,
    moved_aside,
    read_meta,
    utc_now,
)

LATEST = "latest"
VERSION_FILE = re.compile(r"v(\d+)\.pt(\.corrupt-.*)?")
"""A version file, or one moved aside (its number is never given to another version)."""


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


def parse_index(raw: bytes) -> dict[str, Any]:
    """A registry.json's content; ValueError when it is not a whole, well-formed index."""
    data = json.loads(raw)
    if not (
        isinstance(data, dict)
        and isinstance(data.get("versions"), list)
        and isinstance(data.get("aliases"), dict)
        and isinstance(data.get("history"), dict)
        and all(isinstance(v, dict) and {"version", "file", "sha256"} <= v.keys() for v in data["versions"])
    ):
        raise ValueError("not a registry index: versions, aliases and history are required")
    return data


def entry_of(
    meta: CheckpointMeta, path: Path, promoted_at: str, source: str, notes: str, tags: tuple[str, ...] = ()
) -> ModelEntry:
    """The registry entry of the version file `path` (vNNN.pt) holding a checkpoint with `meta`."""
    return ModelEntry(
        version=path.stem,
        file=path.name,
        step_id=meta.step_id,
        reward_ema=meta.reward_ema,
        temporal_core=meta.temporal_core,
        training_source=meta.training_source,
        run_id=meta.run_id,
        created_at=meta.created_at,
        promoted_at=promoted_at,
        source=source,
        sha256=sha256_of(path),
        notes=notes,
        tags=tags,
    )


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
        try:
            return parse_index(self.index_path.read_bytes())
        except ValueError as err:
            raise RegistryError(
                f"{self.index_path} is unreadable ({err}); ModelRegistry.recover() rebuilds it"
            ) from err

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
        """The audit log, oldest first (a line that does not parse, torn by a crash, is left out)."""
        if not self.audit_path.is_file():
            return []
        records = []
        for line in self.audit_path.read_text(errors="replace").splitlines():
            try:
                records.append(AuditRecord(**json.loads(line)))
            except (ValueError, TypeError):
                continue
        return records

    def _log(self, action: str, alias: str, before: str | None, after: str, notes: str) -> None:
        """Append one audit line; a failed write is cut off again, so the log ends at a whole line."""
        line = (
            json.dumps(asdict(AuditRecord(utc_now(), action, alias, before, after, notes))) + "\n"
        ).encode()
        fd = os.open(self.audit_path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            size = os.fstat(fd).st_size
            try:
                view = memoryview(line)
                while view:
                    view = view[os.write(fd, view) :]
            except OSError:
                os.ftruncate(fd, size)
                raise
        finally:
            os.close(fd)

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
        """After a writer was killed or a file was damaged: remove temporary files of interrupted writes,
        rebuild an unreadable registry.json, take versions whose file fails its SHA-256 out of the index
        (moved aside, their aliases moved on), add the audit line of a move the index holds but the log
        lacks, re-copy latest.pt when it is not the latest version. Returns what it did, one line per
        file (empty when the registry was consistent)."""
        if not self.root.is_dir():
            return []
        done: builtins.list[str] = []
        with self._locked():
            for tmp in sorted(self.root.glob(".*.tmp")):
                tmp.unlink(missing_ok=True)
                done.append(f"removed {tmp.name}")
            try:
                data = self._read()
            except RegistryError as err:
                aside = moved_aside(self.index_path)
                data = self._rebuild(done)
                self._write(data)
                done.append(
                    f"{self.index_path.name} is unreadable ({err.__cause__}): moved to {aside.name}, "
                    f"index rebuilt from {len(data['versions'])} version file(s) and {self.audit_path.name}"
                )
            self._drop_bad_versions(data, done)
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

    def _drop_bad_versions(self, data: dict[str, Any], done: builtins.list[str]) -> None:
        """Take versions whose file is missing or fails its recorded SHA-256 out of `data` (the file is
        moved aside); move an alias on one to the best good version (latest) or its previous good one,
        with an audit line; write the index and latest.pt when anything changed. One line per file."""
        bad: dict[str, str] = {}  # version -> what became of its file
        for entry in data["versions"]:
            path = self.root / entry["file"]
            if not path.is_file():
                bad[entry["version"]] = f"{path.name} is missing"
            elif sha256_of(path) != entry["sha256"]:
                aside = moved_aside(path)
                bad[entry["version"]] = (
                    f"{path.name} fails its sha256 (the file changed after it was registered): moved to "
                    f"{aside.name}"
                )
        if not bad:
            return
        data["versions"] = [v for v in data["versions"] if v["version"] not in bad]
        data["history"] = {
            alias: kept for alias, h in data["history"].items() if (kept := [v for v in h if v not in bad])
        }
        outcome = {version: [f"{version} leaves the index"] for version in bad}
        moves: builtins.list[tuple[str, str, str]] = []
        for alias, version in sorted(data["aliases"].items()):
            if version not in bad:
                continue
            if alias == LATEST and data["versions"]:
                after = max(reversed(data["versions"]), key=lambda v: v["reward_ema"])["version"]
            elif alias != LATEST and data["history"].get(alias):
                after = data["history"][alias].pop()
            else:
                del data["aliases"][alias]
                outcome[version].append(f"alias {alias} removed (no good version to point it at)")
                continue
            data["aliases"][alias] = after
            moves.append((alias, version, after))
            outcome[version].append(f"{alias} -> {after}")
        self._write(data)
        for alias, before, after in moves:
            self._log("recover", alias, before, after, f"the file of {before} is missing or fails its sha256")
        self._sync_latest(data)
        done += [f"{line}; {', '.join(outcome[version])}" for version, line in bad.items()]

    def _rebuild(self, done: builtins.list[str]) -> dict[str, Any]:
        """An index from the version files and the audit log: each vNNN.pt that loads and verifies (its
        entry from its checkpoint metadata; promoted_at is the file's time, source and tags are not
        kept anywhere else and stay blank), the aliases and their history replayed from the audit log
        (latest: the best reward_ema when the log has none). A file that does not load is moved aside."""
        records = self.audit()
        versions: builtins.list[dict[str, Any]] = []
        files = [p for p in self.root.glob("v*.pt") if VERSION_FILE.fullmatch(p.name)]
        for path in sorted(files, key=lambda p: int(p.name[1:-3])):
            try:
                meta = read_meta(path)
            except CheckpointError as err:
                aside = moved_aside(path)
                done.append(f"{path.name} is not a loadable checkpoint ({err}): moved to {aside.name}")
                continue
            version = path.stem
            promoted = datetime.fromtimestamp(path.stat().st_mtime, UTC).isoformat(timespec="seconds")
            notes = next((r.notes for r in records if r.to_version == version and r.action == "promote"), "")
            entry = entry_of(meta, path, promoted, "", notes)
            versions.append({**asdict(entry), "tags": []})
        known = {v["version"] for v in versions}
        aliases: dict[str, str] = {}
        history: dict[str, builtins.list[str]] = {}
        for r in records:  # the moves as _point made them
            if r.action == "rollback":
                if history.get(r.alias) and history[r.alias][-1] == r.to_version:
                    history[r.alias].pop()
            elif r.from_version is not None:
                history.setdefault(r.alias, []).append(r.from_version)
            aliases[r.alias] = r.to_version
        aliases = {a: v for a, v in aliases.items() if v in known}
        if versions and LATEST not in aliases:
            aliases[LATEST] = max(reversed(versions), key=lambda v: v["reward_ema"])["version"]
        history = {a: kept for a, h in history.items() if (kept := [v for v in h if v in known])}
        return {"versions": versions, "aliases": aliases, "history": history}

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
        on_disk = (m.group(1) for p in self.root.iterdir() if (m := VERSION_FILE.fullmatch(p.name)))
        number = 1 + max((*(int(v["version"][1:]) for v in data["versions"]), *map(int, on_disk)), default=0)
        version = f"v{number:03d}"
        dest = self.root / f"{version}.pt"

        def copy(f: Any) -> None:
            with checkpoint.open("rb") as s:
                shutil.copyfileobj(s, f)

        atomic_write(dest, copy)
        entry = entry_of(meta, dest, utc_now(), str(checkpoint), notes, tuple(tags))
        data["versions"].append({**asdict(entry), "tags": list(entry.tags)})
        return version

    def promote(
        self, checkpoint: Path | str, alias: str = LATEST, notes: str = "", tags: Sequence[str] = ()
    ) -> ModelEntry:
        """Register a checkpoint file as a new immutable version (or take an existing vNNN/alias) and
        point `alias` at it. `latest` always ends on the best reward_ema of all versions; any other
        alias points exactly at the promoted version. Returns the promoted entry.

        An OSError (a full disk) leaves the registry as it was: a new version file the index did not
        take is removed again."""
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
            try:
                self._commit(data, move)
            except OSError:
                if version not in known and version not in {v["version"] for v in self._read()["versions"]}:
                    (self.root / f"{version}.pt").unlink(missing_ok=True)
                raise
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
