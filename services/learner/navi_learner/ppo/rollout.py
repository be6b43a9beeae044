"""Rollout storage (T, N, ...) allocated once on the training device, and sequence-aware minibatches.

Step t stores the observation the policy acted on, its action, log-prob and value, the reward of the
transition, `resets[t]` (an episode starts at t: the recurrent state and episodic memory were zeroed
before acting), `ends[t]` and `truncs[t]` (the episode ended after step t). The recurrent state that
entered step t is stored at every BPTT chunk start, so each (chunk, actor) sequence can be replayed
independently with truncated BPTT.

Observations are stored in one of two forms. Compact (the drone env, DistanceMatrix v2): channel 0 as
float16 and the semantic code as a byte per ray, 3 bytes per ray; a minibatch's observations are
rebuilt on the device by navi_env.sim.observation.unpack (channel 2 from consecutive frames and the reset
flags), bit-identical to the float32 observations the policy acted on. On CUDA the pack runs
torch.compile'd, one pass instead of a few eager kernels. A compact minibatch hands the update its
frames still compact (CompactFrames): the encoder's input stage (engine/tokens.py) reads them as they
are and writes the patch tokens, on CUDA in one Triton pass that never writes the float32 frames out
(tests/learner/test_learner_rollout.py checks the decode on both devices). Float32 (any other env): the
observations as they came, 12 bytes per ray.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, TypeVar, cast

import torch

from navi_env.sim.observation import pack, semantic_table, unpack
from navi_learner.engine.heads import ACTION_DIM
from navi_learner.engine.temporal import CoreState
from navi_learner.engine.tokens import CompactFrames, gather_frames, sequences

F = TypeVar("F", bound=Callable[..., Any])


@functools.cache
def _compiled(fn: F) -> F:
    """fn compiled once per process (one program per input shape)."""
    return cast(F, torch.compile(fn, fullgraph=True, dynamic=False))


def decode(frames: torch.Tensor | CompactFrames, compiled: bool = False) -> torch.Tensor:
    """A minibatch's observations (L, M, 3, Az, El) float32, exactly what the policy acted on: float32
    frames as they are, compact ones gathered and unpacked, by gather_frames compiled once per process
    (`compiled`) or eager. The update does not call it: the encoder's input stage reads compact frames
    as they are (engine/tokens.py)."""
    if not isinstance(frames, CompactFrames):
        return frames
    gather = _compiled(gather_frames) if compiled else gather_frames
    return gather(*frames)  # (L, M, 3, Az, El)


@dataclass
class Minibatch:
    """M whole sequences of length L (time-major)."""

    frames: torch.Tensor | CompactFrames  # the observations: (L, M, 3, Az, El) float32, or compact
    actions: torch.Tensor  # (L, M, 4) float32
    logp: torch.Tensor  # (L, M) float32
    values: torch.Tensor  # (L, M) float32
    advantages: torch.Tensor  # (L, M) float32
    returns: torch.Tensor  # (L, M) float32
    resets: torch.Tensor  # (L, M) bool
    state: CoreState  # each (M, ...) float32: the recurrent state entering the first step
    chunks: torch.Tensor  # (M,) int64 BPTT chunk of each sequence: steps chunk·L .. chunk·L + L - 1
    actors: torch.Tensor  # (M,) int64 actor of each sequence

    @property
    def obs(self) -> torch.Tensor:
        """The observations (L, M, 3, Az, El) float32, decoded (compiled on CUDA)."""
        return decode(self.frames, compiled=self.resets.is_cuda)


class RolloutStorage:
    """Preallocated (T, N, ...) buffers on one device."""

    def __init__(
        self,
        t_len: int,
        n: int,
        obs_shape: tuple[int, int, int],
        state_template: CoreState,
        bptt_chunk: int,
        device: torch.device,
        compact: bool = False,
        goal_marks: bool = False,
    ) -> None:
        """`goal_marks`: the env paints point-goal marks into channel 1 (its `goal_marks`), which compact
        storage keeps as semantic codes 240-255."""
        if t_len % bptt_chunk:
            raise ValueError(f"rollout length {t_len} is not a multiple of the BPTT chunk {bptt_chunk}")
        self.t_len, self.n, self.chunk, self.compact = t_len, n, bptt_chunk, compact
        self.n_chunks = t_len // bptt_chunk
        c, az, el = obs_shape
        if compact:
            if c != 3:
                raise ValueError(f"compact observations have 3 channels, got {c}")
            # channel 0 of the frame before the rollout, then of its T frames
            self.depth16 = torch.zeros(
                t_len + 1, n, az, el, dtype=torch.float16, device=device
            )  # (T+1, N, Az, El)
            self.semantic = torch.zeros(t_len, n, az, el, dtype=torch.uint8, device=device)  # (T, N, Az, El)
            self.table = semantic_table(device, goal_marks)  # (256,) float32
            self._pack = _compiled(pack) if device.type == "cuda" else pack
        else:
            self.obs = torch.zeros(t_len, n, c, az, el, device=device)  # (T, N, 3, Az, El) float32
        self.actions = torch.zeros(t_len, n, ACTION_DIM, device=device)  # (T, N, 4) float32
        self.logp = torch.zeros(t_len, n, device=device)  # (T, N) float32
        self.values = torch.zeros(t_len, n, device=device)  # (T, N) float32
        self.rewards = torch.zeros(t_len, n, device=device)  # (T, N) float32 extrinsic + intrinsic
        self.resets = torch.zeros(t_len, n, dtype=torch.bool, device=device)  # (T, N) bool
        self.ends = torch.zeros(t_len, n, dtype=torch.bool, device=device)  # (T, N) bool
        self.truncs = torch.zeros(t_len, n, dtype=torch.bool, device=device)  # (T, N) bool
        self.advantages = torch.zeros(t_len, n, device=device)  # (T, N) float32
        self.returns = torch.zeros(t_len, n, device=device)  # (T, N) float32
        self.states = tuple(
            torch.zeros(self.n_chunks, *s.shape, dtype=s.dtype, device=device) for s in state_template
        )  # each (T/L, N, ...)

    def begin(self) -> None:
        """Start a rollout: the last frame of the previous one becomes the frame before this one."""
        if self.compact:
            self.depth16[0].copy_(self.depth16[self.t_len])

    def store_obs(self, t: int, obs: torch.Tensor) -> None:
        """Keep step t's observation obs (N, 3, Az, El) float32. Compact storage rebuilds its delta
        channel from step t - 1's frame and self.resets[t], so store resets[t] as well."""
        if self.compact:
            self._pack(obs, self.depth16[t + 1], self.semantic[t])
        else:
            self.obs[t].copy_(obs)

    def obs_at(self, t: int) -> torch.Tensor:
        """Step t's stored observation (N, 3, Az, El) float32, as the policy saw it."""
        if not self.compact:
            return self.obs[t]
        frames = unpack(self.depth16[t : t + 2], self.semantic[t : t + 1], self.resets[t : t + 1], self.table)
        return frames[0]  # (N, 3, Az, El)

    def store_state(self, t: int, state: CoreState) -> None:
        """Keep the recurrent state entering step t when t starts a BPTT chunk."""
        if t % self.chunk == 0:
            for buf, s in zip(self.states, state, strict=True):
                buf[t // self.chunk].copy_(s)

    def minibatch_ids(self, num_minibatches: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """Shuffle the (chunk, actor) sequences into groups of whole sequences: (K, M) int64 sequence ids
        (c·N + a), K = S // (S // num_minibatches) groups of M = S // num_minibatches (S sequences)."""
        total = self.n_chunks * self.n
        device = self.actions.device
        perm = torch.randperm(total, generator=generator).to(device)  # (S,) int64 sequence ids
        size = max(1, total // num_minibatches)
        return perm[: total // size * size].view(-1, size)  # (K, M)

    def minibatches(
        self, num_minibatches: int, generator: torch.Generator | None = None
    ) -> Iterator[Minibatch]:
        """Shuffle the (chunk, actor) sequences and yield groups of whole sequences (minibatch_ids)."""
        for ids in self.minibatch_ids(num_minibatches, generator):
            yield self.minibatch(ids)

    def minibatch(self, ids: torch.Tensor) -> Minibatch:
        """The sequences ids (M,) int64 (c·N + a) as a minibatch."""
        c, a = ids // self.n, ids % self.n  # (M,) each

        def seq(buf: torch.Tensor) -> torch.Tensor:
            return sequences(buf, c, a, self.chunk)  # (L, M, ...)

        resets = seq(self.resets)  # (L, M) bool
        frames: torch.Tensor | CompactFrames = (
            CompactFrames(self.depth16, self.semantic, resets, self.table, c, a, self.chunk)
            if self.compact
            else seq(self.obs)  # (L, M, 3, Az, El)
        )
        return Minibatch(
            frames=frames,
            actions=seq(self.actions),
            logp=seq(self.logp),
            values=seq(self.values),
            advantages=seq(self.advantages),
            returns=seq(self.returns),
            resets=resets,
            state=tuple(s[c, a] for s in self.states),
            chunks=c,
            actors=a,
        )
