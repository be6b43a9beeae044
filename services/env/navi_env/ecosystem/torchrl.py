"""TorchRL over the batched env: NaviTorchRLEnv is an EnvBase with batch size (N,) on the env's device,
TensorDict in and out, with specs that pass torchrl.envs.utils.check_env_specs.

Keys: "observation" (N, 3, Az, El) float32 (with view=(Az', El') the pooled view an MLP reads, (N, 3,
Az', El'): navi_env.ecosystem.batch.pool_view), "action" (N, 4) float32 in [-1, 1], ("next", "reward")
(N, 1) float32, ("next", "done" | "terminated" | "truncated") (N, 1) bool, and with info=True (the
default) "info" (collision, obstacle_collision, drone_collision, novel_cell, starved: (N,) bool;
clearance, speed: (N,) float32) and "reward_terms" (term name -> (N,) float32, summing to the reward).

Episodes end inside the env's step (SdfDagEnv auto-resets), and TorchRL's convention is kept on top of
it: ("next", "observation") of an actor whose episode ended is its final observation (its last view,
the one its action was chosen on: the env does not trace the final pose), and the partial reset that
TorchRL's step_and_maybe_reset then asks for hands out the first observation of its next episode
without stepping anything. A full reset (no "_reset" mask) restarts every actor from the seed.

TorchRL keeps every step's TensorDict until it stacks a batch, so each step returns new tensors: one
copy of the observation per step (the final views of the actors that ended are then written over their
rows), and small per-actor copies. After a step where an episode ended, TorchRL's data holds a second
observation tensor (the root of the next step, with the next episodes' first views): maybe_reset makes
it as one more copy of the env's observation, where TorchRL's generic partial reset would merge two
observations in a full masked pass. The env writes two observation buffers in turn (make_batched_env),
so the view an action was chosen on is intact while the env steps. The step writes the final views
without reading the other rows or the host (navi_env.ecosystem.rows); maybe_reset reads the done flags
on the host, as TorchRL's own does at every step.
"""

from __future__ import annotations

import os
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from navi_env.config import EnvConfig
from navi_env.ecosystem.batch import ACTION_DIM, make_batched_env, obs_bounds, pool_view, view_of
from navi_env.ecosystem.rows import copy_rows
from navi_env.sim.env import SdfDagEnv

FLAGS: tuple[str, ...] = ("collision", "obstacle_collision", "drone_collision", "novel_cell", "starved")
"""Boolean info entries, (N,) each, from SdfDagEnv's StepOut.info."""
VALUES: tuple[str, ...] = ("clearance", "speed")
"""Float info entries, (N,) each (meters, m/s)."""


