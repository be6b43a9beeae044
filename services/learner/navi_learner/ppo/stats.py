"""Episode and reward statistics accumulated on the device (no host sync until `read`)."""

from __future__ import annotations

from collections.abc import Callable

import torch

from navi_learner.envs.protocol import StepLike


class EpisodeStats:
    """Running sums over a window of steps; `read()` moves them to the host once and clears them."""

    def __init__(self, n: int, device: torch.device) -> None:
        self.device = device
        self.ep_return = torch.zeros(n, device=device)  # (N,) float32 return of the running episode
        self.ep_len = torch.zeros(n, device=device)  # (N,) float32 length of the running episode
        self.sums: dict[str, torch.Tensor] = {}  # name -> () float32
        self.steps = 0  # actor-steps in the window (host counter, no sync)
        self.episodes_total = torch.zeros((), device=device)  # () float32 finished episodes, whole run

    def _add(self, name: str, value: torch.Tensor) -> None:
        if name not in self.sums:
            self.sums[name] = torch.zeros((), device=self.device)  # () float32
        self.sums[name] += value

    def update(self, out: StepLike, intrinsic: torch.Tensor | None = None) -> None:
        """Fold one step in: extrinsic reward, terms, episode ends, collisions (and those with moving
        obstacles), novel cells, clearance, starvation, and point-goal success and SPL."""
        ends = out.done | out.truncated  # (N,) bool
        endf = ends.float()  # (N,)
        self.ep_return += out.reward
        self.ep_len += 1.0
        self._add("reward", out.reward.sum())
        for name, term in out.reward_terms.items():
            self._add(f"reward/{name}", term.sum())
        if intrinsic is not None:
            self._add("reward/intrinsic", intrinsic.sum())
        self._add("episodes", endf.sum())
        self._add("episode_return", (self.ep_return * endf).sum())
        self._add("episode_length", (self.ep_len * endf).sum())
        for key in ("collision", "obstacle_collision", "drone_collision", "starved", "novel_cell"):
            if key in out.info:
                self._add(key, out.info[key].float().sum())
        if "clearance" in out.info:
            self._add("clearance", out.info["clearance"].float().sum())
        if "success" in out.info:  # point-goal: success and SPL of the episodes that ended here
            success = out.info["success"].float()  # (N,)
            shortest, flown = out.info["start_distance"], out.info["path_length"]  # (N,) each
            self._add("success", success.sum())
            self._add("spl", (success * shortest / torch.maximum(flown, shortest).clamp(min=1e-6)).sum())
        self.episodes_total += endf.sum()
        self.ep_return *= 1.0 - endf
        self.ep_len *= 1.0 - endf
        self.steps += out.reward.shape[0]

    def read(self, reduce: Callable[[torch.Tensor], torch.Tensor] | None = None) -> dict[str, float]:
        """Host-side means for the window (one transfer), then clear the window. `reduce` (data-parallel
        runs: Sync.sum_) sums the window's sums and step count over ranks first (every rank calls it)."""
        if reduce is None:
            names = list(self.sums)
            values = torch.stack([self.sums[k] for k in names]).tolist() if names else []  # (K,) -> host
            raw = dict(zip(names, values, strict=True))
            steps = max(self.steps, 1)
        else:
            names = sorted(self.sums)
            window = torch.tensor([float(self.steps)], device=self.device)  # (1,) float32 actor-steps
            summed = reduce(torch.cat([*(self.sums[k].reshape(1) for k in names), window]))  # (K + 1,)
            *values, total = summed.tolist()
            raw = dict(zip(names, values, strict=True))
            steps = max(int(total), 1)
        episodes = raw.get("episodes", 0.0)
        out: dict[str, float] = {"episodes": episodes}
        for k, v in raw.items():
            if k.startswith("reward") or k == "clearance":
                out[f"{k}_per_step"] = v / steps
        if episodes > 0:
            out["episode_return"] = raw["episode_return"] / episodes
            out["episode_length"] = raw["episode_length"] / episodes
        if "collision" in raw:
            out["collisions_per_1k"] = 1000.0 * raw["collision"] / steps
        if "obstacle_collision" in raw:
            out["obstacle_collisions_per_1k"] = 1000.0 * raw["obstacle_collision"] / steps
        if "drone_collision" in raw:
            out["drone_collisions_per_1k"] = 1000.0 * raw["drone_collision"] / steps
        if "novel_cell" in raw:
            out["coverage_per_1k"] = 1000.0 * raw["novel_cell"] / steps
        if "starved" in raw and episodes > 0:
            out["starvation_rate"] = raw["starved"] / episodes
        if "success" in raw and episodes > 0:
            out["success_rate"] = raw["success"] / episodes
            out["spl"] = raw["spl"] / episodes
        self.sums = {}
        self.steps = 0
        return out
