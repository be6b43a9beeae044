"""Every knob of the drone environment in one typed dataclass (docs/SIMULATION.md explains each).

Units: meters, seconds, radians. World frame: right-handed, +Z up. Body frame: +X forward, +Y left,
+Z up; yaw turns the body about +Z (counter-clockwise seen from above is positive).
"""

from __future__ import annotations

from dataclasses import dataclass, field

RESOLUTIONS: tuple[tuple[int, int], ...] = ((256, 48), (384, 72), (512, 96), (768, 144))
"""Observation resolutions (Az, El) the environment accepts."""


@dataclass(frozen=True)
class SensorConfig:
    """Optional sensor model; with the defaults the observation is the exact traced depth."""

    range_noise_std: float = 0.0
    """Standard deviation of additive Gaussian range noise, meters (0 = off)."""
    range_noise_relative: float = 0.0
    """Extra noise standard deviation per meter of range (0 = off): std = abs + relative * depth."""
    dropout: float = 0.0
    """Probability that a ray returns nothing (reported as a miss at the horizon), per ray and step."""
    elevation_min_deg: float = -90.0
    """Lowest elevation of the ray pattern, degrees (-90 = straight down)."""
    elevation_max_deg: float = 90.0
    """Highest elevation of the ray pattern, degrees (+90 = straight up)."""

    @property
    def enabled(self) -> bool:
        """True when noise or dropout changes the observation."""
        return self.range_noise_std > 0.0 or self.range_noise_relative > 0.0 or self.dropout > 0.0


@dataclass(frozen=True)
class RewardConfig:
    """Weights and shapes of every reward term; the reward is the sum of the weighted terms.

    Terms that reward a change of state are potential-based (Ng, Harada & Russell 1999):
    F = shaping_gamma * Phi(s') - Phi(s), so no closed loop of states earns net shaping reward.
    docs/SIMULATION.md gives every term's formula and its bound per step.
    """

    collision_weight: float = 15.0
    """Explore: weight of the collision penalty, -(collision_base + speed / max_speed) on a contact step, so
    a full-speed crash costs as much as 75 novel cells (point-goal's is pointgoal_collision_weight)."""
    collision_base: float = 0.5
    """Part of the collision penalty paid even at zero speed (grazing)."""
    proximity_weight: float = 0.2
    """Proximity cost of the state after the move: -(1 - clearance / proximity_distance)^2 inside it."""
    proximity_distance: float = 1.0
    """Clearance (m) under which the proximity cost and the escape potential vary."""
    escape_weight: float = 0.5
    """Escape potential: weight * min(clearance, proximity_distance) / (max_speed * dt); its shaping
    pays for clearance gained near geometry and charges the same amount for clearance lost."""
    exploration_weight: float = 0.3
    """Bonus for entering a cell not visited this episode (1 per novel cell)."""
    exploration_min_clearance: float = 0.6
    """A novel cell pays only when the clearance there is at least this (m): wall hugging earns nothing."""
    exploration_cell: float = 1.0
    """Edge of an exploration cell, meters."""
    exploration_table_bits: int = 15
    """log2 of the visited-cell bitmap size per actor (2^15 bits = 4 KiB)."""
    blind_weight: float = 0.05
    """Information foraging: -(void fraction above blind_threshold, rescaled to [0, 1])."""
    blind_threshold: float = 0.5
    """Fraction of horizon-saturated rays tolerated before the blind penalty starts."""
    near_weight: float = 0.05
    """Information foraging: -(fraction of rays closer than near_distance) (near-field wall hugging)."""
    near_distance: float = 1.0
    """Range (m) under which a ray counts as near field."""
    structure_weight: float = 0.05
    """Structure potential: weight * fraction of the view's rays in the mid-range band."""
    structure_front_weight: float = 0.05
    """Structure potential: weight * mid-range fraction of the front half of the view (turning toward
    structure raises it)."""
    mid_range_min: float = 2.0
    """Lower edge (m) of the mid-range band of structure seeking."""
    mid_range_max: float = 20.0
    """Upper edge (m) of the mid-range band of structure seeking."""
    existential_tax: float = -0.02
    """Constant reward every step, whatever the drone does (it does not by itself make hovering cost more than
    flying: exploring episodes end only by time or starvation)."""
    shaping_gamma: float = 0.99
    """Discount of the potential-based terms; set it to the learner's gamma (PPOConfig.gamma)."""
    progress_weight: float = 0.5
    """Point-goal: goal potential per meter of path length gained toward the goal (weight * max(d0 - d,
    0), d the true path length to the goal and d0 its value at the episode's start); its shaping pays for
    each meter of progress and charges the same for each meter lost."""
    success_weight: float = 5.0
    """Point-goal: paid once, on the step that ends the episode at the goal."""
    pointgoal_collision_weight: float = 3.0
    """Point-goal: weight of the collision penalty (explore's is collision_weight)."""

    def collision_price(self, task: str) -> float:
        """The collision penalty's weight in `task`'s episodes (EnvConfig.task; COLLISION_WEIGHT names it)."""
        return float(getattr(self, COLLISION_WEIGHT[task]))


