"""Builds navi_env.tracer._trace_cpu, the CPU launchers of the tracer, at `pip install` time.

The CUDA launchers are compiled on first use instead (navi_env/tracer/cuda_build.py), on hosts with nvcc.
"""

from __future__ import annotations

import sys

from pybind11.setup_helpers import Pybind11Extension, build_ext
from setuptools import setup

CSRC = "navi_env/tracer/csrc"

compile_args = ["-O3", "-ffp-contract=off", "-fvisibility=hidden"] if sys.platform != "win32" else ["/O2"]
link_args = ["-pthread"] if sys.platform != "win32" else []

setup(
    ext_modules=[
        Pybind11Extension(
            "navi_env.tracer._trace_cpu",
            sources=[f"{CSRC}/bindings.cpp", f"{CSRC}/trace_cpu.cpp"],
            include_dirs=[CSRC],
            depends=[
                f"{CSRC}/trace_common.h",
                f"{CSRC}/launch_args.h",
                f"{CSRC}/scene_record.h",
                f"{CSRC}/brick_sample.h",
                f"{CSRC}/primitives.h",
                f"{CSRC}/ray_walk.h",
                f"{CSRC}/queries.h",
                f"{CSRC}/gmdag_trace.h",
                f"{CSRC}/trace_launch.h",
            ],
            cxx_std=17,
            extra_compile_args=compile_args,
            extra_link_args=link_args,
        )
    ],
    cmdclass={"build_ext": build_ext},
)
