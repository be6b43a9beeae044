"""Builds and loads the CUDA launchers (csrc/trace_cuda.cu) on first use.

The shared library is compiled once with nvcc for sm_90 plus compute_80 PTX (which the driver JIT-
compiles for other GPUs), cached under ~/.cache/navi/ (or $NAVI_CACHE_DIR) keyed by a hash of the
sources, the flags and `nvcc --version`, and loaded with ctypes. The CUDA runtime is linked statically.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from navi_env.tracer.abi import check_layout

CSRC = Path(__file__).resolve().parent / "csrc"
SOURCES = (  # every file the nvcc build reads: hashed into the build key
    "trace_common.h",
    "launch_args.h",
    "scene_record.h",
    "brick_sample.h",
    "primitives.h",
    "ray_walk.h",
    "queries.h",
    "gmdag_trace.h",
    "trace_launch.h",
    "trace_cuda.cu",
)
NVCC_FLAGS = (
    "-O3",
    "-std=c++17",
    "--fmad=true",  # fused multiply-add; agrees with the CPU build to a tolerance (docs)
    "-Xcompiler=-fPIC,-fvisibility=hidden",
    "-shared",
    "-cudart=static",
    "-gencode=arch=compute_90,code=sm_90",
    "-gencode=arch=compute_80,code=compute_80",
)
NVCC_TIMEOUT_S = 600


def cache_dir() -> Path:
    """Where built libraries live: $NAVI_CACHE_DIR, else ~/.cache/navi."""
    root = os.environ.get("NAVI_CACHE_DIR")
    return Path(root) if root else Path.home() / ".cache" / "navi"


def find_nvcc() -> str:
    """Path of nvcc ($CUDA_HOME/bin, then PATH); RuntimeError when there is none."""
    for home in (os.environ.get("CUDA_HOME"), os.environ.get("CUDA_PATH")):
        if home and (Path(home) / "bin" / "nvcc").is_file():
            return str(Path(home) / "bin" / "nvcc")
    found = shutil.which("nvcc")
    if found is None:
        raise RuntimeError(
            "tracing CUDA tensors needs nvcc to build the CUDA tracer once; install the CUDA toolkit "
            "or set CUDA_HOME (CPU tensors need no build)"
        )
    return found


def build_key(nvcc: str) -> str:
    """Hash of the sources, the flags and the nvcc version."""
    version = subprocess.run([nvcc, "--version"], capture_output=True, text=True, check=True).stdout
    h = hashlib.sha256()
    for name in SOURCES:
        h.update((CSRC / name).read_bytes())
    h.update("\0".join(NVCC_FLAGS).encode())
    h.update(version.encode())
    return h.hexdigest()[:16]


def build_library() -> Path:
    """Compile the CUDA launchers unless a cached build with the same key exists; return its path."""
    nvcc = find_nvcc()
    out = cache_dir() / f"navi_trace_cuda-{build_key(nvcc)}.so"
    if out.is_file():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    print(
        f"navi_env: compiling the CUDA tracer with {nvcc} (once per source version) -> {out}", file=sys.stderr
    )
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    cmd = [nvcc, *NVCC_FLAGS, f"-I{CSRC}", "-o", tmp, str(CSRC / "trace_cuda.cu")]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=NVCC_TIMEOUT_S)
        if proc.returncode != 0:
            raise RuntimeError(f"building the CUDA tracer failed ({' '.join(cmd)}):\n{proc.stderr[-4000:]}")
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


@functools.cache
def cuda_library() -> ctypes.CDLL:
    """The loaded CUDA launchers (built on first call), argument types declared, layout checked."""
    lib = ctypes.CDLL(str(build_library()))
    for name in ("navi_trace_cuda", "navi_sample_cuda", "navi_sweep_cuda"):
        fn = getattr(lib, name)
        fn.argtypes = [ctypes.c_void_p]
        fn.restype = ctypes.c_int
    for name in (
        "navi_trace_args_size",
        "navi_sample_args_size",
        "navi_sweep_args_size",
        "navi_origin_sample_size",
    ):
        getattr(lib, name).argtypes = []
        getattr(lib, name).restype = ctypes.c_int
    lib.navi_atlas_create_cuda.argtypes = [ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64,
                                           ctypes.c_int, ctypes.POINTER(ctypes.c_uint64), ctypes.POINTER(ctypes.c_void_p)]  # fmt: skip
    lib.navi_atlas_create_cuda.restype = ctypes.c_int
    lib.navi_atlas_destroy_cuda.argtypes = [ctypes.c_uint64, ctypes.c_void_p, ctypes.c_int]
    lib.navi_atlas_destroy_cuda.restype = ctypes.c_int
    lib.navi_cuda_error_string.argtypes = [ctypes.c_int]
    lib.navi_cuda_error_string.restype = ctypes.c_char_p
    check_layout(
        lib.navi_trace_args_size,
        lib.navi_sample_args_size,
        lib.navi_sweep_args_size,
        lib.navi_origin_sample_size,
        "the CUDA tracer library",
    )
    return lib
