"""Builds navi_compiler._core (C++17, pybind11) as part of `pip install`."""

from __future__ import annotations

import sys
from pathlib import Path

from pybind11.setup_helpers import Pybind11Extension, build_ext
from setuptools import setup

CSRC = Path("navi_compiler") / "csrc"

if sys.platform == "win32":
    compile_args = ["/O2", "/std:c++17", "/fp:strict"]
    link_args: list[str] = []
else:
    # -ffp-contract=off: no fused multiply-add, so float math rounds exactly like NumPy.
    compile_args = ["-O3", "-std=c++17", "-ffp-contract=off", "-fno-fast-math", "-pthread"]
    link_args = ["-pthread"]

setup(
    ext_modules=[
        Pybind11Extension(
            "navi_compiler._core",
            [str(CSRC / "core.cpp")],
            depends=sorted(str(p) for p in CSRC.glob("*.h")),
            include_dirs=[str(CSRC)],
            cxx_std=17,
            extra_compile_args=compile_args,
            extra_link_args=link_args,
        )
    ],
    cmdclass={"build_ext": build_ext},
)
