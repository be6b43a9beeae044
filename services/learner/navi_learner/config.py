"""Typed configuration of the learner: the engine, PPO, and a training run.

Every field is documented: the commands' options for these settings are generated from the fields,
their defaults and their docstrings (navi/commands/options.py; a `CliOption` in a field's annotation
names its option or bounds it), and the whole `TrainConfig` is stored (as plain dicts) inside every
checkpoint. Importable without torch (`navi --help` reads it).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from typing import TYPE_CHECKING, Annotated, Any, Literal, get_args, get_origin, get_type_hints

if TYPE_CHECKING:
    import torch

TemporalCoreName = Literal["mamba2", "gru", "mambapy"]
TEMPORAL_CORES: tuple[TemporalCoreName, ...] = ("mamba2", "gru", "mambapy")
AttentionName = Literal["auto", "sdpa", "explicit", "fused"]
ATTENTIONS: tuple[AttentionName, ...] = ("auto", "sdpa", "explicit", "fused")


@dataclass(frozen=True)
class CliOption:
    """How the command option of a setting differs from the plain `--field-name`: another name, bounds."""

    flag: str | None = None
    """The option's name (e.g. --actors), where it is not the field's."""
    min: float | None = None
    """Smallest value the option accepts."""
    max: float | None = None
    """Largest value the option accepts."""


@dataclass
class EngineConfig:
    """Shape of the cognitive engine (CognitiveMambaPolicy)."""

    embed_dim: int = 128
    """D: width of the encoder tokens and of the embedding handed to the temporal core."""
    patch_size: int = 16
    """Patch side along azimuth in rays; Az must be divisible by it (16 × 16 → 16·3 = 48 tokens at 256×48)."""
    patch_el: int = 16
    """Patch side along elevation in rays (0: patch_size, a square patch); El must be divisible by it."""
    encoder_layers: int = 1
    """Number of pre-norm transformer blocks in the RayViT encoder. One block learns as well as two in
    `navi bench learn` (three seeds interleaved in one job) and trains about 27% faster at 8,192 actors
    (docs/PERFORMANCE.md, "Learner"); checkpoints store their own count."""
    encoder_heads: int = 4
    """Attention heads per encoder block."""
    attention: AttentionName = "auto"
    """Encoder attention: auto (fused on CUDA where the encoder's tokens and head width fit it, sdpa
    otherwise: on a CPU and for larger encoders), sdpa (F.scaled_dot_product_attention, which picks a
    library kernel), explicit (softmax(QKᵀ/√d)V written out, the softmax in float32, for torch.compile to
    fuse with its neighbours) or fused (one Triton program per sample and head holding all of its tokens;
    up to 128 tokens, heads 16, 32, 64 or 128 wide; the CPU runs its written-out twin). The same
    function; the weights and checkpoints do not depend on it."""
    mlp_ratio: int = 2
    """Hidden width of each encoder MLP as a multiple of D (2 keeps the encoder lean)."""
    temporal_core: TemporalCoreName = "mamba2"
    """Sequence engine: mamba2 (chunked SSD scan), gru (cuDNN), mambapy (plain sequential reference)."""
    ssm_state: int = 16
    """Mamba-2 state size per head (d_state)."""
    ssm_expand: int = 2
    """Mamba-2 inner width as a multiple of D."""
    ssm_head_dim: int = 64
    """Mamba-2 head width P; the inner width must be divisible by it."""
    ssm_conv: int = 4
    """Mamba-2 causal depthwise convolution width (kernel size along time)."""
    ssm_chunk: int = 32
    """Chunk length of the Mamba-2 SSD scan."""
    gru_hidden: int = 128
    """Hidden width of the GRU core (its output is projected back to D)."""
    head_hidden: int = 128
    """Hidden width of the policy and value MLP heads."""
    init_log_std: float = -0.5
    """Initial log standard deviation of the state-independent Gaussian policy."""
    rnd_dim: int = 64
    """Output width of the RND target and predictor networks."""
    memory_slots: int = 64
    """K: episodic-memory ring-buffer length per actor."""
    memory_threshold: float = 0.9
    """Cosine similarity above which a revisit is penalised (penalty ramps linearly from it to 1)."""
    action_input: bool = False
    """The temporal core also reads the action taken one step earlier (clipped to [-1, 1], zero where an
    episode starts), embedded and added to the encoder's embedding. A drone whose move was blocked sees the
    same view after commanding motion, which only its own action tells apart from hovering. Its weights
    start at zero, so a fresh engine acts as one without it until training moves them."""
    view_range: float = 0.0
    """The depth the encoder reads, as a fraction of the env's horizon (0.2: 20 m at the default 100 m):
    every ray beyond it, and every miss, reads as a surface of the unknown class at it (a goal mark
    kept), and delta depth is that of the capped frames; the env's rewards and statistics still see the
    true depth. 1: the whole horizon. 0: the task's (TASK_VIEW_RANGE), fixed when a run starts (`resolve`)
    and stored with its checkpoints; an engine built with 0 outside a run reads the whole horizon."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.view_range <= 1.0:
            raise ValueError(
                f"view_range must lie in [0, 1], a fraction of the horizon; got {self.view_range}"
            )

    @classmethod
    def tiny(cls, **overrides: Any) -> EngineConfig:
        """A small engine (embed 32, one encoder layer) for tests and CPU smoke runs on 16 x 8 views."""
        small: dict[str, Any] = dict(
            embed_dim=32,
            patch_size=4,
            patch_el=4,
            encoder_layers=1,
            encoder_heads=2,
            ssm_head_dim=16,
            ssm_chunk=16,
            memory_slots=8,
            head_hidden=32,
            rnd_dim=16,
        )
        return cls(**(small | overrides))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> EngineConfig:
        """The engine a checkpoint stored. One written before `patch_el` existed had square patches of
        `patch_size`, so a missing `patch_el` is 0 (square), not today's default; one written before
        `view_range` existed read the whole horizon (1)."""
        return cls(**({"patch_el": 0, "view_range": 1.0} | data))

    @property
    def patch(self) -> tuple[int, int]:
        """(azimuth, elevation) patch sides in rays."""
        return self.patch_size, self.patch_el or self.patch_size

    def patch_for(self, az: int, el: int) -> tuple[int, int]:
        """The patch sides on an Az × El view: a side longer than the view is capped at it (a view
        narrower than a patch is one patch along that axis). ValueError where a side does not divide."""
        pa, pe = min(self.patch[0], az), min(self.patch[1], el)
        if az % pa or el % pe:
            raise ValueError(f"observation {az}x{el} is not divisible by the {pa}x{pe} patch")
        return pa, pe


