"""Where and how drones collide: every contact of an evaluation classed by the surface touched, the
geometry behind it, how long its drone had been in contact, what it commanded and what its view showed.

`CollisionSites` is an `evaluate` observer (navi_learner.evaluation.evaluate); `classify` turns what it
kept into counts per scene (COUNTS), as `navi bench transfer` tabulates them on the OpenArena maps and
`navi evaluate --collisions` prints them for any corpus.
"""

from __future__ import annotations

from typing import Any

import torch

from navi_env.config import EnvConfig
from navi_learner.envs.protocol import StepLike
from navi_learner.evaluation.evaluate import scene_table

THIN_M = 0.4
"""A collision is with thin geometry when the solid behind the touched surface is thinner than this."""
NORMAL_STEP_M = 0.05
"""Finite-difference step of the distance field's normal at a collision."""
PINNED_STEPS = 10
"""A contact is pinned when it is at least the PINNED_STEPS-th step in a row that its drone is in contact
(1 s at the default 0.1 s step): the drone stays pressed against a surface rather than grazing it."""
UNSEEN_M = 0.5
"""A contact is unseen when the shortest ray of the drone's view after the move is longer than the field's
clearance there by more than this (m): its rays missed what it touched."""
SURFACES = ("floor", "ceiling", "wall", "slope")
"""Collision classes by the touched surface's normal n: floor n_z >= 0.7 (the surface is below), ceiling
n_z <= -0.7, wall |n_z| < 0.2, slope in between (ramps, stairs' noses, curved patches)."""
COUNTS = (*SURFACES, "thin", "pinned", "pushing", "unseen")
"""What the collision table counts per map: contacts per surface class, those with thin geometry behind,
those that were pinned (PINNED_STEPS), the pinned ones whose command pointed at the nearest surface the
view shows (the drone keeps pushing into what it sees) and those it could not see (UNSEEN_M)."""


