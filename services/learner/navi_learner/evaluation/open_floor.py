"""Does the drone hold its height where nothing is near? The open-floor probe.

Large real maps fail a procedural drone in one way above all: with nothing within its view clearance
(docs/SIMULATION.md, 10 m) it sinks, lands and stays pressed to the floor (docs/TRAINING.md, "Real maps
never seen"). The probe shows that failure in seconds, without the real maps: a flat floor `W` meters
square, walled, under an undrawn sky at W / 3, and nothing else. Drones start above its centre at several
heights (yaw drawn per actor) and fly the policy for `steps` steps; per floor width the probe reports the
height they end at and how much of the time they touch the floor. A drone that holds its height ends
where it started or at a height of its choosing; one that sinks ends on the floor.

Shapes: N actors, S scenes (one per width and start height), T steps.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from navi_env.config import EnvConfig
from navi_learner.evaluation.baselines import EvalPolicy

Say = Callable[[str], None]


@dataclass(frozen=True)
class OpenFloorConfig:
    """The probe's floors, starts and length."""

    widths: tuple[float, ...] = (15.0, 30.0, 60.0, 120.0)
    """Floor edges, meters: a room, a hall, and two open spaces whose walls lie beyond the 10 m clearance."""
    sky_ratio: float = 1.0 / 3.0
    """The undrawn sky lies at this fraction of the floor's width above it."""
    heights: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0, 16.0)
    """Start heights above the floor, meters; a floor keeps those at least 1 m under its sky."""
    actors_per_start: int = 8
    """Drones per start (the same spot, each with its own yaw)."""
    steps: int = 300
    """Steps flown (30 s at dt = 0.1 s)."""
    tail: int = 50
    """The final height is the mean over the last this many steps."""
    resolution: int = 256
    """Lattice cells per cube edge of the floors (their only surfaces are flat: 256 is exact enough)."""
    seed: int = 0

    def starts(self) -> list[tuple[float, float]]:
        """(width, start height) of every scene, in scene order."""
        return [(w, h) for w in self.widths for h in self.heights if h <= w * self.sky_ratio - 1.0]


def floor_scene_name(width: float, cfg: OpenFloorConfig) -> str:
    """The file name of a floor: its width, its sky and its lattice."""
    return f"open-floor-{width:g}m-sky{width * cfg.sky_ratio:.4g}m-{cfg.resolution}"


def build_open_floors(folder: Path, cfg: OpenFloorConfig, say: Say | None = None) -> dict[float, Path]:
    """One .gmdag per floor width in `folder` (kept: a floor is built once), by width."""
    from navi_compiler.compile import compile_scene
    from navi_compiler.gmdag import write_gmdag
    from navi_compiler.ingest.procedural import Box, Family, Layout, mesh_layout

    folder.mkdir(parents=True, exist_ok=True)
    files: dict[float, Path] = {}
    for w in cfg.widths:
        if w <= 0.0 or w * cfg.sky_ratio < 2.0:
            raise ValueError(f"an open floor {w:g} m wide has no start height 1 m under its sky")
        path = folder / f"{floor_scene_name(w, cfg)}.gmdag"
        if not path.is_file():
            sky = w * cfg.sky_ratio
            layout = Layout(
                family=Family.ARENA,
                seed=0,
                air=(Box((0.0, 0.0, 0.0), (w, w, sky)),),
                solids=(),
                open_top=sky,
                seeds=np.array([[w / 2, w / 2, 1.0]]),  # (1, 3)
            )
            gmdag, _ = compile_scene(mesh_layout(layout), resolution=cfg.resolution)
            tmp = path.with_suffix(".part")
            write_gmdag(gmdag, tmp)
            tmp.replace(path)
            if say is not None:
                say(f"[open floor] built {path.name}")
        files[w] = path
    return files


