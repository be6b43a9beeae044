"""Scenes with an exact signed distance and exact ray hits: spheres, boxes, a room, thin slabs.

Used to check the tracer (tests, `python -m navi_bench.device_check`, `navi bench trace` without a file)
and as tiny toy scenes. A scene is a union of solids; `lattice` samples its signed distance on the
(R+1)^3 lattice the way the compiler does, and `build_gmdag` compresses it.

Shapes: P points, B actors, R rays. Coordinates are world meters unless a name says voxels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from navi_compiler.dag.build import build_gmdag
from navi_compiler.gmdag import Gmdag

NO_HIT = np.inf


@dataclass(frozen=True)
class Sphere:
    """A solid ball."""

    centre: tuple[float, float, float]  # meters
    radius: float  # meters

    def sdf(self, p: np.ndarray) -> np.ndarray:
        """(P,) float64 signed distance at p (P, 3)."""
        return np.linalg.norm(p - np.array(self.centre), axis=-1) - self.radius

    def hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(P,) float64 first entry time of rays o + t d (t >= 0), 0 inside, inf on a miss."""
        oc = o - np.array(self.centre)  # (P, 3)
        b = np.einsum("ij,ij->i", oc, d)  # (P,)
        c = np.einsum("ij,ij->i", oc, oc) - self.radius**2  # (P,)
        disc = b * b - c  # (P,)
        t = -b - np.sqrt(np.maximum(disc, 0.0))  # (P,)
        out = np.where((disc >= 0) & (t >= 0), t, NO_HIT)  # (P,)
        return np.where(c <= 0, 0.0, out)


@dataclass(frozen=True)
class Box:
    """A solid axis-aligned box."""

    lo: tuple[float, float, float]  # meters
    hi: tuple[float, float, float]

    def sdf(self, p: np.ndarray) -> np.ndarray:
        centre = (np.array(self.lo) + np.array(self.hi)) / 2  # (3,)
        half = (np.array(self.hi) - np.array(self.lo)) / 2  # (3,)
        q = np.abs(p - centre) - half  # (P, 3)
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)  # (P,)
        return outside + np.minimum(q.max(axis=-1), 0.0)

    def hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        t_near, t_far = _slabs(o, d, np.array(self.lo), np.array(self.hi))  # (P,), (P,)
        out = np.where((t_near <= t_far) & (t_far >= 0), np.maximum(t_near, 0.0), NO_HIT)  # (P,)
        return np.where(self.sdf(o) <= 0, 0.0, out)


@dataclass(frozen=True)
class Room:
    """Solid everywhere except the open box [lo, hi]: walls, floor and ceiling seen from inside."""

    lo: tuple[float, float, float]  # meters
    hi: tuple[float, float, float]

    def sdf(self, p: np.ndarray) -> np.ndarray:
        return -Box(self.lo, self.hi).sdf(p)

    def hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        _, t_far = _slabs(o, d, np.array(self.lo), np.array(self.hi))  # (P,)
        return np.where(self.sdf(o) <= 0, 0.0, np.maximum(t_far, 0.0))


@dataclass(frozen=True)
class Slab:
    """A solid plate {p : |n . p - offset| <= thickness / 2} (unbounded)."""

    normal: tuple[float, float, float]  # unit vector
    offset: float  # meters, plate centre along the normal
    thickness: float  # meters

    def sdf(self, p: np.ndarray) -> np.ndarray:
        return np.abs(p @ np.array(self.normal) - self.offset) - self.thickness / 2

    def hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        n = np.array(self.normal)
        s = o @ n - self.offset  # (P,) signed height above the centre plane
        dn = d @ n  # (P,)
        face = np.sign(s) * self.thickness / 2  # (P,) the face on the origin's side
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (face - s) / dn  # (P,)
        out = np.where(np.isfinite(t) & (t >= 0), t, NO_HIT)
        return np.where(np.abs(s) <= self.thickness / 2, 0.0, out)


Solid = Sphere | Box | Room | Slab


def _slabs(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit times (P,), (P,) of rays o + t d through the box [lo, hi] (t unbounded)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d  # (P, 3)
        ta, tb = (lo - o) * inv, (hi - o) * inv  # (P, 3), (P, 3)
    parallel = d == 0  # (P, 3)
    inside = (o >= lo) & (o <= hi)  # (P, 3)
    t_min = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))  # (P, 3)
    t_max = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))  # (P, 3)
    return t_min.max(axis=-1), t_max.min(axis=-1)