TASK_VIEW_RANGE: dict[str, float] = {"explore": 1.0, "pointgoal": 0.2}
"""EngineConfig.view_range per task where a run leaves it 0. Point-goal drones read 20 m: trained on
procedural scenes with the whole horizon, they stopped following the goal on open real maps whose sky
and far walls fill most of the view (docs/TRAINING.md, "Real maps never seen"). Explore keeps the whole
horizon: its transfer has not been measured with a shorter view."""


def engine_overrides(items: Sequence[str]) -> dict[str, Any]:
    """KEY=VALUE strings (a CLI's --engine) as EngineConfig fields of their declared type, e.g.
    ["patch_el=16", "encoder_heads=2"]; ValueError names an unknown field or a value of the wrong type.
    The temporal core has an option of its own (--temporal-core)."""
    hints = get_type_hints(EngineConfig)
    types = {f.name: hints[f.name] for f in fields(EngineConfig) if f.name != "temporal_core"}
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = (part.strip() for part in item.partition("="))
        if not sep:
            raise ValueError(f"--engine expects KEY=VALUE, got {item!r}")
        if key not in types:
            raise ValueError(f"unknown engine field {key!r}; known: {', '.join(sorted(types))}")
        if get_origin(types[key]) is Literal:  # a named choice, e.g. attention
            choices = get_args(types[key])
            if value not in choices:
                raise ValueError(f"--engine {key} expects one of {', '.join(choices)}, got {value!r}")
            out[key] = value
            continue
        if types[key] is bool:
            flags = {"1": True, "true": True, "on": True, "0": False, "false": False, "off": False}
            if value.lower() not in flags:
                raise ValueError(f"--engine {key} expects 1 or 0 (true or false), got {value!r}")
            out[key] = flags[value.lower()]
            continue
        cast = int if types[key] is int else float
        try:
            out[key] = cast(value)
        except ValueError:
            raise ValueError(f"--engine {key} expects {cast.__name__}, got {value!r}") from None
    return out


