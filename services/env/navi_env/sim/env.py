"""SdfDagEnv: N drones flying in .gmdag scenes, stepped together on one device.

One step, in order (docs/SIMULATION.md):
  physics      moving obstacles (if any) take their scripted step, stopped at the drone; actions ->
               limited body velocity -> contact-safe move in the combined field, yaw, visited cells
  episode      step counts, truncation (time limit, starvation after the void grace), auto-reset
               (scene rotation, spawn) of the actors whose episode ended
  trace        one sphere trace of every actor's rays from its (new or spawn) pose
  observation  sensor model, DistanceMatrix v2 in place, view statistics (clearance included)
  reward       every term from the move and the views before and after it (an actor whose episode
               ended was not traced at its final pose: its view after the move is its last view)

All state lives in buffers allocated once on the device and written in place. The tensors that
`reset` and `step` return are those buffers: copy them before the next step if you keep them.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar, cast

import torch

from navi_env.config import EnvConfig
from navi_env.rays import ray_pattern, tiled_ray_order
from navi_env.sim import episodes, goals, physics, rewards
from navi_env.sim import obstacles as obstacle_motion
from navi_env.sim.observation import CHANNELS, FIRST_MARK_CODE, observe, observe_ref, semantic_table
from navi_env.sim.sensor import apply_sensor
from navi_env.tracer import primitives as ob
from navi_env.tracer.scene import SceneCorpus
from navi_env.tracer.trace import sample_distance, trace

STAGES: tuple[str, ...] = ("physics", "episode", "trace", "observation", "reward")
"""Stage names of one step, in order."""

INFO_KEYS: tuple[str, ...] = (
    "clearance",
    "collision",
    "position",
    "novel_cell",
    "speed",
    "episode_return",
    "episode_length",
    "starved",
    "scene_id",
    "obstacle_collision",
    "drone_collision",
)
"""Keys of StepOut.info; every value is a tensor with leading dimension N."""

GOAL_INFO_KEYS: tuple[str, ...] = ("success", "goal_distance", "start_distance", "path_length")
"""Keys StepOut.info adds in point-goal episodes (EnvConfig.task == "pointgoal"): the episode ended at the
goal; the true path length (m) to the goal after the move, at the episode's start, and the meters flown
so far (final where the episode ended)."""

VIEW_KEYS: tuple[str, ...] = ("clearance", "void", "near", "mid", "front_mid")
"""The view statistics the env keeps per actor (attributes of the same names), from navi_env.sim.observation."""


@dataclass(frozen=True)
class StepOut:
    """One step of N actors. `obs` of an actor whose episode ended is the first of its next episode."""

    obs: torch.Tensor  # (N, 3, Az, El) float32
    reward: torch.Tensor  # (N,) float32, the sum of reward_terms
    done: torch.Tensor  # (N,) bool terminated: at the goal (point-goal); contact never ends an episode
    truncated: torch.Tensor  # (N,) bool ended by the time limit or starvation, not done; auto-reset
    reward_terms: dict[str, torch.Tensor]  # name -> (N,) float32 weighted term
    info: dict[str, torch.Tensor]  # INFO_KEYS -> (N,) or (N, 3); values of the step that just ended


class StageTimer:
    """Accumulates wall time per stage; on CUDA with events, so timing adds no sync until `totals`."""

    def __init__(self, device: torch.device) -> None:
        self.cuda = device.type == "cuda"
        self.host_s: dict[str, float] = {name: 0.0 for name in STAGES}
        self.events: dict[str, list[tuple[torch.cuda.Event, torch.cuda.Event]]] = {
            name: [] for name in STAGES
        }

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        if self.cuda:
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            yield
            end.record()
            self.events[name].append((start, end))
        else:
            t0 = time.perf_counter()
            yield
            self.host_s[name] += time.perf_counter() - t0

    def totals_ms(self) -> dict[str, float]:
        """Milliseconds spent per stage so far (synchronises the device once)."""
        if self.cuda:
            torch.cuda.synchronize()
            return {k: sum(s.elapsed_time(e) for s, e in v) for k, v in self.events.items()}
        return {k: v * 1000.0 for k, v in self.host_s.items()}


class SdfDagEnv:
    """Batched drone environment over a SceneCorpus (see the module docstring)."""

    def __init__(
        self,
        corpus: SceneCorpus,
        n_actors: int,
        device: torch.device | str = "cpu",
        config: EnvConfig | None = None,
        spawns: Sequence[torch.Tensor] | None = None,
        seed: int = 0,
        scene_obstacles: Sequence[Mapping[str, float]] | None = None,
        *,
        eager: bool = False,
    ) -> None:
        """`spawns`: per scene (K_s, 3) quality-gated positions (default: qualify every scene now).
        `scene_obstacles`: per scene, the obstacle settings it declares (obstacle_motion.SCENE_KEYS, e.g.
        from the corpus manifest); they override config.obstacles in that scene.
        `eager`: run every stage as plain PyTorch kernels, one step after another, on CUDA too (no
        torch.compile'd passes, no CUDA graph): the slow, obviously correct twin that the parity tests
        compare the CUDA path with. The CPU always runs this way."""
        if n_actors < 1:
            raise ValueError("n_actors must be >= 1")
        want = torch.device(device)
        if want.type != corpus.device.type or (want.index is not None and want != corpus.device):
            raise ValueError(f"the corpus lives on {corpus.device}, the environment was asked for {want}")
        self.config = cfg = config or EnvConfig()
        self.corpus = corpus
        self.device = corpus.device
        self.n = self.n_actors = n_actors
        self.timer: StageTimer | None = None
        self._fast = self.device.type == "cuda" and not eager  # compiled passes and the step's CUDA graph
        self._graphs: list[torch.cuda.CUDAGraph | None] = [None, None]  # one per observation buffer
        self._eager_steps = 0
        _check_band(corpus, cfg.drone_radius)
        self._build_spawns(spawns)
        self._build_bounds()
        self._build_ray_pattern()
        self._build_counters(seed)
        self._build_obstacles(scene_obstacles)
        self._build_state()
        self._build_stages()
        self._build_outputs()

    def _f32(self, *shape: int) -> torch.Tensor:
        return torch.zeros(*shape, dtype=torch.float32, device=self.device)

    def _i64(self, *shape: int) -> torch.Tensor:
        return torch.zeros(*shape, dtype=torch.int64, device=self.device)

    def _flag(self, *shape: int) -> torch.Tensor:
        return torch.zeros(*shape, dtype=torch.bool, device=self.device)

    def _build_spawns(self, spawns: Sequence[torch.Tensor] | None) -> None:
        """The spawn table (qualifying every scene when no spawns are given) and, in point-goal episodes,
        the goal bank, which drops the spawns no goal pairs with."""
        from navi_env.space.qualify import scene_spawns

        cfg, corpus = self.config, self.corpus
        n_scenes = len(corpus)
        spawn_lists = (
            list(spawns) if spawns is not None else [scene_spawns(corpus, s) for s in range(n_scenes)]
        )
        if len(spawn_lists) != n_scenes:
            raise ValueError(f"got spawns for {len(spawn_lists)} scenes, the corpus has {n_scenes}")
        self.goal_bank: goals.GoalBank | None = None  # every scene's goals and path lengths (point-goal)
        if cfg.task == "pointgoal":
            for info in corpus.infos:
                if len(info.class_names) > FIRST_MARK_CODE - 1:
                    raise ValueError(
                        f"scene {info.name!r} has {len(info.class_names)} semantic classes; point-goal episodes "
                        f"keep codes {FIRST_MARK_CODE}-255 for the goal mark (at most 239 classes)"
                    )
            tables = goals.build_tables(corpus, spawn_lists, cfg.goal, cfg.drone_radius)
            self.goal_bank, spawn_lists = goals.goal_bank(tables, spawn_lists, self.device)
        clearances = [self._clearance_at(s, p) for s, p in enumerate(spawn_lists)]
        self.spawns = episodes.spawn_table(spawn_lists, clearances, self.device)

    def _build_bounds(self) -> None:
        """Every scene's geometry bounds grown by the margin the drone is kept within."""
        infos, margin = self.corpus.infos, self.config.bounds_margin
        lo = torch.tensor([info.bounds_min for info in infos], dtype=torch.float32)  # (S, 3)
        hi = torch.tensor([info.bounds_max for info in infos], dtype=torch.float32)  # (S, 3)
        self._lo = (lo - margin).to(self.device)  # (S, 3)
        self._hi = (hi + margin).to(self.device)  # (S, 3)

    def _build_ray_pattern(self) -> None:
        """The sensor's ray directions and, on CUDA, the order the tracer runs them in."""
        cfg, dev = self.config, self.device
        self.directions = ray_pattern(cfg.azimuth_bins, cfg.elevation_bins, cfg.sensor, dev)  # (R, 3)
        tiles = dev.type == "cuda" and cfg.azimuth_bins % 16 == 0 and cfg.elevation_bins % 2 == 0
        # (R,) int32 16x2 tiles of neighbouring rays per GPU warp: same results, more coherent warps
        self.ray_order = tiled_ray_order(cfg.azimuth_bins, cfg.elevation_bins).to(dev) if tiles else None

    def _build_counters(self, seed: int) -> None:
        """The seed and step counter that key the random numbers, and the actor indices."""
        dev = self.device
        self.seed = torch.full((), seed, dtype=torch.int64, device=dev)  # () seed of the random numbers
        self.tick = torch.zeros(
            (), dtype=torch.int64, device=dev
        )  # () step counter keying the random numbers
        self.actor = torch.arange(self.n, dtype=torch.int64, device=dev)  # (N,)
        self._actor32 = self.actor.to(torch.int32)  # (N,) each actor's obstacle world

    def _build_obstacles(self, scene_obstacles: Sequence[Mapping[str, float]] | None) -> None:
        """The primitive records the tracer reads: each scene's scripted obstacles, then the squad's drones."""
        cfg, dev, n = self.config, self.device, self.n
        n_scenes = len(self.corpus)
        declared = list(scene_obstacles) if scene_obstacles is not None else [{}] * n_scenes
        if len(declared) != n_scenes:
            raise ValueError(f"got obstacle settings for {len(declared)} scenes, the corpus has {n_scenes}")
        names = [info.name for info in self.corpus.infos]
        self.scene_obstacles = obstacle_motion.scene_obstacles(
            cfg.obstacles, declared, names, dev
        )  # (S,) each
        slots = self.scene_obstacles.slots
        self.squad = g = (
            cfg.obstacles.squad if cfg.obstacles.squad >= 2 else 1
        )  # G actors that see each other
        if n % g:
            raise ValueError(f"obstacles.squad {g} must divide the number of actors {n}")
        drones = g if g > 1 else 0
        # (N, K + G, 16) every record the tracer reads: K scripted obstacles, then the G drones of the squad
        self.prims = torch.zeros(n, slots + drones, ob.WORDS, device=dev) if slots + drones else None
        self.obstacles = (
            obstacle_motion.allocate(n, cfg.obstacles, dev, slots, records=self.prims[:, :slots])
            if slots > 0 and self.prims is not None
            else None
        )  # scripted obstacles' motion state (records: a view of self.prims); None without them
        self._mates = (self.actor - self.actor % g)[:, None] + torch.arange(g, device=dev)[None, :]  # (N, G)
        if drones and self.prims is not None:
            mates = self.prims[:, slots:]  # (N, G, 16) view: the squad's drones, each owned by its actor
            mates[..., ob.KIND] = float(ob.SPHERE)
            mates[..., ob.CLASS] = float(cfg.obstacles.drone_class)
            mates[..., ob.OWNER] = self._mates.to(torch.float32)
            mates[..., ob.RADIUS] = cfg.drone_radius
            mates[..., ob.QUAT] = 1.0

    def _build_state(self) -> None:
        """Per-actor state (pose, episode counters, visited cells, goal), the traced rays and the
        observation buffers."""
        cfg, dev, n = self.config, self.device, self.n
        f32, i64 = self._f32, self._i64
        table_bytes = (1 << cfg.reward.exploration_table_bits) // 8
        self.actions = f32(n, 4)  # (N, 4) this step's actions (a fixed address for the CUDA graph)
        self.scene = i64(n)  # (N,) scene index per actor
        self.position = f32(n, 3)  # (N, 3) world meters
        self.yaw = f32(n)  # (N,) radians
        self.safe_distance = f32(n)  # (N,) certified lower bound of the clearance (physics), meters
        self.clearance = f32(
            n
        )  # (N,) view clearance: shortest exact depth of the view, capped at clearance_range
        self.steps = i64(n)  # (N,) steps in this episode
        self.episodes_on_scene = i64(n)  # (N,) ended episodes on the current scene
        self.episode_return = f32(n)  # (N,)
        self.visited = torch.zeros(n, table_bytes, dtype=torch.uint8, device=dev)  # (N, M/8) cell bitmap
        self.goal = i64(n)  # (N,) goal j of the bank per actor (point-goal)
        self.goal_position = f32(n, 3)  # (N, 3) world meters
        self.goal_distance = f32(n)  # (N,) true path length to the goal, meters
        self.start_distance = f32(n)  # (N,) its value at the episode's start
        self.path_length = f32(n)  # (N,) meters flown this episode
        self.fresh = torch.ones(
            n, dtype=torch.bool, device=dev
        )  # (N,) previous frame is from another episode
        self.depth = f32(n, cfg.rays)  # (N, R) traced distance, meters
        self.semantic = torch.zeros(
            n, cfg.rays, dtype=torch.uint8, device=dev
        )  # (N, R) 0 miss, 1 + class on a hit
        self._obs_ring = tuple(
            f32(n, CHANNELS, cfg.azimuth_bins, cfg.elevation_bins) for _ in range(cfg.obs_buffers)
        )  # (N, 3, Az, El) each
        self._slot = 0  # the ring's buffer this step writes (and, on CUDA, its own graph)
        self.obs = self._obs_ring[0]  # (N, 3, Az, El)

    def _build_stages(self) -> None:
        """The stages' elementwise functions: compiled on the CUDA path (`fused`), eager otherwise."""
        fuse = fused if self._fast else _eager
        self._commanded_step = fuse(physics.commanded_step)
        self._safe_move = fuse(physics.safe_move)
        self._visit = fuse(rewards.visit)
        self._next_scene = fuse(episodes.next_scene)
        self._draw_spawns = fuse(episodes.draw_spawns)
        self._reward_terms = fuse(rewards.reward_terms)
        self._draw_goal = fuse(goals.draw_goal)
        # eager everywhere: inductor rounds the hop sums of goal_distance differently
        self._goal_distance = goals.goal_distance
        self._semantic_table = semantic_table(self.device)  # (256,) float32 channel 1 per semantic code

    def _build_outputs(self) -> None:
        """View statistics, rewards, episode flags, info, and the StepOut per observation buffer."""
        n, f32, i64, flag = self.n, self._f32, self._i64, self._flag
        self.void = f32(n)  # (N,) view statistics of the current observation
        self.near = f32(n)  # (N,)
        self.mid = f32(n)  # (N,)
        self.front_mid = f32(n)  # (N,)
        # (N,) each: the statistics of the view the last action was chosen on
        self.before = {k: f32(n) for k in VIEW_KEYS}
        self.reward = f32(n)  # (N,)
        self.terms = {name: f32(n) for name in rewards.task_terms(self.config.task)}  # name -> (N,)
        self.done = flag(n)  # (N,) terminated: at the goal (point-goal); always False when exploring
        self.truncated = flag(n)  # (N,)
        self.ended = flag(n)  # (N,) done or truncated: auto-reset this step
        self._never = flag(n)  # (N,) always False
        self.info = {
            "clearance": f32(n),  # (N,) meters after the move
            "collision": flag(n),  # (N,)
            "position": f32(n, 3),  # (N, 3) world meters after the move
            "novel_cell": flag(n),  # (N,)
            "speed": f32(n),  # (N,) m/s actually flown
            "episode_return": f32(n),  # (N,) return so far (final where truncated)
            "episode_length": i64(n),  # (N,) steps so far (final where truncated)
            "starved": flag(n),  # (N,) ended by starvation
            "scene_id": i64(n),  # (N,)
            "obstacle_collision": flag(n),  # (N,) the collision was with a moving obstacle
            "drone_collision": flag(n),  # (N,) the collision was with another drone of the squad
        }
        if self.config.task == "pointgoal":
            self.info |= {
                "success": flag(n),  # (N,) the episode ended at the goal
                "goal_distance": f32(n),  # (N,) path length to the goal after the move, meters
                "start_distance": f32(n),  # (N,) path length to the goal at the episode's start
                "path_length": f32(n),  # (N,) meters flown this episode so far (final where it ended)
            }
        self._outs = tuple(
            StepOut(
                obs=obs,
                reward=self.reward,
                done=self.done,
                truncated=self.truncated,
                reward_terms=self.terms,
                info=self.info,
            )
            for obs in self._obs_ring
        )
        self.out = self._outs[0]

    compact_obs = True
    """Observations are DistanceMatrix v2 as navi_env.sim.observation writes them (see its pack / unpack)."""

    @property
    def obs_shape(self) -> tuple[int, int, int]:
        """(3, Az, El) of one actor's observation."""
        return (CHANNELS, self.config.azimuth_bins, self.config.elevation_bins)

    def bytes_per_actor(self) -> int:
        """Device bytes of per-actor state and buffers, divided by N."""
        tensors = [
            v for v in vars(self).values() if isinstance(v, torch.Tensor) and v.ndim and v.shape[0] == self.n
        ]
        tensors += list(self.terms.values()) + list(self.info.values()) + list(self._obs_ring[1:])
        if self.obstacles is not None:  # its records are a view of self.prims, counted above
            state = vars(self.obstacles).items()
            tensors += [v for k, v in state if k != "prims" and v.ndim and v.shape[0] == self.n]
        return sum(t.numel() * t.element_size() for t in tensors) // self.n

    def reset(self, seed: int | None = None) -> torch.Tensor:
        """Start every actor's first episode (scenes spread round-robin); returns obs (N, 3, Az, El)."""
        if seed is not None:
            self.seed.fill_(seed)
        self.tick.zero_()
        self.scene.copy_((self.actor // self.squad) % self.spawns.scenes)  # squads share a scene
        self.episodes_on_scene.zero_()
        self.episode_return.zero_()
        self.steps.zero_()
        everyone = torch.ones(self.n, dtype=torch.bool, device=self.device)  # (N,)
        self._spawn(everyone)
        self._place_obstacles(everyone)
        self._drones_where_they_are()
        self._trace()
        self._observe_from_trace()
        return self.obs

    @property
    def goal_marks(self) -> bool:
        """Channel 1 carries the goal mark (point-goal episodes): semantic codes 240-255 are marks."""
        return self.goal_bank is not None

    def step(self, actions: torch.Tensor) -> StepOut:
        """Advance every actor by one step with actions (N, 4) in [-1, 1] (clipped).

        Returns the environment's buffers: the same StepOut every time, or with EnvConfig.obs_buffers=2
        one of two whose observations alternate (the other is `previous_obs`).
        """
        if actions.shape != (self.n, 4):
            raise ValueError(f"actions must be ({self.n}, 4), got {tuple(actions.shape)}")
        self.actions.copy_(actions)
        if len(self._obs_ring) > 1:
            self._slot ^= 1
            self.obs, self.out = self._obs_ring[self._slot], self._outs[self._slot]
        graph = self._graphs[self._slot]
        if graph is not None and self.timer is None:
            graph.replay()
        elif self._graph_ready():
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                self._step()
            graph.replay()
            self._graphs[self._slot] = graph
        else:
            self._step()
            self._eager_steps += 1
        return self.out

    @property
    def previous_obs(self) -> torch.Tensor:
        """(N, 3, Az, El) the observation handed out before `obs` (by the last step or reset), intact until
        the next step writes it again. Needs EnvConfig.obs_buffers == 2."""
        if len(self._obs_ring) < 2:
            raise ValueError("previous_obs needs an env built with EnvConfig(obs_buffers=2)")
        return self._obs_ring[self._slot ^ 1]

    def _graph_ready(self) -> bool:
        """Record the step as a CUDA graph now? (the CUDA path, no timer, after two eager steps)."""
        return self._fast and self.timer is None and self._eager_steps >= 2

    def _step(self) -> None:
        """One step of every actor: reads self.actions, writes the buffers (see the module docstring)."""
        cfg = self.config
        stage = self.timer.stage if self.timer is not None else _no_stage
        self.tick.add_(1)
        with stage("physics"):
            struck = self._move_obstacles()  # (N,) bool: an obstacle ran into the drone
            # (N, 3) body m/s, (N,) rad/s, (N, 3) commanded world move, m
            vel, yaw_rate, step = self._commanded_step(self.actions, self.clearance, self.yaw, cfg)
            if self.squad > 1:  # a mate may move up to its commanded length: it fills that much more room
                self._place_drones(self.position, cfg.drone_radius + step.norm(dim=1))
            if self.prims is not None:
                self.safe_distance.copy_(self._distance(self.position))  # the field changed under the drone
            move = self._safe_move(
                self.position,
                self.safe_distance,
                step,
                self._lo[self.scene],
                self._hi[self.scene],
                self._distance,
                cfg.drone_radius,
                cfg.drone_radius * cfg.path_clearance_fraction,
                cfg.collision_iterations,
            )
            novel = self._visit(
                self.visited, move.position, cfg.reward.exploration_cell, cfg.reward.exploration_table_bits
            )  # (N,) bool
            contact, obstacle_contact, drone_contact = move.contact, struck, self._never
            if self.obstacles is not None:
                nearest = obstacle_motion.obstacle_distance(self.obstacles, move.position, self._fast)  # (N,)
                obstacle_contact = struck | (move.contact & (nearest <= move.clearance + 1e-4))  # (N,)
                contact = move.contact | struck  # (N,) bool
            if self.squad > 1:
                drone_contact = move.contact & (self._mate_distance(move.position) <= move.clearance + 1e-4)
            progress: tuple[torch.Tensor, torch.Tensor] | None = None
            if self.goal_bank is not None:
                progress = self._goal_step(move)  # Phi_goal's progress (N,) in s and s', meters
        with stage("episode"):
            self.steps.add_(1)
            time_limit, starved = episodes.truncation(self.steps, self.void, cfg)  # (N,), (N,) bool
            torch.logical_or(time_limit, starved, out=self.truncated)
            self.truncated.logical_and_(~self.done)
            if self.squad > 1:  # the squad changes scene together: every member's episode ends then
                leader = self._mates[:, 0]  # (N,)
                full = (
                    self.episodes_on_scene[leader] + (self.done | self.truncated)[leader].long()
                    >= cfg.episodes_per_scene
                )
                self.truncated.logical_or_(full & ~self.done)
            torch.logical_or(self.done, self.truncated, out=self.ended)
            self._record_info(move, contact, obstacle_contact, drone_contact, novel, starved)
            for name, value in self.before.items():
                value.copy_(getattr(self, name))
            self.position.copy_(move.position)
            self.safe_distance.copy_(move.clearance)
            self.yaw.copy_(physics.wrap_angle(self.yaw + yaw_rate * cfg.dt))
            self._end_episodes(self.ended)
            self._drones_where_they_are()
        with stage("trace"):
            self._trace()
        with stage("observation"):
            self._observe_from_trace()
        with stage("reward"):
            ended = self.ended  # (N,) bool: not traced at the final pose, the last view stands in

            def after(now: torch.Tensor, before: torch.Tensor) -> torch.Tensor:
                return torch.where(ended, before, now)  # (N,)

            inputs = rewards.RewardInputs(
                contact=contact,
                speed=vel.norm(dim=1),
                novel=novel,
                clearance_before=self.before["clearance"],
                clearance=after(self.clearance, self.before["clearance"]),
                mid_before=self.before["mid"],
                mid=after(self.mid, self.before["mid"]),
                front_mid_before=self.before["front_mid"],
                front_mid=after(self.front_mid, self.before["front_mid"]),
                void=after(self.void, self.before["void"]),
                near=after(self.near, self.before["near"]),
                progress_before=progress[0] if progress is not None else None,
                progress=progress[1] if progress is not None else None,
                success=self.done if progress is not None else None,
            )
            self.reward.zero_()
            for name, value in self._reward_terms(inputs, cfg).items():
                self.terms[name].copy_(value)
                self.reward.add_(value)
            self.episode_return.add_(self.reward)
            self.info["episode_return"].copy_(self.episode_return)
            self.info["clearance"].copy_(inputs.clearance)
            self.episode_return.masked_fill_(ended, 0.0)

    def _goal_step(self, move: physics.Move) -> tuple[torch.Tensor, torch.Tensor]:
        """Point-goal bookkeeping of the move: path length to the goal and flown, success (self.done).
        Returns the goal potential's progress max(d0 - d, 0), capped at goal.far, before and after (N,)."""
        assert self.goal_bank is not None
        cfg = self.config
        dist = self._goal_distance(self.goal_bank, self.goal, self.scene, move.position)  # (N,)
        dist = torch.where(
            torch.isfinite(dist), dist, self.goal_distance
        )  # no free centre round it: as before
        flown = move.displacement.norm(dim=1)  # (N,) meters
        self.done.copy_((dist <= cfg.goal.radius) & (flown <= cfg.goal.stop_speed * cfg.dt))
        before = (self.start_distance - self.goal_distance).clamp(0.0, cfg.goal.far)  # (N,)
        after = (self.start_distance - dist).clamp(0.0, cfg.goal.far)  # (N,)
        self.goal_distance.copy_(dist)
        self.path_length.add_(flown)
        self.info["success"].copy_(self.done)
        self.info["goal_distance"].copy_(dist)
        self.info["start_distance"].copy_(self.start_distance)
        self.info["path_length"].copy_(self.path_length)
        return before, after

    def _record_info(
        self,
        move: physics.Move,
        contact: torch.Tensor,
        obstacle_contact: torch.Tensor,
        drone_contact: torch.Tensor,
        novel: torch.Tensor,
        starved: torch.Tensor,
    ) -> None:
        """Info of the step that just ended (clearance and return are written by the reward stage)."""
        self.info["collision"].copy_(contact)
        self.info["obstacle_collision"].copy_(obstacle_contact)
        self.info["drone_collision"].copy_(drone_contact)
        self.info["position"].copy_(move.position)
        self.info["novel_cell"].copy_(novel)
        self.info["speed"].copy_(move.displacement.norm(dim=1) / self.config.dt)
        self.info["episode_length"].copy_(self.steps)
        self.info["starved"].copy_(starved)
        self.info["scene_id"].copy_(self.scene)

    def _end_episodes(self, ended: torch.Tensor) -> None:
        """Auto-reset actors with `ended` (N,) bool: count, maybe rotate scene, spawn, clear state."""
        count, rotate = episodes.rotation(self.episodes_on_scene, ended, self.config)
        other = self._next_scene(self.scene, self.spawns.scenes, self.seed, self.tick, self.actor)  # (N,)
        if self.squad > 1:  # the leader's count decides and its draw is the squad's next scene
            leader = self._mates[:, 0]  # (N,)
            rotate, other = rotate[leader], other[leader]
            count = torch.where(rotate, torch.zeros_like(count), count)
        self.episodes_on_scene.copy_(count)
        self.scene.copy_(torch.where(rotate, other, self.scene))
        self.steps.masked_fill_(ended, 0)
        self._spawn(ended)
        self._place_obstacles(ended)

    def _spawn(self, mask: torch.Tensor) -> None:
        """Place actors with `mask` (N,) bool at a fresh spawn of their scene; clear their visited cells."""
        pos, clr, yaw, row = self._draw_spawns(
            self.spawns, self.scene, self.seed, self.tick, self.actor, self.squad
        )
        self.position.copy_(torch.where(mask[:, None], pos, self.position))
        if self.goal_bank is not None:
            bank = self.goal_bank
            goal = self._draw_goal(bank, self.scene, row, self.seed, self.tick, self.actor)  # (N,)
            self.goal.copy_(torch.where(mask, goal, self.goal))
            self.goal_position.copy_(bank.position[self.goal])
            start = self._goal_distance(bank, self.goal, self.scene, self.position)  # (N,)
            self.start_distance.copy_(torch.where(mask, start, self.start_distance))
            self.goal_distance.copy_(torch.where(mask, start, self.goal_distance))
            self.path_length.masked_fill_(mask, 0.0)
        self.safe_distance.copy_(torch.where(mask, clr, self.safe_distance))
        self.yaw.copy_(torch.where(mask, yaw, self.yaw))
        self.visited.masked_fill_(mask[:, None], 0)
        cfg = self.config.reward
        self._visit(self.visited, self.position, cfg.exploration_cell, cfg.exploration_table_bits)
        self.fresh.copy_(mask)

    def _place_obstacles(self, mask: torch.Tensor) -> None:
        """New obstacles around the (just spawned) drones of the actors with `mask` (N,) bool."""
        if self.obstacles is None:
            return
        if self.device.type == "cpu" and not bool(mask.any()):
            return  # nothing to place (a host read costs nothing on the CPU; CUDA always runs the fixed work)
        cfg = self.config
        obstacle_motion.place(
            self.obstacles,
            mask,
            self.spawns,
            self.scene,
            self.position,
            cfg.drone_radius,
            cfg.obstacles,
            self.scene_obstacles,
            self.seed,
            self.tick,
            self.actor,
            self._fast,
        )

    def _place_drones(self, position: torch.Tensor, radius: torch.Tensor) -> None:
        """Write the squad's drone records of every actor's world: centres at the members' position (N, 3),
        radii (N,) per member."""
        assert self.prims is not None
        first = self.prims.shape[1] - self.squad
        self.prims[:, first:, ob.CENTER : ob.CENTER + 3] = position[self._mates]  # (N, G, 3)
        self.prims[:, first:, ob.RADIUS] = radius[self._mates]  # (N, G)

    def _drones_where_they_are(self) -> None:
        """Squad drone records at the drones' current positions with the plain drone radius (for the view)."""
        if self.squad > 1:
            self._place_drones(self.position, torch.full_like(self.safe_distance, self.config.drone_radius))

    def _mate_distance(self, points: torch.Tensor) -> torch.Tensor:
        """Distance (N,) from each actor's point (N, 3) to the nearest other drone record of its squad."""
        assert self.prims is not None
        mates = self.prims[:, self.prims.shape[1] - self.squad :]  # (N, G, 16)
        d = ob.distance(mates, points[:, None, :])  # (N, G)
        own = self._mates == self.actor[:, None]  # (N, G) bool
        return torch.where(own, torch.full_like(d, float("inf")), d).amin(dim=1)

    def _move_obstacles(self) -> torch.Tensor:
        """The obstacles' scripted step (stopped at the drone). Returns (N,) bool: an obstacle ran into the
        drone."""
        if self.obstacles is None:
            return self._never  # (N,) all False
        cfg = self.config
        k = self.obstacles.count
        scene_k = self.scene.repeat_interleave(k)  # (N*K,)

        def static(points: torch.Tensor) -> torch.Tensor:
            return sample_distance(self.corpus, scene_k, points)  # (N*K,)

        return obstacle_motion.advance(
            self.obstacles,
            static,
            self.position,
            cfg.drone_radius,
            cfg.dt,
            cfg.obstacles,
            self.seed,
            self.tick,
            self.actor,
            self._fast,
        )

    def _trace(self) -> None:
        cfg = self.config
        trace(
            self.corpus,
            self.scene,
            self.position,
            self.directions,
            yaw=self.yaw,
            out_depth=self.depth,
            out_semantic=self.semantic,
            ray_order=self.ray_order,
            max_steps=cfg.trace_max_steps,
            horizon=cfg.horizon,
            hit_epsilon=cfg.hit_epsilon,
            hit_slope=cfg.hit_slope,
            skip_direction_validation=True,
            prims=self.prims,
        )

    def _observe_from_trace(self) -> None:
        """Sensor model, then obs from the sensed rays and the view statistics from the exact ones."""
        cfg = self.config
        depth, semantic = self.depth, self.semantic  # (N, R) float32, (N, R) uint8
        prev = self._obs_ring[self._slot ^ 1] if len(self._obs_ring) > 1 else None  # the last frame
        if cfg.sensor.enabled:
            depth, semantic = apply_sensor(depth, semantic, cfg.sensor, cfg.horizon, self.seed, self.tick)
        views = (self.obs, depth, semantic, self.fresh, self.depth, self.semantic)  # what both passes read
        if self._fast:
            stats = observe(*views, self._semantic_table, cfg.horizon, cfg.reward, prev)
        else:
            stats = observe_ref(*views, cfg.horizon, cfg.reward, prev)
        self.void.copy_(stats.void)
        self.near.copy_(stats.near)
        self.mid.copy_(stats.mid)
        self.front_mid.copy_(stats.front_mid)
        torch.clamp(stats.clearance, max=cfg.clearance_range, out=self.clearance)
        if self.goal_bank is not None:
            offset = self.goal_position - self.position  # (N, 3)
            goals.paint_goal(self.obs, offset, self.yaw, cfg, self.goal_bank.edges)
        self.fresh.zero_()

    def _distance(self, points: torch.Tensor) -> torch.Tensor:
        """Clearance (M,) at points (M, 3), M a multiple of N in actor-major order."""
        per = points.shape[0] // self.n
        scene = self.scene.repeat_interleave(per)  # (M,)
        if self.prims is None:
            return sample_distance(self.corpus, scene, points)
        world = self._actor32.repeat_interleave(
            per
        )  # (M,) int32: each point's actor's world, own drone left out
        return sample_distance(
            self.corpus, scene, points, prims=self.prims, prim_world=world, prim_owner=world
        )

    def _clearance_at(self, scene: int, points: torch.Tensor) -> torch.Tensor:
        """Clearance (K,) at a scene's points (K, 3), on the host (construction only)."""
        dev = self.corpus.device
        ids = torch.full((points.shape[0],), scene, dtype=torch.int64, device=dev)  # (K,)
        return sample_distance(self.corpus, ids, points.to(dev, torch.float32).contiguous()).cpu()


def _check_band(corpus: SceneCorpus, drone_radius: float) -> None:
    """Every scene's exact band reaches past the drone radius, or the drone would read contact far from
    walls."""
    for info in corpus.infos:
        certified = (info.band - math.sqrt(3.0) / 2.0) * info.voxel_size  # a far cube's least bound, m
        if certified < drone_radius:
            raise ValueError(
                f"scene {info.name!r} is exact only {certified:.3f} m from its surfaces (band {info.band} "
                f"voxels of {info.voxel_size:.3f} m), less than the drone radius {drone_radius} m: far "
                "from walls the drone would read contact. Recompile it with `navi compile --band-m 0.5`."
            )


@contextlib.contextmanager
def _no_stage(name: str) -> Iterator[None]:
    yield


F = TypeVar("F", bound=Callable[..., Any])


def fused(fn: F, backend: str = "inductor", fullgraph: bool = False) -> F:
    """fn compiled by torch.compile into few kernels (the env's CUDA path; `SdfDagEnv(eager=True)` runs
    fn itself), compiled by the first eager steps, before the step's CUDA graph is recorded. Inductor
    runs without fp contraction (`emulate_precision_casts`) and with round-to-nearest division
    (`eager_numerics.division_rounding`), so every float operation rounds as in the eager kernels;
    `sample_distance` enters the graph as an opaque op (navi_env.tracer.trace._sample_op).

    Shapes are specialised first and made dynamic when a second env brings other sizes. Not fullgraph:
    past dynamo's recompile limit (many envs with other configurations in one process) a function
    runs its eager kernels, which give the same values, instead of failing. Tests compile with
    `fullgraph=True` and `backend="aot_eager"` (no codegen) to check that every graph stays whole."""
    options: dict[str, str | int | bool | Callable[..., Any]] | None = None
    if backend == "inductor":
        options = {"emulate_precision_casts": True, "eager_numerics.division_rounding": True}
    return cast(F, torch.compile(fn, fullgraph=fullgraph, backend=backend, options=options))


def _eager(fn: F) -> F:
    return fn