COLLISION_WEIGHT: dict[str, str] = {"explore": "collision_weight", "pointgoal": "pointgoal_collision_weight"}
"""Per task, the RewardConfig field that prices a contact in its episodes."""


OBSTACLE_SHAPES: tuple[str, ...] = ("sphere", "capsule", "box", "obb")
"""Primitive shapes a scripted obstacle can take (navi_env.tracer.primitives: sphere, capsule, axis-aligned box,
oriented box)."""
OBSTACLE_MOTIONS: tuple[str, ...] = ("linear", "circular", "random_walk")
"""Scripted motions: back and forth along a segment, round a horizontal circle, a random walk on a leash."""


@dataclass(frozen=True)
class ObstacleConfig:
    """Scripted moving obstacles, `count` per actor's world, traced and felt without any rebuild of the
    scene (docs/SIMULATION.md, "Moving obstacles"). Off by default (count 0)."""

    count: int = 0
    """K: obstacles per actor (slots fixed at env creation; the tracer tests every one on every ray)."""
    shapes: tuple[str, ...] = OBSTACLE_SHAPES
    """Shapes given to the slots in turn (slot k gets shapes[k % len])."""
    motions: tuple[str, ...] = OBSTACLE_MOTIONS
    """Motions given to the slots in turn (slot k gets motions[k % len])."""
    size_min: float = 0.3
    """Smallest radius / half extent, meters."""
    size_max: float = 0.8
    """Largest radius / half extent, meters."""
    speed_min: float = 0.5
    """Slowest obstacle, m/s."""
    speed_max: float = 3.0
    """Fastest obstacle, m/s (may exceed the drone's speed: the sweep test stops it at the drone)."""
    reach_min: float = 1.0
    """Shortest half segment (linear), circle radius (circular) or leash (random walk), meters."""
    reach_max: float = 4.0
    """Longest half segment, circle radius or leash, meters."""
    place_min: float = 2.0
    """An obstacle starts at least this far from its actor's spawn, meters."""
    place_max: float = 15.0
    """and at most this far (spawn points of the scene farther away are not used)."""
    place_tries: int = 8
    """Spawn points tried per obstacle at placement; with none valid the slot stays empty that episode."""
    walk_turn: float = 0.3
    """Random walk: standard deviation of the heading change per step (unit heading + this * noise)."""
    wall_iterations: int = 3
    """Steps of the march that stops an obstacle at the static geometry (static samples per step)."""
    sweep_iterations: int = 16
    """Steps of the conservative march that stops an obstacle at a drone (never through it)."""
    semantic_class: int = 8
    """Class of an obstacle hit (semantic 1 + class in the observation)."""
    squad: int = 0
    """Other drones as obstacles: squads of this many consecutive actors share a scene (always) and see
    and collide with each other, each drone a sphere of drone_radius (0 or 1: off)."""
    drone_class: int = 9
    """Class of a hit on another drone (semantic 1 + class)."""

    def __post_init__(self) -> None:
        if self.count < 0 or self.count > 64:
            raise ValueError("obstacles.count must be in [0, 64]")
        if not self.shapes or any(s not in OBSTACLE_SHAPES for s in self.shapes):
            raise ValueError(f"obstacles.shapes must be a non-empty subset of {OBSTACLE_SHAPES}")
        if not self.motions or any(m not in OBSTACLE_MOTIONS for m in self.motions):
            raise ValueError(f"obstacles.motions must be a non-empty subset of {OBSTACLE_MOTIONS}")
        if not 0.0 < self.size_min <= self.size_max:
            raise ValueError("obstacles need 0 < size_min <= size_max")
        if not 0.0 <= self.speed_min <= self.speed_max:
            raise ValueError("obstacles need 0 <= speed_min <= speed_max")
        if not 0.0 < self.reach_min <= self.reach_max:
            raise ValueError("obstacles need 0 < reach_min <= reach_max")
        if not 0.0 <= self.place_min < self.place_max:
            raise ValueError("obstacles need 0 <= place_min < place_max")
        if self.place_tries < 1 or self.sweep_iterations < 1 or self.wall_iterations < 1:
            raise ValueError("obstacles need place_tries, sweep_iterations and wall_iterations >= 1")
        if not 0 <= self.semantic_class <= 253 or not 0 <= self.drone_class <= 253:
            raise ValueError("obstacles.semantic_class and drone_class must be in [0, 253]")
        if not 0 <= self.squad <= 64:
            raise ValueError("obstacles.squad must be in [0, 64]")