TASK_RATE = -1.0
"""PPOConfig.lr of the learning recipe: no rate of its own, resolve sets the task's (TASK_LR). A rate of 0
keeps its meaning, a run whose weights do not move."""


@dataclass
class PPOConfig:
    """PPO hyper-parameters and the weights of the intrinsic rewards."""

    lr: Annotated[float, CliOption(min=TASK_RATE)] = 5e-4
    """Adam learning rate (policy and RND predictor); the starting value when target_kl > 0. -1 (TASK_RATE):
    the learning recipe's rate for the run's task (TASK_LR: 6e-4 for explore and point-goal); 0 trains
    nothing."""
    target_kl: Annotated[float, CliOption(min=0.0)] = 0.0
    """> 0: adaptive learning rate. Before each minibatch's optimizer step the approximate KL divergence
    from the rollout's policy is compared with this target: above 2× it the rate is divided by 1.5,
    below half of it multiplied by 1.5, within [lr_min, lr_max]. The rate stays on the device (no host
    read) and is the same on every rank of a data-parallel run. 0: the rate stays `lr`."""
    lr_min: float = 1e-5
    """Lower bound of the adaptive learning rate."""
    lr_max: float = 1e-3
    """Upper bound of the adaptive learning rate."""
    gamma: float = 0.99
    """Discount factor."""
    gae_lambda: float = 0.95
    """GAE λ."""
    ppo_epochs: Annotated[int, CliOption(min=1)] = 1
    """Passes over each rollout."""
    num_minibatches: int = 4
    """Minibatches per epoch; each holds whole BPTT sequences of a subset of (chunk, actor) pairs."""
    max_minibatch: Annotated[int, CliOption(min=1)] = 8_192
    """Upper bound on samples (steps) per PPO minibatch; large rollouts get more minibatches. The update's
    activation memory grows with it (lower it where the GPU runs out of memory)."""
    bptt_chunk: int = 32
    """Truncated-BPTT sequence length; the recurrent state is stored at every chunk start."""
    clip_coef: float = 0.2
    """Policy ratio clip ε."""
    value_clip_coef: float = 0.2
    """Value clip around the rollout value estimate (≤ 0 disables value clipping)."""
    ent_coef: float = 0.003
    """Entropy bonus weight."""
    vf_coef: float = 0.5
    """Value loss weight."""
    mean_bound_coef: Annotated[float, CliOption(min=0.0)] = 0.0
    """Weight of the penalty on action means outside [-1, 1], where the env clips every action:
    `coef · Σ_a relu(|μ_a| − 1)²`, averaged over the minibatch's samples (ppo.loss.mean_bound_loss). A mean
    beyond the bound flies as the bound does, so nothing holds it there and it drifts out; a drone whose
    mean sits far out then samples the bound almost every step, and one that pushes into a wall stays
    pinned. 0: no penalty."""
    rnd_coef: float = 1.0
    """Weight of the RND predictor loss in the total loss."""
    max_grad_norm: float = 0.5
    """Global gradient-norm clip."""
    norm_adv: bool = True
    """Normalise advantages per minibatch."""
    intrinsic_rnd_weight: float = 0.01
    """Weight of the normalised RND novelty added to the extrinsic reward."""
    intrinsic_episodic_weight: float = 0.01
    """Weight of the episodic-memory loop penalty subtracted from the extrinsic reward."""
    reward_ema_decay: float = 0.9
    """Decay of reward_ema (EMA of the mean extrinsic reward per actor-step, one update per rollout)."""


