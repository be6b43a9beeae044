"""Floor plans of actor 0's scene for dashboards (navi/env/floor_plan): the clearance on a horizontal
slice at the drone's height, 128 cells on the long side, computed on its own thread when the scene
changes and published again every 5 s."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from navi_contracts.models import (
    FloorPlan,
)
from navi_learner.service.publishers import MeshPublishers

log = logging.getLogger(__name__)


PLAN_CELLS = 128
"""Cells on the long side of a floor plan."""
PLAN_PERIOD_S = 5.0
"""A floor plan is published again this often (for dashboards that connect late)."""


def floor_plan(corpus: Any, scene: int, z: float, cells: int = PLAN_CELLS, run_id: str = "") -> FloorPlan:
    """The clearance on the horizontal slice at height z of one scene of a SceneCorpus, over its
    geometry's x-y bounds, `cells` cells on the long side."""
    from navi_env.tracer.trace import sample_distance

    info = corpus.infos[scene]
    lo, hi = np.asarray(info.bounds_min, np.float64), np.asarray(info.bounds_max, np.float64)  # (3,) m
    extent = max(float(hi[0] - lo[0]), float(hi[1] - lo[1]), 1e-3)
    cell = extent / cells
    w = max(1, min(cells, math.ceil((hi[0] - lo[0]) / cell)))
    h = max(1, min(cells, math.ceil((hi[1] - lo[1]) / cell)))
    xs = lo[0] + (np.arange(w) + 0.5) * cell  # (W,) m
    ys = lo[1] + (np.arange(h) + 0.5) * cell  # (H,) m
    gx, gy = np.meshgrid(xs, ys)  # (H, W) each
    points = np.stack([gx, gy, np.full_like(gx, z)], axis=-1).reshape(-1, 3)  # (H*W, 3) m
    dev = corpus.device
    ids = torch.full((points.shape[0],), scene, dtype=torch.int64, device=dev)  # (H*W,)
    pts = torch.from_numpy(points.astype(np.float32)).to(dev).contiguous()  # (H*W, 3)
    clearance = sample_distance(corpus, ids, pts).cpu().numpy().reshape(h, w)  # (H, W) float32 m
    return FloorPlan(
        scene=info.name,
        run_id=run_id,
        origin_x=float(lo[0]),
        origin_y=float(lo[1]),
        cell_size=cell,
        z=float(z),
        clearance=np.ascontiguousarray(clearance, dtype=np.float32),
        timestamp=time.time(),
    )


class FloorPlanner:
    """Publishes the floor plan of actor 0's scene from a daemon thread: computed when the scene
    changes (or the drone's height moved more than a meter), sent again every PLAN_PERIOD_S."""

    def __init__(self, corpus: Any, pubs: MeshPublishers, run_id: Callable[[], str]) -> None:
        self.corpus, self.pubs, self.run_id = corpus, pubs, run_id
        self.plans = 0  # floor plans computed
        self._want: tuple[int, float] | None = None
        self._plan: FloorPlan | None = None
        self._key: tuple[int, float] | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="navi-floor-plan", daemon=True)
        self._thread.start()

    def request(self, scene: int, z: float) -> None:
        """Actor 0 is in `scene` at height z (called with every published pose; cheap)."""
        self._want = (scene, z)
        key = self._key
        if key is None or key[0] != scene or abs(key[1] - z) > 1.0:
            self._wake.set()

    def _run(self) -> None:
        last_sent = 0.0
        while not self._stop.is_set():
            self._wake.wait(PLAN_PERIOD_S)
            self._wake.clear()
            if self._stop.is_set():
                return
            want, key = self._want, self._key
            if want is not None and (key is None or key[0] != want[0] or abs(key[1] - want[1]) > 1.0):
                try:
                    self._plan = floor_plan(self.corpus, want[0], want[1], run_id=self.run_id())
                except (RuntimeError, ValueError, IndexError, TypeError) as err:
                    log.warning("floor plan of scene %d failed: %s", want[0], err)
                    self._key = want  # not again for this scene and height
                    continue
                self._key = want
                self.plans += 1
                last_sent = 0.0
            if self._plan is not None and time.monotonic() - last_sent >= min(1.0, PLAN_PERIOD_S):
                self.pubs.floor_plans.publish(self._plan)
                last_sent = time.monotonic()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=5.0)
