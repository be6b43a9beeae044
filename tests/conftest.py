"""Repo-wide test tiers: `gpu`-marked tests skip, with the reason, where CUDA is absent; `--long`
selects the long fuzz run."""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

FUZZ_CASES = 3000  # the .gmdag fuzz in CI
LONG_FUZZ_CASES = 100_000  # with --long


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--long",
        action="store_true",
        default=False,
        help=f"long runs: the .gmdag reader fuzz takes {LONG_FUZZ_CASES:,} cases instead of {FUZZ_CASES:,}",
    )


@pytest.fixture
def fuzz_cases(request: pytest.FixtureRequest) -> int:
    """Cases for the .gmdag fuzz: NAVI_FUZZ_CASES if set, else 100,000 with --long, else 3,000."""
    if "NAVI_FUZZ_CASES" in os.environ:
        return int(os.environ["NAVI_FUZZ_CASES"])
    return LONG_FUZZ_CASES if request.config.getoption("--long") else FUZZ_CASES


GPU_MARK = "mark.gpu"
"""The text every module with gpu-marked tests holds (`pytest.mark.gpu`, as a decorator, a param mark or
pytestmark)."""


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    """With NAVI_GPU_ONLY=1 (tests/gpu_suite.sh on a benchmark host) modules without a gpu mark are not
    imported: they may need packages that host lacks. `-m gpu` then selects by the marker itself."""
    if os.environ.get("NAVI_GPU_ONLY") != "1":
        return None
    if collection_path.is_dir():  # a folder (and its conftest.py) with no gpu-marked module at all
        return not any(GPU_MARK in f.read_text(encoding="utf-8") for f in collection_path.rglob("test_*.py"))
    if collection_path.suffix != ".py" or not collection_path.name.startswith("test_"):
        return None
    return GPU_MARK not in collection_path.read_text(encoding="utf-8")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    gpu_items = [item for item in items if item.get_closest_marker("gpu") is not None]
    if not gpu_items:
        return
    import torch

    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device (torch.cuda.is_available() is False)")
    for item in gpu_items:
        item.add_marker(skip)


@pytest.fixture
def single_thread() -> Iterator[None]:
    """One intra-op torch thread: small tensors on a shared 2-core machine run far faster that way."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


GPU_GATE_CYCLES = 2_000_000_000
"""torch.cuda._sleep's length for the host-sync gate: about a second of GPU clock cycles, hundreds of times
what the host spends queueing an env step or a trace."""


@pytest.fixture
def returns_before_the_gpu() -> Callable[[Callable[[], object]], None]:
    """A check that `fn()` never waits for the device, wherever the wait would be (a torch op, or a
    synchronising call inside a compiled extension, which torch's sync debug mode cannot see): `fn` is
    queued behind a GPU sleep and must return while the sleep still runs."""

    def check(fn: Callable[[], object]) -> None:
        import torch

        torch.cuda.synchronize()
        gate = torch.cuda.Event()
        torch.cuda._sleep(GPU_GATE_CYCLES)
        gate.record()
        fn()
        waited = gate.query()  # True only if the host waited for the sleep (query itself never waits)
        torch.cuda.synchronize()
        assert not waited, "the call waited for the GPU: a host synchronisation on the hot path"

    return check


SKIPS: dict[str, list[str]] = {}
"""Skip reason -> the tests skipped for it, in this pytest run."""


def skip_reason(report: pytest.TestReport) -> str:
    """The reason of a skipped report (pytest stores (file, line, 'Skipped: reason') for skips)."""
    longrepr = report.longrepr
    if isinstance(longrepr, tuple) and len(longrepr) == 3:
        return str(longrepr[2]).removeprefix("Skipped: ")
    return str(longrepr)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if report.skipped and not hasattr(report, "wasxfail"):
        SKIPS.setdefault(skip_reason(report), []).append(report.nodeid)


def unexpected_skips(allowed: str) -> dict[str, list[str]]:
    """The skips whose reason matches none of the `|`-separated regular expressions in `allowed`."""
    patterns = [re.compile(p) for p in allowed.split("|") if p]
    return {reason: ids for reason, ids in SKIPS.items() if not any(p.search(reason) for p in patterns)}


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int, config: pytest.Config) -> None:
    """A table of skip reasons with their counts; with NAVI_ALLOWED_SKIPS set (CI), the skips it does not
    allow are listed and fail the run (pytest_sessionfinish sets the exit status)."""
    if not SKIPS:
        return
    terminalreporter.section("skips by reason")
    for reason, ids in sorted(SKIPS.items(), key=lambda kv: -len(kv[1])):
        terminalreporter.write_line(f"{len(ids):5d}  {reason}")
    allowed = os.environ.get("NAVI_ALLOWED_SKIPS")
    if allowed is not None:
        for reason, ids in unexpected_skips(allowed).items():
            terminalreporter.write_line(
                f"UNEXPECTED SKIP ({len(ids)}): {reason}: {', '.join(ids[:5])}", red=True
            )


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    allowed = os.environ.get("NAVI_ALLOWED_SKIPS")
    if allowed is not None and unexpected_skips(allowed) and exitstatus == pytest.ExitCode.OK:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


HOPPER = ("cuda", 90, 32)
"""The GPU target the CUDA code is built for (sm_90, 32-lane warps)."""


@pytest.fixture
def hopper_compile() -> Callable[[Any, dict[str, str], dict[str, Any]], dict[str, Any]]:
    """Compile a Triton kernel for sm_90 down to its cubin, on a machine without a GPU: Triton's front end
    and ptxas run on the host, so a kernel the interpreter accepts but the compiler refuses (a global, an
    annotation, a type the GPU lowering lacks) fails here and not first on a benchmark host. The
    returned function takes the kernel, the launch signature ({"X": "*bf16", "n": "i32", "k":
    "constexpr"}) and the constexpr values, and returns the compiled kernel's assembly by stage
    ("ptx", "cubin", ...) and its shared memory in bytes ("shared")."""
    triton = pytest.importorskip("triton", reason="the kernels are Triton programs; this torch has no Triton")
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    def compile_kernel(kernel: Any, signature: dict[str, str], constexprs: dict[str, Any]) -> dict[str, Any]:
        source = ASTSource(fn=kernel, signature=signature, constexprs=constexprs)
        compiled = triton.compile(source, target=GPUTarget(*HOPPER))
        return {**compiled.asm, "shared": int(compiled.metadata.shared)}

    return compile_kernel
