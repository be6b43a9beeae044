"""Pictures of the batched env for people: what one drone sees (its spherical depth unrolled into a
panorama) above a top-down slice of its scene at its height with every drone flying there.

Host-side NumPy, read from the device once per picture: for videos and debugging, never for the step
path. `render_frame` returns (H, W, 3) uint8 RGB.
"""

from __future__ import annotations

import numpy as np
import torch

from navi_env.sim.env import SdfDagEnv
from navi_env.tracer.trace import sample_distance

PANORAMA_WIDTH = 512
"""Width of the picture in pixels (the panorama is scaled up to it by whole pixels)."""
MAP_CELLS = 256
"""Cells along the longer side of the top-down slice (one pixel each)."""
# Colour map from near (bright) to far (dark), control points of a magma-like ramp.
_RAMP = np.array(
    [[252, 253, 191], [252, 137, 97], [183, 55, 121], [81, 18, 124], [0, 0, 4]], dtype=np.float64
)
_SOLID = np.array([40, 44, 52], dtype=np.uint8)
_FREE_NEAR = np.array([150, 160, 175], dtype=np.float64)
_FREE_FAR = np.array([235, 238, 242], dtype=np.float64)
_OTHERS = np.array([40, 110, 220], dtype=np.uint8)
_CHOSEN = np.array([230, 40, 40], dtype=np.uint8)


def colour_depth(depth: np.ndarray, horizon: float) -> np.ndarray:
    """(..., 3) uint8 colours of depth / horizon values (...) in [0, 1]: near bright, far dark, on a
    logarithmic scale of the distance (as much colour from 1 m to 10 m as from 10 m to 100 m)."""
    meters = np.clip(depth, 0.0, 1.0) * horizon
    x = np.log1p(meters) / np.log1p(horizon) * (len(_RAMP) - 1)
    lo = np.floor(x).astype(np.int64).clip(0, len(_RAMP) - 2)
    t = (x - lo)[..., None]
    return (_RAMP[lo] * (1.0 - t) + _RAMP[lo + 1] * t).round().astype(np.uint8)


def panorama(obs: torch.Tensor, horizon: float) -> np.ndarray:
    """(El, Az, 3) uint8 picture of one observation (3, Az, El) of an env with this horizon (m): straight
    ahead in the middle column, left of the drone on the left, up at the top."""
    depth = obs[0].detach().float().cpu().numpy()  # (Az, El) depth / horizon
    az = depth.shape[0]
    columns = (az // 2 - np.arange(az)) % az  # (Az,) bin shown in each column, left to right
    return colour_depth(depth[columns].T[::-1], horizon)  # (El, Az, 3)


def top_down(env: SdfDagEnv, actor: int) -> np.ndarray:
    """(H, W, 3) uint8 slice of `actor`'s scene at its height (solid dark, free space shaded by the
    distance to the nearest surface, its own moving obstacles included), with the drones in that scene
    as dots (the chosen one red, with a line along its heading) and north (+Y) up."""
    scene = int(env.scene[actor])
    info = env.corpus.infos[scene]
    lo, hi = np.array(info.bounds_min[:2]), np.array(info.bounds_max[:2])
    cell = float(max(hi - lo)) / MAP_CELLS
    nx, ny = (np.ceil((hi - lo) / cell).astype(int) + 1).tolist()
    z = float(env.position[actor, 2])
    xs = lo[0] + (np.arange(nx) + 0.5) * cell
    ys = lo[1] + (np.arange(ny) + 0.5) * cell
    gx, gy = np.meshgrid(xs, ys[::-1], indexing="xy")  # (H, W): row 0 is the largest y
    points = np.stack([gx, gy, np.full_like(gx, z)], axis=-1).reshape(-1, 3)  # (H*W, 3)
    pts = torch.from_numpy(points).to(env.device, torch.float32)  # (H*W, 3)
    ids = torch.full((pts.shape[0],), scene, dtype=torch.int64, device=env.device)  # (H*W,)
    if env.prims is None:
        d = sample_distance(env.corpus, ids, pts)  # (H*W,)
    else:
        world = torch.full((pts.shape[0],), actor, dtype=torch.int32, device=env.device)  # (H*W,)
        d = sample_distance(env.corpus, ids, pts, prims=env.prims, prim_world=world, prim_owner=world)
    dist = d.cpu().numpy().reshape(gx.shape)  # (H, W) meters
    shade = np.clip(dist / 3.0, 0.0, 1.0)[..., None]
    image = (_FREE_NEAR * (1.0 - shade) + _FREE_FAR * shade).round().astype(np.uint8)  # (H, W, 3)
    image[~(dist > 0.0)] = _SOLID
    here = (env.scene == scene).cpu().numpy()  # (N,) bool
    pos = env.position.cpu().numpy()  # (N, 3)
    yaw = float(env.yaw[actor])

    def pixel(x: float, y: float) -> tuple[int, int]:
        return int((hi[1] - y) / cell), int((x - lo[0]) / cell)

    def dot(x: float, y: float, colour: np.ndarray, radius: int) -> None:
        r, c = pixel(x, y)
        image[max(r - radius, 0) : r + radius + 1, max(c - radius, 0) : c + radius + 1] = colour

    for other in np.flatnonzero(here):
        if other != actor:
            dot(pos[other, 0], pos[other, 1], _OTHERS, 2)
    for t in np.linspace(0.0, 2.0, 24):  # 2 m along the heading
        dot(pos[actor, 0] + t * np.cos(yaw), pos[actor, 1] + t * np.sin(yaw), _CHOSEN, 0)
    dot(pos[actor, 0], pos[actor, 1], _CHOSEN, 3)
    return image


def render_frame(env: SdfDagEnv, obs: torch.Tensor, actor: int = 0) -> np.ndarray:
    """(H, W, 3) uint8: `actor`'s view obs (N, 3, Az, El) as a panorama above the top-down slice."""
    view = panorama(obs[actor], env.config.horizon)  # (El, Az, 3)
    scale = max(1, PANORAMA_WIDTH // view.shape[1])
    view = view.repeat(scale, axis=0).repeat(scale, axis=1)
    plan = top_down(env, actor)
    width = max(view.shape[1], plan.shape[1])

    def pad(image: np.ndarray) -> np.ndarray:
        left = (width - image.shape[1]) // 2
        out = np.full((image.shape[0], width, 3), 255, dtype=np.uint8)
        out[:, left : left + image.shape[1]] = image
        return out

    gap = np.full((4, width, 3), 255, dtype=np.uint8)
    return np.concatenate([pad(view), gap, pad(plan)], axis=0)