@dataclass
class TrainConfig:
    """A training run: environment size, budget, checkpoints, device and the two configs above."""

    n_actors: Annotated[int, CliOption("--actors", min=0)] = 0
    """N parallel actors; 0 picks the device default (4 on CPU, 4096 on CUDA)."""
    rollout_length: Annotated[int, CliOption(min=0)] = 0
    """T steps per actor per update; 0 picks ROLLOUT_DEFAULT for the device, capped so the rollout fits
    `rollout_memory_gb`."""
    total_steps: Annotated[int, CliOption(min=1)] = 1_000_000
    """Budget in env steps (actor-steps); the run ends with a final checkpoint."""
    time_limit_s: Annotated[float, CliOption(min=0.0)] = 0.0
    """Budget in seconds of training (a monitor's evaluations excluded); 0: no limit."""
    checkpoint_every: Annotated[int, CliOption(min=1)] = 25_000
    """Env steps between periodic checkpoints."""
    keep_checkpoints: int = 5
    """Newest K checkpoints kept in the run folder."""
    log_every: int = 1
    """Updates between log lines (metrics JSONL, TensorBoard, on_log callback)."""
    seed: int = 0
    """Seed for torch and the environment."""
    device: str = "cpu"
    """Torch device: cpu, cuda or cuda:N (a command's auto picks cuda where available, else cpu)."""
    amp: bool = True
    """bf16 autocast for the encoder on CUDA (ignored on CPU)."""
    compile: bool = True
    """torch.compile the encoder (CUDA only; the first steps wait for the compile, the later ones run
    fused kernels)."""
    compile_rollout: bool = True
    """With `compile`, on CUDA: also compile the rollout's whole policy step (encoder, temporal-core step,
    heads, action sample, RND novelty, episodic memory) as one graph, so the launch-bound forward of
    small actor counts runs fewer, fused kernels. The same step as the eager one (a CPU parity test);
    False: the encoder alone is compiled."""
    compile_update: bool = True
    """With `compile`, on CUDA: compile each PPO minibatch's objective (the policy's sequence pass with
    the temporal core's chunked scan, the PPO and RND losses) and its backward as one graph, fewer and
    fused kernels; False: the encoder alone is compiled. The same objective as the eager one (a CPU
    parity test)."""
    update_graphs: bool = True
    """With `compile_update`, on CUDA, where the objective is one graph (mamba2; the gru's splits it):
    replay the compiled minibatch objective and its backward as CUDA graphs (torch.compile's
    reduce-overhead mode), so the host launches a few graphs per minibatch instead of about 300 kernels
    and the update stops waiting for a slow or busy host's launches. The same kernels and results (a CUDA
    parity test); the graphs keep a memory pool of their own. False: the compiled kernels launched one by
    one."""
    tf32: bool = False
    """On CUDA: let float32 matrix products (the temporal core's, the heads' and RND's; the encoder runs
    in bf16 under `amp`) use TF32 tensor cores (torch.backends.cuda.matmul.allow_tf32, for the whole
    process from the run's start)."""
    obs_dtype: Annotated[str, CliOption("--obs-storage")] = "auto"
    """Rollout observation storage: compact (float16 depth and a semantic byte per ray, 3 bytes; needs
    DistanceMatrix v2 observations, the drone env's), float32 (12 bytes per ray, any env), or auto
    (compact when the env says its observations are DistanceMatrix v2, float32 otherwise). Either way
    the update sees bit for bit the observations the policy acted on."""
    rollout_memory_gb: float = 20.0
    """Memory budget for stored observations when rollout_length is 0 (64 steps at 8,192 actors compact)."""
    rank_scenes: str = "all"
    """Data-parallel ranks' scenes: all (every rank flies every scene from its own spawns, so every
    rank's step costs what one process's does) or share (each rank flies its own share, dealt by the
    trace cost measured at qualification); one process flies them all. The same default as
    navi_env.corpus.folder.DEFAULT_RANK_SCENES."""
    task: str = "explore"
    """What the env's episodes ask (EnvConfig.task): explore or pointgoal; stored so that evaluations of a
    checkpoint fly the task it learned."""
    init_from: str = ""
    """Weights a fresh run starts from: a checkpoint's path, or explore / pointgoal for that task's shipped
    reference (navi_learner.serving.references). It brings the policy's weights and the novelty normaliser's
    statistics (its engine must be the run's: `navi train` and `navi bench transfer` take the engine the
    checkpoint stored, with their --engine fields on top, ppo.learner.init_engine); the optimizer, the
    counters and the reward average start fresh. Empty: random weights. A resumed run takes everything
    from its checkpoint instead."""
    sync_timers: bool = False
    """Exact per-stage times on CUDA (benchmarks): CUDA events bracket every stage and are read once per
    log line, with no host wait inside the loop (StageTimers)."""
    engine: EngineConfig = field(default_factory=EngineConfig)
    """The cognitive engine."""
    ppo: PPOConfig = field(default_factory=PPOConfig)
    """PPO and intrinsic-reward settings."""

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (str, int, float, bool only) for checkpoints and manifests."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrainConfig:
        """Inverse of to_dict; unknown keys are rejected by the dataclass constructors."""
        flat = {k: v for k, v in data.items() if k not in ("engine", "ppo")}
        if flat.get("obs_dtype") == "bfloat16":  # written before compact storage: bf16 is gone
            flat["obs_dtype"] = "auto"
        return cls(
            **flat,
            engine=EngineConfig.from_dict(data.get("engine", {})),
            ppo=PPOConfig(**data.get("ppo", {})),
        )