class NaviTorchRLEnv(EnvBase):
    """N drones of one SdfDagEnv as a TorchRL environment (see the module docstring); `view` (Az', El')
    hands out the pooled view instead of the env's own (None: the env's own, the image a CNN reads)."""

    def __init__(
        self, env: SdfDagEnv, info: bool = True, seed: int = 0, view: tuple[int, int] | None = None
    ) -> None:
        n, dev = env.n_actors, env.device
        super().__init__(device=dev, batch_size=torch.Size([n]))
        self.env = env
        self.info = info
        self.next_seed = seed
        self.view = view_of(env, view)
        low, high = obs_bounds(env, self.view)  # (3, Az', El') each
        shape = (n, *low.shape)
        observation = Composite(
            observation=Bounded(
                low=low.expand(shape).to(dev), high=high.expand(shape).to(dev), shape=shape, device=dev
            ),
            shape=(n,),
            device=dev,
        )
        if info:
            flags = {k: Categorical(2, shape=(n,), dtype=torch.bool, device=dev) for k in FLAGS}
            values = {k: Unbounded(shape=(n,), dtype=torch.float32, device=dev) for k in VALUES}
            observation["info"] = Composite(**flags, **values, shape=(n,), device=dev)
            terms = {k: Unbounded(shape=(n,), dtype=torch.float32, device=dev) for k in env.terms}
            observation["reward_terms"] = Composite(**terms, shape=(n,), device=dev)
        self.observation_spec = observation
        self.action_spec = Bounded(low=-1.0, high=1.0, shape=(n, ACTION_DIM), device=dev)
        self.reward_spec = Unbounded(shape=(n, 1), device=dev)
        self.done_spec = Composite(
            done=Categorical(2, shape=(n, 1), dtype=torch.bool, device=dev),
            terminated=Categorical(2, shape=(n, 1), dtype=torch.bool, device=dev),
            truncated=Categorical(2, shape=(n, 1), dtype=torch.bool, device=dev),
            shape=(n,),
            device=dev,
        )

    def seen(self, obs: torch.Tensor) -> torch.Tensor:
        """A new tensor of what the adapter hands out for the env's obs (N, 3, Az, El): a copy, or the
        pooled view (N, 3, Az', El')."""
        return obs.clone() if self.view is None else pool_view(obs, self.view)

    def _extras(self, zero: bool) -> dict[str, Any]:
        """ "info" and "reward_terms" entries: new tensors of the last step's values, or zeros."""
        if not self.info:
            return {}
        info, terms = self.env.info, self.env.terms

        def fresh(t: torch.Tensor) -> torch.Tensor:
            return torch.zeros_like(t) if zero else t.clone()  # (N,)

        return {
            "info": {k: fresh(info[k]) for k in (*FLAGS, *VALUES)},
            "reward_terms": {k: fresh(v) for k, v in terms.items()},
        }

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        n = self.env.n_actors
        partial = tensordict is not None and "_reset" in tensordict
        if partial:  # reset() with a "_reset" mask (step_and_maybe_reset goes through maybe_reset)
            # the env already began the ended actors' episodes
            obs = self.seen(self.env.obs)  # (N, 3, Az', El')
        else:
            obs = self.seen(self.env.reset(seed=self.next_seed))  # (N, 3, Az', El')
            self.next_seed += 1
        flags = torch.zeros(n, 1, dtype=torch.bool, device=self.device)  # (N, 1)
        out = {"observation": obs, "done": flags, "terminated": flags.clone(), "truncated": flags.clone()}
        return TensorDict(out | self._extras(zero=True), batch_size=self.batch_size, device=self.device)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        before = tensordict.get("observation")  # (N, 3, Az', El') the view the actions were chosen on
        out = self.env.step(tensordict.get("action"))
        ended = out.done | out.truncated  # (N,) bool
        obs = self.seen(out.obs)  # (N, 3, Az', El') a new tensor: TorchRL keeps it until it stacks a batch
        copy_rows(obs, before, ended)  # the final view where ended (only those rows read, no host sync)
        result = {
            "observation": obs,
            "reward": out.reward[:, None].clone(),  # (N, 1)
            "done": ended[:, None],  # (N, 1)
            "terminated": out.done[:, None].clone(),  # (N, 1)
            "truncated": out.truncated[:, None].clone(),  # (N, 1)
        }
        return TensorDict(result | self._extras(zero=False), batch_size=self.batch_size, device=self.device)

    def maybe_reset(self, tensordict: TensorDictBase) -> TensorDictBase:
        """EnvBase.maybe_reset for an env that has already begun the next episode of every actor whose
        episode ended: the same root TensorDict as a partial reset through _reset gives (the env's
        current observation, done flags cleared, zero info and reward terms where ended), built as one
        copy of the observation instead of TorchRL's generic reset and its masked merge (a full pass
        over both observations). Entries are replaced, never written in place: the step's "next" keeps
        its own."""
        done = tensordict.get("done")  # (N, 1) bool
        if not bool(done.any()):  # TorchRL's own check reads the flags on the host here too
            return tensordict
        first = self.seen(self.env.obs)  # (N, 3, Az', El') the next episode's first view
        tensordict.set("observation", first)
        for key in ("done", "terminated", "truncated"):
            tensordict.set(key, torch.zeros_like(done))  # (N, 1): nobody is done after the reset
        ended = done[:, 0]  # (N,) bool
        for group in ("info", "reward_terms") if self.info else ():
            node = tensordict.get(group)
            for key, value in node.items():
                node.set(key, value.masked_fill(ended, 0))  # (N,) zero where the episode restarted
        return tensordict

    def _set_seed(self, seed: int | None) -> None:
        """The next full reset restarts every actor from `seed` (each later full reset from the next
        integer)."""
        if seed is not None:
            self.next_seed = int(seed)


def make_torchrl_env(
    num_envs: int,
    corpus: str | os.PathLike[str],
    device: str = "cpu",
    config: EnvConfig | None = None,
    obstacles: int = 0,
    squad: int = 0,
    max_episode_steps: int = 0,
    info: bool = True,
    seed: int = 0,
    view: tuple[int, int] | None = None,
) -> NaviTorchRLEnv:
    """NaviTorchRLEnv over a corpus folder (arguments of navi_env.ecosystem.batch.make_batched_env, then
    NaviTorchRLEnv's)."""
    batched = make_batched_env(corpus, num_envs, device, config, obstacles, squad, max_episode_steps, seed)
    return NaviTorchRLEnv(batched, info=info, seed=seed, view=view)
