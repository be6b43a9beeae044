"""Quake 3 .pk3 archives (zip files): list the maps they hold and read one BSP out of them.

A member is read only when the size its header declares is within the source size cap, and then with a
bounded read (navi_compiler.ingest.limits): a small archive of a huge member fails before it is inflated.
"""

from __future__ import annotations

import os
import zipfile
import zlib
from pathlib import Path

from navi_compiler.ingest.errors import IngestError
from navi_compiler.ingest.limits import MAX_SOURCE_BYTES, checked_limit, read_stream_capped, too_large


def _open(path: str | os.PathLike[str]) -> zipfile.ZipFile:
    if not Path(path).is_file():
        raise IngestError(f"pk3 archive not found: {path}")
    try:
        return zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as err:
        raise IngestError(f"{path} is not a readable pk3 (zip) archive: {err}") from err


def _map_members(archive: zipfile.ZipFile) -> dict[str, str]:
    """Lower-case map name -> archive member, for every maps/<name>.bsp."""
    members: dict[str, str] = {}
    for member in archive.namelist():
        lower = member.lower()
        if lower.startswith("maps/") and lower.endswith(".bsp") and lower.count("/") == 1:
            members[lower[len("maps/") : -len(".bsp")]] = member
    return members


def list_pk3_maps(path: str | os.PathLike[str]) -> list[str]:
    """Names of the maps in a pk3 (maps/<name>.bsp), sorted, e.g. ["oa_dm1", "oa_dm2"]."""
    with _open(path) as archive:
        return sorted(_map_members(archive))


def _normalise(map_name: str) -> str:
    """'oa_dm1', 'oa_dm1.bsp', 'maps/oa_dm1.bsp' -> 'oa_dm1' (lower case: pk3 paths ignore case)."""
    name = map_name.strip().replace("\\", "/").lower()
    name = name.removeprefix("maps/")
    return name.removesuffix(".bsp")


def read_pk3_map(
    path: str | os.PathLike[str], map_name: str | None, max_bytes: int = MAX_SOURCE_BYTES
) -> tuple[str, bytes]:
    """(map name, BSP bytes) of one map; with no name the archive must hold exactly one map.

    SourceTooLargeError when the member is larger than max_bytes (checked before it is read)."""
    checked_limit(max_bytes)
    with _open(path) as archive:
        members = _map_members(archive)
        if not members:
            raise IngestError(f"{path} holds no maps (no maps/*.bsp)")
        if map_name is None:
            if len(members) != 1:
                raise IngestError(
                    f"{path} holds {len(members)} maps; choose one with a map name: {', '.join(sorted(members))}"
                )
            key = next(iter(members))
        else:
            key = _normalise(map_name)
            if key not in members:
                raise IngestError(
                    f"map {map_name!r} is not in {path}; it holds: {', '.join(sorted(members))}"
                )
        member = members[key]
        declared = archive.getinfo(member).file_size
        if declared > max_bytes:
            raise too_large(f"{path}:{member}", declared, max_bytes)
        try:
            with archive.open(member) as stream:
                return Path(member).stem, read_stream_capped(stream, f"{path}:{member}", max_bytes)
        except (zipfile.BadZipFile, OSError, EOFError, zlib.error) as err:
            raise IngestError(f"cannot read {member} from {path}: {err}") from err