ROLLOUT_DEFAULT = {"cuda": 512, "cpu": 64}
"""Rollout length when TrainConfig.rollout_length is 0: the original system's 512 on a GPU; 64 on a CPU,
where 4 actors x 512 steps would make the first update (and a dashboard's first chart point) wait minutes."""


def default_actors(device: torch.device) -> int:
    """Actor count that fits the device: 4 on CPU, 4096 on a GPU."""
    return 4096 if device.type == "cuda" else 4


TASK_LR: dict[str, float] = {"explore": 6e-4, "pointgoal": 6e-4}
"""The learning recipe's Adam rate per task, where a run's PPOConfig.lr is TASK_RATE. Both at 6e-4, each
chosen by an A/B of its own against 3e-4, seeds 0-2 interleaved in one job (8,192 actors, 120 s, one H200;
docs/TRAINING.md, "Levers"). Explore held the bar after 60 / 41 / 41 s against 102 / 63 / 120 s, with
fewer late collisions on every seed and about 5% less coverage. Point-goal was ahead on every seed after 62 s
of training (success 0.87 / 0.59 / 0.74 against 0.72 / 0.54 / 0.57), level or ahead at 93 s, and reached the
bar on 2 of 3 seeds (93 / - / 121 s) against 1 of 3 (93 / - / -), with fewer collisions per episode on every
seed at the end."""


def task_lr(task: str) -> float:
    """TASK_LR of a task; ValueError names the known ones."""
    if task not in TASK_LR:
        raise ValueError(f"unknown task {task!r}: expected one of {', '.join(TASK_LR)}")
    return TASK_LR[task]


def learning_recipe(cfg: TrainConfig | None = None) -> TrainConfig:
    """The settings of the measured learning run (`navi bench learn`, and `navi run` on CUDA) on top of
    `cfg` (TrainConfig() when None): two PPO epochs per rollout at the task's learning rate (TASK_RATE,
    which resolve turns into TASK_LR's) over minibatches of up to 16,384 samples, and a step budget so
    large that the run's time limit ends it."""
    base = TrainConfig() if cfg is None else cfg
    ppo = replace(base.ppo, lr=TASK_RATE, ppo_epochs=2, max_minibatch=16_384)
    return replace(base, total_steps=10**12, ppo=ppo)


LEARNING_ACTORS = 8192
"""The learning run's actors on a GPU: in one job of seeds 0-2 interleaved with 2,048 (explore, 120 s, one
H200) they reached the bar no later (median 100 against 101 s, 3 of 3 seeds against 2 of 3) and flew a
third of the late collisions (docs/PERFORMANCE.md). The run peaked at about 28 GiB of GPU memory."""

SMALL_GPU_ACTORS = 2048
"""The learning run's actors on a GPU with less than SMALL_GPU_GIB of memory."""

SMALL_GPU_GIB = 36.0
"""Total GPU memory (GiB) below which LEARNING_ACTORS would not fit beside the CUDA context and caches."""


def gpu_memory_gib(device: torch.device) -> float | None:
    """Total memory of the CUDA `device` in GiB; None on a CPU or where CUDA is absent."""
    import torch

    if device.type != "cuda" or not torch.cuda.is_available():
        return None
    return torch.cuda.get_device_properties(device).total_memory / 2**30


def learning_size(cfg: TrainConfig, device: torch.device) -> TrainConfig:
    """The learning run's actors and rollout length where `cfg` leaves them 0: LEARNING_ACTORS (8,192;
    SMALL_GPU_ACTORS, 2,048, on a GPU under SMALL_GPU_GIB) and 64-step rollouts on CUDA, 8 actors and
    32-step rollouts on a CPU. A GPU whose memory cannot be read (no CUDA here) counts as large."""
    if device.type == "cuda":
        gib = gpu_memory_gib(device)
        actors = SMALL_GPU_ACTORS if gib is not None and gib < SMALL_GPU_GIB else LEARNING_ACTORS
        rollout = 64
    else:
        actors, rollout = 8, 32
    return replace(cfg, n_actors=cfg.n_actors or actors, rollout_length=cfg.rollout_length or rollout)


