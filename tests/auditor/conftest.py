"""Fixtures of the auditor tests: a Zenoh router on loopback and client sessions to it. The helpers of the
service tests (tests/services/services_testlib.py: a router on an OS-picked port, reserved ports,
waiting on a condition) are importable here too."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from navi_contracts.settings import NaviSettings

sys.path.insert(0, str(Path(__file__).parents[1] / "services"))

from services_testlib import loopback_router


@pytest.fixture
def zenoh_router() -> Iterator[NaviSettings]:
    """A Zenoh router on a loopback port the OS picks; yields settings that connect to it."""
    pytest.importorskip("zenoh", reason="eclipse-zenoh is not installed")
    with loopback_router() as endpoint:
        yield NaviSettings(zenoh_connect=endpoint)


@pytest.fixture
def zenoh_client(zenoh_router: NaviSettings) -> Iterator[Any]:
    """A client session to the test router (for publishing test traffic)."""
    from navi_mesh.session import config_from_settings, open_new_session

    session = open_new_session(config_from_settings(zenoh_router, connect_timeout_s=60.0))
    try:
        yield session
    finally:
        session.close()


ROOM_RES, ROOM_VOXEL = 32, 0.5  # a 16 m cube


def room_corpus() -> Any:
    """A real SceneCorpus: the free inside of a box room from (1, 1, 1) to (15, 15, 7) m."""
    import numpy as np

    from navi_compiler.dag.build import build_gmdag
    from navi_env.tracer.scene import load_corpus

    i = np.arange(ROOM_RES + 1, dtype=np.float64) * ROOM_VOXEL
    p = np.stack(np.meshgrid(i, i, i, indexing="ij"), axis=-1)  # (R+1, R+1, R+1, 3) meters
    lo, hi = np.array([1.0, 1.0, 1.0]), np.array([15.0, 15.0, 7.0])
    q = np.abs(p - (lo + hi) / 2) - (hi - lo) / 2
    box = np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)  # >0 outside the room
    g = build_gmdag(
        (-box / ROOM_VOXEL).astype(np.float32),
        origin=(0.0, 0.0, 0.0),
        voxel_size=ROOM_VOXEL,
        spawns=np.array([[8.0, 8.0, 4.0]]),
        bounds=(tuple(lo), tuple(hi)),
    )
    return load_corpus([g], "cpu")


@pytest.fixture(scope="module")
def make_env() -> Callable[[], Any]:
    """A factory of one-actor SdfDagEnvs (32x8 rays) in the room, spawning at its centre."""
    import torch

    from navi_env.config import EnvConfig
    from navi_env.sim.env import SdfDagEnv

    corpus = room_corpus()
    config = EnvConfig(azimuth_bins=32, elevation_bins=8)
    return lambda: SdfDagEnv(corpus, 1, "cpu", config, spawns=[torch.tensor([[8.0, 8.0, 4.0]])])