def open_floor_env(
    files: dict[float, Path], cfg: OpenFloorConfig, device: str, env: EnvConfig | None = None
) -> Any:
    """The probe's env: one scene per (width, start height) with that start as its only spawn, so actor i
    starts at cfg.starts()[i % S]; episodes last longer than the probe. It steps eagerly (no compiled
    passes, no CUDA graph): a hundred-odd drones for a few hundred steps cost less than compiling."""
    from navi_env.corpus.folder import load_corpus
    from navi_env.sim.env import SdfDagEnv

    starts = cfg.starts()
    corpus = load_corpus([files[w] for w, _ in starts], device)
    spawns = [torch.tensor([[w / 2, w / 2, h]], dtype=torch.float32) for w, h in starts]  # S x (1, 3)
    base = env or EnvConfig()
    config = replace(base, max_steps_per_episode=max(base.max_steps_per_episode, cfg.steps + 1))
    n = len(starts) * cfg.actors_per_start
    return SdfDagEnv(corpus, n, device, config, spawns=spawns, seed=cfg.seed, eager=True)


@dataclass
class OpenFloorRow:
    """One policy on one floor width."""

    policy: str
    width: float
    sky: float
    starts: list[float]
    """Start heights flown (m)."""
    final_height: float
    """Median over the drones of their mean height over the last `tail` steps (m)."""
    final_by_start: list[float]
    """The same median per start height."""
    on_floor: float
    """Share of the drones pressed to the floor: in contact for most of the last `tail` steps, and lower than
    two drone radii on average over them."""
    contacts_per_1k: float
    """Contact steps per 1,000 steps, over the whole probe."""
    episodes_ended: int
    """Episodes that ended early (starvation): their drones started again and are not probe data."""


def open_floor_probe(policy: EvalPolicy, env: Any, cfg: OpenFloorConfig) -> list[OpenFloorRow]:
    """Fly `policy` on the probe's env for cfg.steps steps; one row per floor width."""
    starts = cfg.starts()
    n, s = env.n_actors, len(starts)
    obs = env.reset(cfg.seed)
    policy.reset(n, env.device)
    resets = torch.ones(n, dtype=torch.bool, device=env.device)  # (N,)
    height = torch.zeros(cfg.steps, n, device=env.device)  # (T, N) m above the floor
    contact = torch.zeros(cfg.steps, n, dtype=torch.bool, device=env.device)  # (T, N)
    ended = torch.zeros(n, dtype=torch.long, device=env.device)  # (N,)
    with torch.no_grad():
        for t in range(cfg.steps):
            out = env.step(policy.act(obs, resets))
            obs, resets = out.obs, out.done | out.truncated  # (N, 3, Az, El), (N,)
            height[t] = out.info["position"][:, 2].float()
            contact[t] = out.info["collision"].bool()
            ended += resets.long()
    tail = max(1, min(cfg.tail, cfg.steps))
    final = height[-tail:].mean(0).cpu().numpy()  # (N,)
    low = height[-tail:].mean(0) < 2.0 * env.config.drone_radius  # (N,) bool
    floor = ((contact[-tail:].float().mean(0) > 0.5) & low).cpu().numpy()  # (N,)
    contacts = contact.float().sum(0).cpu().numpy()  # (N,)
    ended_np = ended.cpu().numpy()  # (N,)
    scene = np.arange(n) % s  # (N,) actor i starts at starts[i % S]
    rows = []
    for w in cfg.widths:
        mine = [k for k, (width, _) in enumerate(starts) if width == w]
        actors = np.isin(scene, mine)  # (N,) bool
        rows.append(
            OpenFloorRow(
                policy=getattr(policy, "name", type(policy).__name__),
                width=w,
                sky=w * cfg.sky_ratio,
                starts=[starts[k][1] for k in mine],
                final_height=float(np.median(final[actors])),
                final_by_start=[float(np.median(final[scene == k])) for k in mine],
                on_floor=float(floor[actors].mean()),
                contacts_per_1k=float(1000.0 * contacts[actors].sum() / (actors.sum() * cfg.steps)),
                episodes_ended=int(ended_np[actors].sum()),
            )
        )
    return rows


def probe_table(rows: list[OpenFloorRow]) -> str:
    """Markdown: per policy and floor, the final height (per start) and the floor contacts."""
    lines = [
        "| policy | floor (m) | final height (m), median | by start height | on the floor | contacts / 1k |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        by_start = ", ".join(f"{h:g}: {f:.2f}" for h, f in zip(r.starts, r.final_by_start, strict=True))
        lines.append(
            f"| {r.policy} | {r.width:g} x {r.width:g}, sky {r.sky:.0f} | {r.final_height:.2f} | {by_start} "
            f"| {r.on_floor:.0%} | {r.contacts_per_1k:.0f} |"
        )
    return "\n".join(lines)
