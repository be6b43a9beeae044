"""Size caps on scene sources, checked before a byte of the source is read into memory.

A source file (.bsp, mesh) and every archive member (.pk3 = zip) may hold at most `max_bytes`
(default `MAX_SOURCE_BYTES`, 256 MiB; `NAVI_MAX_SOURCE_BYTES` or `--max-source-mb` change it). A file
is measured with stat(); an archive member by the size its zip header declares, and then read with a
bounded read, so a header that understates the size cannot make the reader take more than the cap.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import IO

from navi_compiler.ingest.errors import IngestError

MAX_SOURCE_BYTES = 256 * 2**20
"""Default cap on one source file or archive member (256 MiB)."""
MIB = 2**20


class SourceTooLargeError(IngestError):
    """A source file or archive member exceeds the size cap."""


def _mib(n: int) -> str:
    return f"{n / MIB:,.1f} MiB" if n >= MIB else f"{n:,} bytes"


def checked_limit(max_bytes: int) -> int:
    """The cap itself must be a positive number of bytes."""
    if max_bytes < 1:
        raise IngestError(f"the source size cap must be at least 1 byte, got {max_bytes}")
    return max_bytes


def too_large(what: str, size: int, max_bytes: int) -> SourceTooLargeError:
    return SourceTooLargeError(
        f"{what} is {_mib(size)}, over the source size limit of {_mib(max_bytes)} "
        "(NAVI_MAX_SOURCE_BYTES or --max-source-mb raise it)"
    )


def check_file_size(path: str | os.PathLike[str], max_bytes: int) -> int:
    """The file's size in bytes; SourceTooLargeError when it exceeds max_bytes (nothing is read)."""
    checked_limit(max_bytes)
    try:
        size = Path(path).stat().st_size
    except OSError as err:
        raise IngestError(f"cannot read {path}: {err}") from err
    if size > max_bytes:
        raise too_large(str(path), size, max_bytes)
    return size


def read_file_capped(path: str | os.PathLike[str], max_bytes: int) -> bytes:
    """The whole file, after checking its size; a file that grew past the cap meanwhile also fails."""
    check_file_size(path, max_bytes)
    with open(path, "rb") as f:
        return read_stream_capped(f, str(path), max_bytes)


def read_stream_capped(stream: IO[bytes], what: str, max_bytes: int) -> bytes:
    """Read a stream to its end, but never more than max_bytes + 1 bytes (one over the cap fails)."""
    data = stream.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise SourceTooLargeError(
            f"{what} holds more than {_mib(max_bytes)} (the source size limit; "
            "NAVI_MAX_SOURCE_BYTES or --max-source-mb raise it)"
        )
    return data