class CollisionSites:
    """An `evaluate` observer that keeps where each collision happened, (scene, position) per contact, and
    how many steps in a row its drone had been in contact by then (a new episode starts a new run). Given
    the env's `config` (an EnvConfig: sensor, horizon, speeds), it also reads each contact's view and
    command: whether the commanded body velocity pointed at the view's shortest ray, and whether that ray
    was longer than the field's clearance by more than UNSEEN_M."""

    def __init__(self, config: EnvConfig | None = None) -> None:
        self.config = config
        self.scene: list[torch.Tensor] = []
        self.position: list[torch.Tensor] = []
        self.run: list[torch.Tensor] = []
        self.toward: list[torch.Tensor] = []
        self.unseen: list[torch.Tensor] = []
        self.streak: torch.Tensor | None = None  # (N,) contact steps in a row, up to the last step
        self.rays: torch.Tensor | None = None  # (R, 3) body-frame ray directions of the view

    def __call__(self, out: StepLike, action: torch.Tensor | None = None) -> None:
        hit = out.info["collision"].bool()  # (N,)
        if self.streak is None:
            self.streak = torch.zeros(hit.shape[0], dtype=torch.long, device=hit.device)  # (N,)
        self.streak = (self.streak + 1) * hit  # (N,) a step without contact ends the run
        self.scene.append(out.info["scene_id"].long()[hit])  # (C_t,)
        self.position.append(out.info["position"].float()[hit])  # (C_t, 3)
        self.run.append(self.streak[hit])  # (C_t,) 1 for a first contact
        if self.config is not None and action is not None:
            toward, unseen = self._view(out, action)  # (N,) bool each
            self.toward.append(toward[hit])  # (C_t,)
            self.unseen.append(unseen[hit])  # (C_t,)
        self.streak = self.streak * ~(out.done | out.truncated)  # (N,) the next episode starts afresh

    def _view(self, out: StepLike, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per drone (N,) bool each: the command points at the view's nearest surface; the view's
        shortest ray is longer than the field's clearance by more than UNSEEN_M."""
        from navi_env.rays import ray_pattern
        from navi_env.sim.physics import body_velocity, dot

        assert self.config is not None
        n, _, az, el = out.obs.shape  # (N, C, Az, El)
        if self.rays is None:
            self.rays = ray_pattern(az, el, self.config.sensor, out.obs.device)  # (R, 3) body frame
        near, ray = out.obs[:, 0].reshape(n, az * el).float().min(dim=1)  # (N,), (N,) depth / horizon
        velocity, _ = body_velocity(action.float(), self.config)  # (N, 3) body m/s
        toward = (dot(velocity, self.rays[ray]) > 0.0) & (near < 1.0)  # (N,) a miss shows no surface
        unseen = near * self.config.horizon > out.info["clearance"].float() + UNSEEN_M  # (N,)
        return toward, unseen

    def classify(self, env: Any, names: tuple[str, ...]) -> dict[str, dict[str, int]]:
        """Per scene name (and "all"): contacts per surface class (SURFACES), how many were thin, pinned,
        pinned and pushing, and unseen (COUNTS; pushing and unseen stay 0 where the view was not read)."""
        from navi_env.tracer.trace import sample_distance

        scene = torch.cat(self.scene) if self.scene else torch.zeros(0, dtype=torch.long)  # (C,)
        pos = torch.cat(self.position) if self.position else torch.zeros(0, 3)  # (C, 3)
        run = torch.cat(self.run) if self.run else torch.zeros(0, dtype=torch.long)  # (C,)
        seen_view = bool(self.toward) and len(self.toward) == len(self.run)
        toward = torch.cat(self.toward) if seen_view else torch.zeros_like(run, dtype=torch.bool)  # (C,)
        unseen = torch.cat(self.unseen) if seen_view else torch.zeros_like(run, dtype=torch.bool)  # (C,)
        out: dict[str, dict[str, int]] = {"all": dict.fromkeys(COUNTS, 0)}
        if scene.numel() == 0:
            return out
        corpus = env.corpus

        def field_at(points: torch.Tensor) -> torch.Tensor:  # (C, 3) -> (C,) signed distance
            return sample_distance(corpus, scene, points.contiguous())

        axes = torch.eye(3, device=pos.device) * NORMAL_STEP_M  # (3, 3)
        grad = torch.stack([field_at(pos + axes[a]) - field_at(pos - axes[a]) for a in range(3)], 1)  # (C, 3)
        normal = grad / grad.norm(dim=1, keepdim=True).clamp(min=1e-9)  # (C, 3) away from the surface
        d = field_at(pos)  # (C,) distance to the surface
        nz = normal[:, 2]  # (C,)
        surface = torch.where(
            nz >= 0.7, 0, torch.where(nz <= -0.7, 1, torch.where(nz.abs() < 0.2, 2, 3))
        )  # (C,) index into SURFACES
        thin = torch.zeros_like(d, dtype=torch.bool)  # (C,) the solid ends within THIN_M behind the surface
        for depth in torch.arange(NORMAL_STEP_M, THIN_M + 1e-6, NORMAL_STEP_M).tolist():
            behind = pos - normal * (d.clamp(min=0.0) + depth)[:, None]  # (C, 3)
            thin |= field_at(behind) > 0.0
        for k, name in enumerate([*names, "all"]):
            mine = scene == k if name != "all" else torch.ones_like(thin)  # (C,) bool
            row = {s: int(((surface == i) & mine).sum()) for i, s in enumerate(SURFACES)}
            row["thin"] = int((thin & mine).sum())
            row["pinned"] = int(((run >= PINNED_STEPS) & mine).sum())
            row["pushing"] = int(((run >= PINNED_STEPS) & toward & mine).sum())
            row["unseen"] = int((unseen & mine).sum())
            if name == "all" or any(row.values()):
                out[name] = row
        return out


def collision_table(rows: dict[str, dict[str, int]]) -> str:
    """A markdown table of `CollisionSites.classify` rows: one line per scene with contacts, then "all"."""
    return scene_table(rows, COUNTS, lambda _, v: str(v or 0))
