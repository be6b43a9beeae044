"""How point-goal episodes end and what the drone did on the way: for every episode of an evaluation, how
near it came to the goal and where it ended (path lengths as fractions of the start's), how far it rose
above and sank below its height after its first step, and how fast it flew.

`GoalFlights` is an `evaluate` observer (navi_learner.evaluation.evaluate); `summary` gives the medians
per scene (FLIGHTS), as `navi bench transfer` reports them for point-goal runs on the OpenArena maps and
`navi evaluate --goal-flights` prints them for any corpus. On large open maps they tell a drone that flies
away from its goal from one that times out short of it or overshoots it (docs/TRAINING.md).
"""

from __future__ import annotations

import torch

from navi_learner.envs.protocol import StepLike
from navi_learner.evaluation.evaluate import scene_table

NEAR_M = 2.0
"""An episode came near its goal when its path length to the goal fell below this (m) at some step."""
FLIGHTS = ("episodes", "success", "near", "nearest", "final", "climb_m", "sink_m", "speed")
"""What `summary` gives per scene: episodes ended; the share that reached the goal; the share that came
within NEAR_M of it; medians of the nearest and the final path length to the goal over the start's, of
the height risen above and sunk below the drone's height after its first step (m), and of its mean speed
(m/s)."""
COLUMNS = ("scene", "success", "near", "nearest", "final", "climb_m", "sink_m", "speed")
"""The columns of one ended episode's record (`GoalFlights.records`)."""


class GoalFlights:
    """An `evaluate` observer of point-goal episodes (the drone env's info: scene_id, position, speed,
    goal_distance, start_distance, success). Per actor it follows the running episode; every step keeps
    each actor's record so far and whether its episode ended there, with no host read, and `records`
    picks the ended ones at the end."""

    def __init__(self) -> None:
        self.rows: list[torch.Tensor] = []  # per step (N, 8) float32, COLUMNS
        self.ends: list[torch.Tensor] = []  # per step (N,) bool
        self.state: dict[str, torch.Tensor] = {}  # the running episode per actor, (N,) each
        self.fresh: torch.Tensor | None = None  # (N,) bool: this step is an episode's first

    def __call__(self, out: StepLike, action: torch.Tensor | None = None) -> None:
        info = out.info
        z = info["position"][:, 2].float()  # (N,) meters
        d = info["goal_distance"].float()  # (N,) meters
        speed = info["speed"].float()  # (N,) m/s
        fresh = torch.ones_like(z, dtype=torch.bool) if self.fresh is None else self.fresh  # (N,)
        s = self.state
        zero = torch.zeros_like(z)  # (N,)
        s["z0"] = torch.where(fresh, z, s.get("z0", z))  # (N,)
        s["top"] = torch.where(fresh, z, torch.maximum(s.get("top", z), z))  # (N,)
        s["bottom"] = torch.where(fresh, z, torch.minimum(s.get("bottom", z), z))  # (N,)
        s["nearest"] = torch.where(fresh, d, torch.minimum(s.get("nearest", d), d))  # (N,)
        s["speed"] = torch.where(fresh, zero, s.get("speed", zero)) + speed  # (N,) summed
        s["steps"] = torch.where(fresh, zero, s.get("steps", zero)) + 1.0  # (N,)
        start = info["start_distance"].float().clamp(min=1e-6)  # (N,) meters
        row = torch.stack(
            [
                info["scene_id"].float(),
                info["success"].float(),
                (s["nearest"] < NEAR_M).float(),
                s["nearest"] / start,
                d / start,
                s["top"] - s["z0"],
                s["z0"] - s["bottom"],
                s["speed"] / s["steps"],
            ],
            dim=1,
        )  # (N, 8) COLUMNS
        ends = out.done | out.truncated  # (N,) bool
        self.rows.append(row)
        self.ends.append(ends.clone())
        self.fresh = ends.clone()

    def records(self) -> torch.Tensor:
        """(E, 8) float32 on the CPU, COLUMNS: one row per episode that ended during the evaluation."""
        if not self.rows:
            return torch.zeros(0, len(COLUMNS))
        rows = torch.stack(self.rows).cpu()  # (T, N, 8)
        ends = torch.stack(self.ends).cpu()  # (T, N)
        return rows[ends]  # (E, 8)

    def summary(self, names: tuple[str, ...]) -> dict[str, dict[str, float]]:
        """Per scene name that ended an episode, and "all": FLIGHTS (shares and medians; an empty "all"
        holds 0 episodes)."""
        rec = self.records()  # (E, 8)
        out: dict[str, dict[str, float]] = {}
        for k, name in [*enumerate(names), (-1, "all")]:
            mine = rec if k < 0 else rec[rec[:, 0] == k]  # (E_k, 8)
            if mine.shape[0] == 0 and k >= 0:
                continue
            row = {"episodes": float(mine.shape[0])}
            for j, col in enumerate(COLUMNS[1:], start=1):
                values = mine[:, j]  # (E_k,)
                if not len(values):
                    row[col] = float("nan")
                elif col in ("success", "near"):
                    row[col] = float(values.mean())
                else:
                    row[col] = float(values.median())
            out[name] = row
        return out


def flight_table(rows: dict[str, dict[str, float]]) -> str:
    """A markdown table of `GoalFlights.summary` rows: one line per scene, then "all"."""
    return scene_table(rows, FLIGHTS, lambda k, v: f"{v:.0f}" if k == "episodes" else f"{v:.3g}")
