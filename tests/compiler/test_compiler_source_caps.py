"""Size caps on scene sources: a file or .pk3 member over the cap fails before it is read, for the
library, the `navi compile` command and compile jobs alike (navi_compiler.ingest.limits)."""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import tracemalloc
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import pytest

from navi_compiler.ingest import IngestError, SourceTooLargeError, load_scene, read_entities
from navi_compiler.ingest.limits import MAX_SOURCE_BYTES
from navi_compiler.service import run_compile_job
from navi_contracts.models import CompileJob

MIB = 2**20
T = TypeVar("T")


def zeros_pk3(path: Path, member_bytes: int, name: str = "maps/zeros.bsp") -> Path:
    """A .pk3 holding one deflated member of `member_bytes` zeros, written in 1 MiB chunks."""
    chunk = bytes(MIB)
    with (
        zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive,
        archive.open(name, "w", force_zip64=member_bytes > 2**31) as member,
    ):
        left = member_bytes
        while left > 0:
            member.write(chunk[: min(left, MIB)])
            left -= MIB
    return path


def understate_size(path: Path, declared: int) -> None:
    """Patch the central directory so the (only) member claims to hold `declared` bytes."""
    data = bytearray(path.read_bytes())
    at = data.rindex(b"PK\x01\x02")  # the central directory entry
    data[at + 24 : at + 28] = struct.pack("<I", declared)  # uncompressed size
    path.write_bytes(bytes(data))


def sparse(path: Path, size: int) -> Path:
    """A file of `size` bytes that takes no disk space."""
    with path.open("wb") as f:
        f.truncate(size)
    return path


def peak_python_bytes(call: Callable[[], T]) -> tuple[T | BaseException, int]:
    """(result or raised exception, peak bytes Python allocated during the call)."""
    tracemalloc.start()
    try:
        outcome: T | BaseException = call()
    except BaseException as err:  # the test inspects it
        outcome = err
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    return outcome, peak


def test_pk3_member_over_the_cap_fails_before_it_is_inflated(tmp_path: Path) -> None:
    archive = zeros_pk3(tmp_path / "bomb.pk3", 8 * MIB)
    assert archive.stat().st_size < 64 * 1024  # 8 MiB of zeros deflate to a few KiB
    raised, peak = peak_python_bytes(lambda: load_scene(archive, max_bytes=MIB))
    assert isinstance(raised, SourceTooLargeError)
    assert "maps/zeros.bsp is 8.0 MiB, over the source size limit of 1.0 MiB" in str(raised)
    assert "NAVI_MAX_SOURCE_BYTES" in str(raised)
    assert peak < MIB // 4  # nothing of the member was inflated
    # The same member under a larger cap is read and reaches the BSP parser, which rejects it.
    with pytest.raises(IngestError) as parsed:
        load_scene(archive, max_bytes=16 * MIB)
    assert not isinstance(parsed.value, SourceTooLargeError)
    with pytest.raises(SourceTooLargeError):
        read_entities(f"{archive}:maps/zeros.bsp", max_bytes=MIB)


def test_a_header_that_understates_the_size_cannot_over_read(tmp_path: Path) -> None:
    archive = zeros_pk3(tmp_path / "liar.pk3", 16 * MIB)
    understate_size(archive, 1000)  # claims 1,000 bytes; inflates to 16 MiB
    raised, peak = peak_python_bytes(lambda: load_scene(archive, max_bytes=MIB))
    assert isinstance(raised, IngestError) and "Bad CRC-32" in str(raised)  # read stops at the declared size
    assert peak < 3 * MIB  # bounded by the cap (buffers of the bounded read), not by the 16 MiB inside


def test_bsp_and_mesh_files_over_the_cap(tmp_path: Path) -> None:
    for name in ("big.bsp", "big.obj", "big.glb"):
        path = sparse(tmp_path / name, 2 * MIB)
        raised, peak = peak_python_bytes(lambda p=path: load_scene(p, max_bytes=MIB))  # type: ignore[misc]
        assert isinstance(raised, SourceTooLargeError), (name, raised)
        assert f"{path} is 2.0 MiB, over the source size limit of 1.0 MiB" in str(raised)
        assert peak < MIB // 4
    with pytest.raises(IngestError, match="at least 1 byte"):
        load_scene(tmp_path / "big.bsp", max_bytes=0)
    assert MAX_SOURCE_BYTES == 256 * MIB  # the documented default (docs/COMPILER.md)


def test_compile_job_over_the_cap_is_a_clear_error_and_writes_nothing(tmp_path: Path) -> None:
    archive = zeros_pk3(tmp_path / "bomb.pk3", 8 * MIB)
    out = tmp_path / "out" / "bomb.gmdag"
    job = CompileJob(job_id="bomb", source=str(archive), output=str(out), resolution=64)
    import navi_compiler.compile  # imported by the job; its import is not the job's reading  # noqa: F401

    result, peak = peak_python_bytes(lambda: run_compile_job(job, "w0", max_source_bytes=MIB))
    assert not isinstance(result, BaseException)
    assert not result.ok and result.error_type == "SourceTooLargeError"
    assert "over the source size limit of 1.0 MiB" in (result.error or "")
    assert peak < MIB // 2 and not out.exists()


def run_measured(argv: list[str], env: dict[str, str], log: Path) -> tuple[int, str, int]:
    """(exit code, stderr, peak resident set in bytes) of one child process (reaped with wait4)."""
    with log.open("wb") as err:
        proc = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, log.read_text(errors="replace"), usage.ru_maxrss * 1024


def test_navi_compile_rejects_a_zip_bomb_archive_without_inflating_it(tmp_path: Path) -> None:
    """A ~300 KB .pk3 holding one 300 MB member of zeros, at the default cap."""
    bomb = zeros_pk3(tmp_path / "bomb.pk3", 300_000_000)
    small = zeros_pk3(tmp_path / "small.pk3", 4096)
    assert bomb.stat().st_size < 400_000
    env = {k: v for k, v in os.environ.items() if k != "NAVI_MAX_SOURCE_BYTES"}
    navi = [sys.executable, "-m", "navi", "compile"]
    log = tmp_path / "stderr.txt"
    rc, err, rss = run_measured([*navi, str(bomb), "-o", str(tmp_path / "bomb.gmdag")], env, log)
    assert rc == 2, err
    assert "over the source size limit of 256.0 MiB" in err and "Traceback" not in err
    assert not (tmp_path / "bomb.gmdag").exists()
    base_rc, base_err, base_rss = run_measured(
        [*navi, str(small), "-o", str(tmp_path / "small.gmdag")], env, log
    )
    assert base_rc == 2 and "over the source size limit" not in base_err  # read, then not a BSP
    assert rss - base_rss < 64 * MIB, (rss, base_rss)  # before the cap: +600 MB
    # --max-source-mb lowers the cap for one command.
    tiny_cap = ["--max-source-mb", "0.001"]  # 1,048 bytes
    rc, err, _ = run_measured([*navi, str(small), "-o", str(tmp_path / "s.gmdag"), *tiny_cap], env, log)
    assert rc == 2 and "4,096 bytes, over the source size limit of 1,048 bytes" in err