@dataclass(frozen=True)
class AnalyticScene:
    """A union of solids in a cube of `resolution` cells of `voxel_size` meters from `origin`."""

    solids: tuple[Solid, ...]
    resolution: int
    voxel_size: float  # meters
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)  # meters

    def sdf(self, p: np.ndarray) -> np.ndarray:
        """(P,) float64 signed distance of the union at p (P, 3), meters."""
        return np.min(np.stack([s.sdf(p) for s in self.solids]), axis=0)

    def lattice(self, dilate_voxels: float = 0.0) -> np.ndarray:
        """(R+1, R+1, R+1) float32 signed distances in voxels at the lattice points, [x, y, z].

        dilate_voxels thickens every solid (the compiler's rule for thin walls is 0.5: every lattice
        point within half a voxel of a surface is inside).
        """
        n = self.resolution + 1
        idx = np.arange(n, dtype=np.float64)  # (R+1,)
        gx, gy, gz = np.meshgrid(idx, idx, idx, indexing="ij")  # (R+1, R+1, R+1) each
        pts = np.stack([gx, gy, gz], axis=-1).reshape(-1, 3) * self.voxel_size + np.array(
            self.origin
        )  # (P, 3)
        vox = self.sdf(pts) / self.voxel_size - dilate_voxels  # (P,)
        return vox.reshape(n, n, n).astype(np.float32)

    def gmdag(self, dilate_voxels: float = 0.0, spawns: np.ndarray | None = None) -> Gmdag:
        """The scene compressed by the compiler's build_gmdag."""
        return build_gmdag(
            self.lattice(dilate_voxels), origin=self.origin, voxel_size=self.voxel_size, spawns=spawns
        )

    def hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(P,) float64 exact first-hit distance (meters) of rays o (P, 3) + t d (P, 3); inf on a miss."""
        return np.min(np.stack([s.hit(o, d) for s in self.solids]), axis=0)

    @property
    def cube_max(self) -> np.ndarray:
        return np.array(self.origin) + self.resolution * self.voxel_size


def demo_room(resolution: int = 64, size: float = 16.0) -> AnalyticScene:
    """A closed room of edge `size` meters with a ball, a pillar and a low box on the floor."""
    h = size / resolution
    lo, hi = 3 * h, size - 3 * h
    return AnalyticScene(
        solids=(
            Room((lo, lo, lo), (hi, hi, hi)),
            Sphere((0.62 * size, 0.41 * size, 0.37 * size), 0.13 * size),
            Box((0.2 * size, 0.6 * size, lo), (0.3 * size, 0.7 * size, hi)),
            Box((0.55 * size, 0.7 * size, lo), (0.8 * size, 0.85 * size, 0.2 * size)),
        ),
        resolution=resolution,
        voxel_size=h,
    )


def leaf_kind_scenes() -> list[AnalyticScene]:
    """Three small scenes that between them hold every leaf kind at two depths: `demo_room(32, 8.0)`
    (bricks and far codes in a closed room), a lone sphere in a 64^3 cube (mostly far codes) and two
    boxes at a finer voxel (tracer layout and parity tests)."""
    sparse = AnalyticScene((Sphere((21.0, 12.0, 9.5), 2.5),), resolution=64, voxel_size=0.5)
    boxes = AnalyticScene(
        (Box((1.0, 1.5, 0.5), (3.0, 6.0, 2.5)), Box((4.5, 0.7, 1.0), (7.2, 2.1, 7.0))),
        resolution=32,
        voxel_size=0.25,
    )
    return [demo_room(32, 8.0), sparse, boxes]


def free_points(scene: AnalyticScene, count: int, clearance: float, seed: int = 0) -> np.ndarray:
    """(count, 3) float64 points in the cube at least `clearance` meters from every solid."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array(scene.origin), scene.cube_max
    found: list[np.ndarray] = []
    total = 0
    for _ in range(1000):
        p = rng.uniform(lo, hi, size=(4 * count, 3))  # (4C, 3)
        keep = p[scene.sdf(p) >= clearance]  # (K, 3)
        found.append(keep)
        total += len(keep)
        if total >= count:
            return np.concatenate(found)[:count]
    raise ValueError(f"found only {total} of {count} points with clearance {clearance} m")


def random_directions(count: int, seed: int = 0) -> np.ndarray:
    """(count, 3) float64 unit vectors, uniform on the sphere."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(count, 3))  # (count, 3)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def slab_scene(thickness_voxels: float, normal: np.ndarray, resolution: int = 32) -> AnalyticScene:
    """One thin plate through the cube centre, voxel size 1 m (so meters are voxels)."""
    n = normal / np.linalg.norm(normal)
    centre = resolution / 2 + 0.37  # off the lattice planes
    offset = float(centre * n.sum())
    return AnalyticScene(
        solids=(Slab((float(n[0]), float(n[1]), float(n[2])), offset, thickness_voxels),),
        resolution=resolution,
        voxel_size=1.0,
    )


def unit(v: tuple[float, float, float]) -> np.ndarray:
    """(3,) float64 v normalised."""
    a = np.array(v, np.float64)
    return a / math.sqrt(float(a @ a))