TASKS: tuple[str, ...] = ("explore", "pointgoal")
"""What an episode asks of the drone: explore (cover the scene, no end but the time limit) or pointgoal
(reach a goal drawn in the scene's free space; docs/TASKS.md)."""
POINTGOAL_EPISODE_STEPS = 500
"""Steps of a point-goal episode where nothing else is said (50 s: a 30 m path at 1 m/s fits)."""


@dataclass(frozen=True)
class GoalConfig:
    """Point-goal episodes (EnvConfig.task == "pointgoal"): where goals lie, how far they are, when one is
    reached, and how the observation shows it (docs/TASKS.md)."""

    near: float = 5.0
    """Shortest true path length (m) from an episode's spawn to its goal."""
    far: float = 30.0
    """Longest true path length (m) from an episode's spawn to its goal."""
    per_scene: int = 16
    """Goals drawn per scene, each with its path-length field."""
    cell: float = 0.5
    """Voxel edge (m) of the free-space lattice the path lengths are computed on."""
    max_voxels: int = 1 << 21
    """Largest lattice per scene: a bigger scene uses a coarser cell (1.5^k * cell)."""
    clearance: float = 0.5
    """A goal lies at least this far (m) from every surface."""
    radius: float = 0.5
    """The goal is reached within this path length (m) of it,"""
    stop_speed: float = 1.0
    """at no more than this speed (m/s): the drone has to arrive, not fly through."""
    seed: int = 0
    """Seed of the goal draw (per scene: seed + scene index)."""
    mark_degrees: float = 4.5
    """Half width (degrees) of the goal mark painted into the semantic channel around the goal's
    direction: about 3 azimuth bins either side and 1 elevation bin above and below at 256 x 48."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.near < self.far:
            raise ValueError(f"goal.near must be in [0, goal.far), got {self.near}, {self.far}")
        if self.per_scene < 1 or self.cell <= 0.0 or self.max_voxels < 8:
            raise ValueError("goal.per_scene must be >= 1, goal.cell positive and goal.max_voxels >= 8")
        if self.radius <= 0.0 or self.stop_speed <= 0.0 or self.clearance < 0.0:
            raise ValueError("goal.radius and goal.stop_speed must be positive, goal.clearance >= 0")
        if not 0.0 < self.mark_degrees <= 45.0:
            raise ValueError("goal.mark_degrees must be in (0, 45]")


@dataclass(frozen=True)
class EnvConfig:
    """The drone environment: kinematics, observation, episodes and rewards."""

    azimuth_bins: int = 256
    """Az: azimuth bins over 360 degrees; bin 0 is straight ahead."""
    elevation_bins: int = 48
    """El: elevation bins from the pattern's lowest to its highest elevation."""
    horizon: float = 100.0
    """Ray range (m); a miss reads as the horizon and depth is normalised by it."""
    trace_max_steps: int = 256
    """Sphere-tracing iteration cap per ray."""
    hit_epsilon: float = 0.01
    """Sphere-tracing hit threshold near the drone, meters."""
    hit_slope: float = 0.005
    """Growth of the hit threshold with distance: a ray stops within hit_epsilon + hit_slope * t of
    a surface t meters away and reports where the line through its last two samples meets it. 0.005 is
    a fifth of the default pattern's azimuth spacing (2 pi / 256): a ray passing that close to an edge
    reads as a hit, and shallow rays on floors and walls stop in fewer steps (docs/SDFDAG_RUNTIME.md)."""
    dt: float = 0.1
    """Seconds of simulated time per step."""
    max_speed: float = 5.0
    """Cap on the translational speed (m/s), applied to the norm of the velocity vector."""
    max_vertical_speed: float = 2.0
    """Vertical speed at action[1] = +-1, m/s."""
    max_lateral_speed: float = 3.0
    """Lateral speed at action[2] = +-1, m/s (positive: to the left)."""
    max_yaw_rate: float = 1.5
    """Yaw rate at action[3] = +-1, rad/s (positive: counter-clockwise seen from above)."""
    clearance_range: float = 10.0
    """The view clearance (the shortest depth of the view, read by the rewards and the speed limiter) is
    capped at this (m): farther away the ray spacing (1.4 x 3.75 degrees at 256x48) can miss features a
    voxel wide, so beyond it the clearance only says "open"."""
    drone_radius: float = 0.3
    """Contact when the clearance at the commanded position is below this, meters."""
    limiter_distance: float = 3.0
    """The proximity speed limiter starts slowing the drone below this clearance, meters."""
    limiter_min_fraction: float = 0.2
    """Speed fraction that the limiter always leaves, so a drone can fly away from a wall."""
    path_clearance_fraction: float = 0.5
    """Along a move the certified clearance may dip to this fraction of the radius (never to 0)."""
    collision_iterations: int = 8
    """Bisection steps that find the farthest safe point of a blocked move."""
    bounds_margin: float = 0.5
    """The drone is kept inside the scene's geometry bounds grown by this margin, meters."""
    max_steps_per_episode: int = 2000
    """Hard truncation: an episode ends after this many steps."""
    episodes_per_scene: int = 16
    """An actor flies this many episodes in a scene, then moves to another scene."""
    void_grace_steps: int = 10
    """Starvation truncation is suppressed for this many steps after a reset."""
    starvation_threshold: float = 0.9
    """A view is starving when at least this fraction of its rays miss (see the horizon)."""
    obs_buffers: int = 1
    """Observation buffers the env writes in turn: 1 (each step overwrites the last observation) or 2 (a
    step's observation stays intact through the next step, and the one before it is `previous_obs`: what
    Gymnasium-style adapters hand out without copying; one more (N, 3, Az, El) float32 buffer)."""
    sensor: SensorConfig = field(default_factory=SensorConfig)
    """Optional noise, dropout and ray pattern; off by default."""
    reward: RewardConfig = field(default_factory=RewardConfig)
    """Reward weights."""
    obstacles: ObstacleConfig = field(default_factory=ObstacleConfig)
    """Scripted moving obstacles; none by default."""
    task: str = "explore"
    """One of TASKS: explore (the default) or pointgoal (`goal` says how goals are drawn and reached)."""
    goal: GoalConfig = field(default_factory=GoalConfig)
    """Point-goal episodes; read only when task is pointgoal."""

    def __post_init__(self) -> None:
        if self.task not in TASKS:
            raise ValueError(f"task must be one of {', '.join(TASKS)}, got {self.task!r}")
        if self.task == "pointgoal" and max(self.obstacles.semantic_class, self.obstacles.drone_class) > 238:
            raise ValueError(
                "point-goal episodes keep semantic codes 240-255 for the goal mark: obstacle "
                "classes must be at most 238"
            )
        if self.azimuth_bins < 4 or self.elevation_bins < 2:
            raise ValueError("need at least 4 azimuth and 2 elevation bins")
        if self.horizon <= 0 or self.dt <= 0 or self.max_speed <= 0 or self.drone_radius <= 0:
            raise ValueError("horizon, dt, max_speed and drone_radius must be positive")
        if not (self.hit_epsilon > 0 and 0.0 <= self.hit_slope < 1.0):
            raise ValueError("hit_epsilon must be positive and hit_slope in [0, 1)")
        if not 0.0 <= self.limiter_min_fraction <= 1.0:
            raise ValueError("limiter_min_fraction must be in [0, 1]")
        if not 0.0 < self.path_clearance_fraction <= 1.0:
            raise ValueError("path_clearance_fraction must be in (0, 1]")
        if not self.limiter_distance < self.clearance_range <= self.horizon:
            raise ValueError("clearance_range must lie between limiter_distance and the horizon")
        if self.limiter_distance <= self.drone_radius:
            raise ValueError("limiter_distance must exceed drone_radius")
        if self.obs_buffers not in (1, 2):
            raise ValueError(f"obs_buffers must be 1 or 2, got {self.obs_buffers}")
        if self.max_steps_per_episode < 1 or self.episodes_per_scene < 1 or self.void_grace_steps < 0:
            raise ValueError("episode limits must be positive")
        if not 0.0 < self.starvation_threshold <= 1.0:
            raise ValueError("starvation_threshold must be in (0, 1]")
        if not 0.0 <= self.sensor.dropout < 1.0:
            raise ValueError("sensor dropout must be in [0, 1)")
        if self.reward.mid_range_max >= self.horizon or self.reward.near_distance >= self.horizon:
            raise ValueError("the near and mid-range bands must end before the horizon")
        if not 0.0 < self.reward.shaping_gamma <= 1.0:
            raise ValueError("shaping_gamma must be in (0, 1]")
        if not 4 <= self.reward.exploration_table_bits <= 24:
            raise ValueError("exploration_table_bits must be in [4, 24]")

    @property
    def rays(self) -> int:
        """R = Az * El rays per actor."""
        return self.azimuth_bins * self.elevation_bins
