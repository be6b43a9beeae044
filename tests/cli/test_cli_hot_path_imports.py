"""The training core imports with torch + numpy (+ Navi's own extensions) alone: no service package and
none of the RL libraries that only navi_env.ecosystem's adapters use."""

from __future__ import annotations

import subprocess
import sys

SERVICE_ONLY = ("pydantic", "pydantic_settings", "zenoh", "fastapi", "uvicorn", "zarr", "prometheus_client",
                "trimesh", "msgpack", "typer")  # fmt: skip
RL_LIBRARIES = (
    "gymnasium",
    "torchrl",
    "tensordict",
    "skrl",
    "rsl_rl",
)  # navi_env.ecosystem's optional extras
HOT_PATH = (
    "navi_compiler.compile", "navi_compiler.gmdag", "navi_compiler.ingest", "navi_compiler.ingest.procedural",
    "navi_env.sim.env", "navi_env.tracer.trace", "navi_env.corpus.folder", "navi_env.space.qualify",
    "navi_learner.ppo.train", "navi_learner.engine.policy", "navi_learner.evaluation.evaluate", "navi_learner.serving.checkpoint",
    "navi_learner.serving.registry", "navi_learner.evaluation.main_job", "navi_learner.envs.factory",
)  # fmt: skip

PROGRAM = f"""
import importlib, importlib.abc, sys
class Blocker(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in {SERVICE_ONLY!r}:
            raise ImportError("service-only package imported: " + name)
        if name.split(".")[0] in {RL_LIBRARIES!r}:
            raise ImportError("an RL library (an optional extra) imported: " + name)
sys.meta_path.insert(0, Blocker())
for module in {HOT_PATH!r}:
    importlib.import_module(module)
print("ok")
"""


def test_hot_path_needs_no_service_packages() -> None:
    out = subprocess.run([sys.executable, "-c", PROGRAM], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]