OBS_STORAGE = ("auto", "compact", "float32")
"""Values of TrainConfig.obs_dtype."""


class StorageError(ValueError):
    """An observation storage the run cannot use."""


def compact_storage(cfg: TrainConfig, env_compact: bool) -> bool:
    """Whether this run stores observations compact, for an env whose observations are DistanceMatrix
    v2 (`env_compact`) or not."""
    if cfg.obs_dtype not in OBS_STORAGE:
        raise StorageError(f"obs_dtype must be one of {', '.join(OBS_STORAGE)}, got {cfg.obs_dtype!r}")
    if cfg.obs_dtype == "compact" and not env_compact:
        raise StorageError(
            "compact observation storage needs DistanceMatrix v2 observations (the drone env's)"
        )
    return env_compact and cfg.obs_dtype != "float32"


def obs_bytes(obs_shape: tuple[int, int, int], compact: bool) -> int:
    """Bytes one stored observation takes: 3 per ray compact, 4 per value as float32."""
    c, az, el = obs_shape
    return 3 * az * el if compact else 4 * c * az * el


def resolve(cfg: TrainConfig, obs_shape: tuple[int, int, int], compact: bool = True) -> TrainConfig:
    """Fill the derived defaults (actor count, rollout length, the engine's view range and the learning
    rate for the task) once, right after parsing.

    The rollout length defaults to ROLLOUT_DEFAULT for the device but is capped, to a multiple of the
    BPTT chunk, so that N·T stored observations (`compact` or float32, see obs_bytes) fit in
    `rollout_memory_gb`: at 256×48 and 8,192 actors compact that is 64 steps. The minibatch count
    grows so no minibatch exceeds max_minibatch.
    """
    import torch

    device = torch.device(cfg.device)
    n_actors = cfg.n_actors or default_actors(device)
    rollout = cfg.rollout_length
    if rollout == 0:
        fit = int(cfg.rollout_memory_gb * 2**30 // (n_actors * obs_bytes(obs_shape, compact)))
        rollout = max(8, min(ROLLOUT_DEFAULT.get(device.type, 64), fit // 8 * 8))
    bptt = min(cfg.ppo.bptt_chunk, rollout)
    rollout = max(bptt, rollout // bptt * bptt)
    minibatches = max(cfg.ppo.num_minibatches, -(-n_actors * rollout // cfg.ppo.max_minibatch))
    if cfg.ppo.lr < 0 and cfg.ppo.lr != TASK_RATE:
        raise ValueError(f"lr must be >= 0, or {TASK_RATE:g} for the task's rate; got {cfg.ppo.lr:g}")
    lr = task_lr(cfg.task) if cfg.ppo.lr == TASK_RATE else cfg.ppo.lr
    ppo = replace(cfg.ppo, bptt_chunk=bptt, num_minibatches=minibatches, lr=lr)
    engine = replace(cfg.engine, view_range=cfg.engine.view_range or TASK_VIEW_RANGE.get(cfg.task, 1.0))
    return replace(cfg, n_actors=n_actors, rollout_length=rollout, ppo=ppo, engine=engine)


@dataclass(frozen=True, kw_only=True)
class RunBudget:
    """How long `navi run` trains: seconds on CUDA, env steps on a CPU (its MainJobConfig extends this)."""

    budget_s: Annotated[float, CliOption(min=1.0)] = 600.0
    """CUDA: training seconds at most (evaluations excluded; stops earlier at competence)."""
    eval_every_s: Annotated[float, CliOption(min=1.0)] = 30.0
    """CUDA: training seconds between two unseen evaluations."""
    cpu_steps: Annotated[int, CliOption(min=0)] = 2048
    """CPU: env steps of fine-tuning the task's reference checkpoint."""
    n_actors: Annotated[int, CliOption("--actors", min=0)] = 0
    """CUDA: drones trained at once (0: the learning benchmark's 8,192; 2,048 on a GPU under 36 GiB)."""
