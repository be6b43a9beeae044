"""Compact rollout storage: the update sees bit for bit the observations the policy acted on.

The drone env's observations are stored as float16 depth and a semantic byte per ray (3 bytes instead
of 12); each minibatch rebuilds the three channels (delta depth from consecutive frames and the reset
flags). Two rollouts are collected with short episodes (resets inside a rollout and across the
rollout boundary) and the sensor's noise and dropout on, and every minibatch sequence is compared with
what `act` was given, on the CPU (eager kernels) and on CUDA (the env's compiled observation pass in
its CUDA graph, compiled pack and unpack).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import pytest
import torch

from navi_env.config import EnvConfig, SensorConfig
from navi_env.sim.env import SdfDagEnv
from navi_env.tracer.analytic_scenes import demo_room, free_points
from navi_env.tracer.scene import load_corpus
from navi_learner.config import (
    EngineConfig,
    PPOConfig,
    TemporalCoreName,
    TrainConfig,
    compact_storage,
    obs_bytes,
    resolve,
)
from navi_learner.engine.memory import EpisodicMemory
from navi_learner.engine.moments import moment_sums
from navi_learner.engine.policy import ActOut, CognitiveMambaPolicy
from navi_learner.engine.temporal import CoreState
from navi_learner.ppo.compile import PooledForward, compile_graph, make_forward, pooled_step, rollout_forward
from navi_learner.ppo.dist import Dist, Sync
from navi_learner.ppo.rollout import RolloutStorage
from navi_learner.ppo.stats import EpisodeStats
from navi_learner.ppo.timing import StageTimers
from navi_learner.ppo.train import collect

ACTORS, T_LEN, CHUNK = 6, 8, 4
DEVICES = [
    "cpu",
    pytest.param(
        "cuda",
        marks=[
            pytest.mark.gpu,
            pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
        ],
    ),
]


def small_env(device: str) -> SdfDagEnv:
    """A 16 m room at 32³, 32×8 rays, 5-step episodes, sensor noise and dropout on."""
    scene = demo_room(32, 16.0)
    spawns = free_points(scene, 8, clearance=1.5, seed=3)
    corpus = load_corpus([scene.gmdag(spawns=spawns)], device)
    sensor = SensorConfig(range_noise_std=0.05, dropout=0.02)
    cfg = replace(EnvConfig(), azimuth_bins=32, elevation_bins=8, max_steps_per_episode=5, sensor=sensor)
    return SdfDagEnv(corpus, ACTORS, device, cfg, seed=5)


Parts = tuple[
    RolloutStorage, EpisodicMemory, EpisodeStats, StageTimers, tuple[torch.Tensor, torch.Tensor, CoreState]
]


def rollout_parts(
    env: SdfDagEnv, policy: CognitiveMambaPolicy, engine: EngineConfig, dev: torch.device
) -> Parts:
    """Compact storage, episodic memory, statistics, timers and the first carry of a collection."""
    buf = RolloutStorage(
        T_LEN, ACTORS, env.obs_shape, policy.initial_state(ACTORS, dev), CHUNK, dev, compact=True
    )
    memory = EpisodicMemory(ACTORS, engine.memory_slots, engine.embed_dim, engine.memory_threshold, dev)
    starts = torch.ones(ACTORS, dtype=torch.bool, device=dev)  # (N,)
    carry = (env.reset(seed=1), starts, policy.initial_state(ACTORS, dev))
    return buf, memory, EpisodeStats(ACTORS, dev), StageTimers(False), carry


@pytest.mark.parametrize("device", DEVICES)
def test_minibatches_rebuild_exactly_what_the_policy_saw(device: str) -> None:
    torch.manual_seed(0)
    dev = torch.device(device)
    env = small_env(device)
    engine = EngineConfig.tiny()
    cfg = TrainConfig(n_actors=ACTORS, rollout_length=T_LEN, engine=engine, ppo=PPOConfig(bptt_chunk=CHUNK))
    policy = CognitiveMambaPolicy(env.obs_shape, engine).to(dev)
    seen: list[torch.Tensor] = []
    act = policy.act

    def recording_act(
        obs: torch.Tensor, resets: torch.Tensor, state: CoreState, deterministic: bool = False
    ) -> ActOut:
        seen.append(obs.clone())  # (N, 3, Az, El) float32, exactly as the policy got it
        return act(obs, resets, state, deterministic)

    policy.act = recording_act  # type: ignore[method-assign]
    assert compact_storage(cfg, env.compact_obs)
    buf, memory, stats, timers, carry = rollout_parts(env, policy, engine, dev)
    assert buf.depth16.dtype == torch.float16 and buf.semantic.dtype == torch.uint8
    gen = torch.Generator().manual_seed(0)
    for rollout in range(2):
        seen.clear()
        carry, _ = collect(policy, env, buf, memory, stats, cfg, carry, timers, check_storage=rollout == 0)
        frames = torch.stack(seen)  # (T, N, 3, Az, El)
        assert bool(buf.resets[1:].any()) and bool((~buf.resets).any())  # episodes end inside the rollout
        assert bool((frames[:, :, 2] != 0).any())  # the drones moved: delta depth is not all zero
        for t in range(T_LEN):
            assert torch.equal(buf.obs_at(t), frames[t]), (rollout, t)
        covered = 0
        for mb in buf.minibatches(3, gen):
            for i, (c, a) in enumerate(zip(mb.chunks.tolist(), mb.actors.tolist(), strict=True)):
                want = frames[c * CHUNK : (c + 1) * CHUNK, a]  # (L, 3, Az, El)
                assert torch.equal(mb.obs[:, i], want), (rollout, c, a)
                covered += 1
        assert covered == ACTORS * T_LEN // CHUNK
    # the second rollout's first frame follows the first rollout's last one, unless an episode began
    assert not bool(buf.resets[0].all())


def test_a_non_distance_matrix_env_cannot_store_compact() -> None:
    cfg = TrainConfig(obs_dtype="compact")
    with pytest.raises(ValueError, match="DistanceMatrix v2"):
        compact_storage(cfg, False)
    assert not compact_storage(TrainConfig(), False) and compact_storage(TrainConfig(), True)
    assert not compact_storage(TrainConfig(obs_dtype="float32"), True)
    with pytest.raises(ValueError, match="obs_dtype"):
        compact_storage(TrainConfig(obs_dtype="bfloat16"), True)
    # a checkpoint written before compact storage (bf16) resumes with the default storage
    assert TrainConfig.from_dict({**TrainConfig().to_dict(), "obs_dtype": "bfloat16"}).obs_dtype == "auto"


def test_default_rollout_is_64_steps_at_8192_actors_in_20_gb() -> None:
    shape = (3, 256, 48)
    assert obs_bytes(shape, True) == 3 * 256 * 48 and obs_bytes(shape, False) == 12 * 256 * 48
    cfg = resolve(TrainConfig(n_actors=8192, device="cpu"), shape, compact=True)
    assert cfg.rollout_length == 64
    assert 8192 * 65 * obs_bytes(shape, True) <= cfg.rollout_memory_gb * 2**30  # T + 1 depth frames
    assert resolve(TrainConfig(n_actors=8192, device="cpu"), shape, compact=False).rollout_length == 16


@pytest.mark.parametrize(("core", "action_input"), [("mamba2", False), ("gru", False), ("mamba2", True)])
def test_the_compiled_rollout_step_collects_what_the_eager_one_does(
    core: TemporalCoreName, action_input: bool
) -> None:
    """`--compile-rollout` traces the rollout's policy step whole (act, RND, memory; fullgraph), with
    either temporal core and with the previous action as an input: traced here with the aot_eager backend
    (the CPU runs the same graph without code generation), two rollouts fill the storage, the RND
    normaliser and the episodic memory bit for bit as the eager step does, same seeds."""
    engine = replace(EngineConfig.tiny(), temporal_core=core, action_input=action_input)
    cfg = TrainConfig(n_actors=ACTORS, rollout_length=T_LEN, engine=engine, ppo=PPOConfig(bptt_chunk=CHUNK))
    cpu = torch.device("cpu")
    filled = []
    for compiled in (False, True):
        torch.manual_seed(0)
        env = small_env("cpu")
        policy = CognitiveMambaPolicy(env.obs_shape, engine).eval()
        if policy.action_embed is not None:
            torch.nn.init.normal_(policy.action_embed.weight)  # the input matters, as after training
        buf = RolloutStorage(
            T_LEN, ACTORS, env.obs_shape, policy.initial_state(ACTORS, cpu), CHUNK, cpu, True
        )
        memory = EpisodicMemory(ACTORS, engine.memory_slots, engine.embed_dim, engine.memory_threshold, cpu)
        forward = rollout_forward(policy, memory)
        if compiled:
            forward = compile_graph(forward, backend="aot_eager")
        stats, timers = EpisodeStats(ACTORS, cpu), StageTimers(False)
        starts = torch.ones(ACTORS, dtype=torch.bool)  # (N,)
        carry = (env.reset(seed=1), starts, policy.initial_state(ACTORS, cpu))
        rows = []
        for _ in range(2):
            carry, _ = collect(policy, env, buf, memory, stats, cfg, carry, timers, forward=forward)
            rows += [buf.actions.clone(), buf.logp.clone(), buf.values.clone(), buf.rewards.clone()]
        rows += [
            policy.rnd.err_mean.clone(),
            policy.rnd.err_var.clone(),
            memory.keys.clone(),
            memory.ptr.clone(),
        ]
        filled.append(rows)
    eager, traced = filled
    assert bool(eager[-1].any())  # the memory was written
    for a, b in zip(eager, traced, strict=True):
        assert torch.equal(a, b)


def compiled_fn(fn: object) -> bool:
    """Whether `fn` is a torch.compile wrapper (it keeps the function it compiles)."""
    return hasattr(fn, "_torchdynamo_orig_callable")


def test_the_rollout_step_is_compiled_by_default_on_cuda_only() -> None:
    """On CUDA the default compiles the whole step; the CPU, --no-compile and --no-compile-rollout keep
    it eager. Nothing is compiled here: torch.compile only wraps until the first call."""
    engine = EngineConfig.tiny()
    policy = CognitiveMambaPolicy((3, 32, 8), engine)
    memory = EpisodicMemory(
        2, engine.memory_slots, engine.embed_dim, engine.memory_threshold, torch.device("cpu")
    )
    eager = rollout_forward(policy, memory)
    for cfg, device in [
        (TrainConfig(), "cpu"),
        (TrainConfig(compile_rollout=False), "cuda"),
        (TrainConfig(compile=False), "cuda"),
    ]:
        forward = make_forward(policy, memory, cfg, torch.device(device))
        assert forward.__qualname__ == eager.__qualname__ and not compiled_fn(forward)
    assert compiled_fn(make_forward(policy, memory, TrainConfig(), torch.device("cuda")))
    # a data-parallel rank: the same rule for the step inside its PooledForward (no collective is made)
    sync = Sync(
        Dist(rank=0, world=2), [q for q in policy.parameters() if q.requires_grad], torch.device("cpu")
    )
    try:
        for cfg, device, compiled in [
            (TrainConfig(), "cpu", False),
            (TrainConfig(compile_rollout=False), "cuda", False),
            (TrainConfig(), "cuda", True),
        ]:
            forward = make_forward(policy, memory, cfg, torch.device(device), sync)
            assert isinstance(forward, PooledForward) and compiled_fn(forward.step) == compiled
    finally:
        sync.release()


def one_rank_chain(
    step: Callable[..., tuple[ActOut, torch.Tensor, torch.Tensor, torch.Tensor]],
    policy: CognitiveMambaPolicy,
    obs: torch.Tensor,
    resets: torch.Tensor,
    state: CoreState,
    steps: int,
) -> list[dict[str, torch.Tensor]]:
    """`steps` calls of a rank's pooled step, each handed the sums the one before returned (one rank's
    pooling, one step late); the first is handed its own batch's sums. Returns each call's outputs and
    the normaliser after it."""
    with torch.no_grad():
        pooled = moment_sums(policy.rnd.error(policy.act(obs, resets, state).emb))  # (3,) float64
        rows = []
        for _ in range(steps):
            out, novelty, loop, pooled = step(obs, resets, state, pooled)  # ActOut, (N,), (N,), (3,)
            rows.append(
                {
                    "value": out.value,
                    "emb": out.emb,
                    "novelty": novelty,
                    "loop": loop,
                    "sums": pooled,
                    "err_mean": policy.rnd.err_mean.clone(),
                    "err_var": policy.rnd.err_var.clone(),
                }
            )
            state, resets = out.state, torch.zeros_like(resets)
    return rows


def test_the_rnd_step_given_pooled_sums_is_the_step_whose_reduce_returns_them() -> None:
    """RND.intrinsic_pooled (a rank's compiled step) folds in the sums it is handed exactly as intrinsic
    folds in what its `reduce` returns, and hands back this batch's own sums."""
    torch.manual_seed(0)
    engine = EngineConfig.tiny()
    rnds = [CognitiveMambaPolicy((3, 16, 8), engine).rnd for _ in "ab"]
    rnds[1].load_state_dict(rnds[0].state_dict())
    for k in range(3):
        emb = torch.randn(10, engine.embed_dim) * (k + 1)  # (N, D)
        pooled = moment_sums(torch.rand(7) * (k + 2))  # (3,) float64: another batch's sums
        got, sums = rnds[0].intrinsic_pooled(emb, pooled)  # (N,), (3,)
        want = rnds[1].intrinsic(emb, lambda t, p=pooled: p)  # (N,)
        assert torch.equal(got, want)
        assert torch.equal(sums, moment_sums(rnds[1].error(emb)))
        for (name, a), b in zip(rnds[0].named_buffers(), rnds[1].buffers(), strict=True):
            assert torch.equal(a, b), name


def test_a_ranks_rollout_step_is_one_graph_around_its_pooled_sums() -> None:
    """A data-parallel rank's step without its collective compiles whole (fullgraph; AOTAutograd on the
    CPU) and gives the eager step's outputs, sums and normaliser bit for bit over 3 chained steps."""
    engine = EngineConfig.tiny()
    cpu = torch.device("cpu")
    obs = torch.rand(ACTORS, 3, 32, 8, generator=torch.Generator().manual_seed(1))  # (N, 3, Az, El)
    resets = torch.ones(ACTORS, dtype=torch.bool)  # (N,)
    chains = []
    for compiled in (False, True):
        torch.manual_seed(0)
        policy = CognitiveMambaPolicy((3, 32, 8), engine).eval()
        memory = EpisodicMemory(ACTORS, engine.memory_slots, engine.embed_dim, engine.memory_threshold, cpu)
        step = pooled_step(policy, memory)
        if compiled:
            step = compile_graph(step, backend="aot_eager")
        chains.append(one_rank_chain(step, policy, obs, resets, policy.initial_state(ACTORS, cpu), 3))
    for eager, traced in zip(*chains, strict=True):
        for name, value in eager.items():
            assert torch.equal(value, traced[name]), name


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("action_input", [False, True])
def test_the_inductor_compiled_rollout_step_matches_the_eager_one_on_cuda(action_input: bool) -> None:
    """On CUDA, with bf16 autocast, the compiled step's deterministic outputs and state match eager, also
    with the previous action as an input."""
    torch.manual_seed(0)
    dev = torch.device("cuda")
    engine = EngineConfig(action_input=action_input)
    policy = CognitiveMambaPolicy((3, 256, 48), engine).to(dev).eval()
    if policy.action_embed is not None:
        torch.nn.init.normal_(policy.action_embed.weight, std=0.1)  # the input matters, as after training
    policy.amp = True
    n = 256
    memories = [
        EpisodicMemory(n, engine.memory_slots, engine.embed_dim, engine.memory_threshold, dev) for _ in "ab"
    ]
    cfg = TrainConfig(n_actors=n, compile=True, compile_rollout=True)
    compiled = make_forward(policy, memories[0], cfg, dev)
    eager = rollout_forward(policy, memories[1])
    obs = torch.rand(n, 3, 256, 48, device=dev)  # (N, 3, Az, El)
    resets = torch.rand(n, device=dev) < 0.2  # (N,) bool
    state = tuple(s.normal_() * 0.1 for s in policy.initial_state(n, dev))
    with torch.no_grad():
        rnd = {k: v.clone() for k, v in policy.rnd.state_dict().items()}
        got, _, got_loop = compiled(obs, resets, state)
        policy.rnd.load_state_dict(rnd)
        want, _, want_loop = eager(obs, resets, state)
    assert compiled_fn(compiled) and not compiled_fn(eager)
    torch.testing.assert_close(got.value, want.value, atol=2e-2, rtol=2e-2)
    torch.testing.assert_close(got.emb, want.emb, atol=2e-2, rtol=2e-2)
    torch.testing.assert_close(got_loop, want_loop, atol=2e-2, rtol=2e-2)
    core = len(want.state) - int(action_input)  # the core's state; then the sampled action, if read
    for g, w in zip(got.state[:core], want.state[:core], strict=True):
        torch.testing.assert_close(g, w, atol=2e-2, rtol=2e-2)
    for out in (got, want)[: int(action_input) * 2]:  # each carries the action it drew (its own RNG)
        assert torch.equal(out.state[-1], out.action.clamp(-1.0, 1.0))


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_the_inductor_compiled_step_of_a_rank_matches_the_eager_one_on_cuda() -> None:
    """On CUDA, with bf16 autocast, a data-parallel rank's step compiled to one graph gives the eager
    step's values and embeddings, the sums it hands the ranks and the normaliser they make, over 3
    chained steps, and the first step's loop penalty. The novelty (a z-score over near-identical errors)
    and the later loop penalties (threshold tests on memories written in bf16) magnify bf16 rounding;
    the CPU test above holds them to the eager step's bit for bit."""
    dev = torch.device("cuda")
    engine = EngineConfig()
    n = 256
    obs = torch.rand(
        n, 3, 256, 48, device=dev, generator=torch.Generator(dev).manual_seed(1)
    )  # (N, 3, Az, El)
    resets = torch.ones(n, dtype=torch.bool, device=dev)  # (N,)
    chains = []
    for compiled in (False, True):
        torch.manual_seed(0)
        policy = CognitiveMambaPolicy((3, 256, 48), engine).to(dev).eval()
        policy.amp = True
        memory = EpisodicMemory(n, engine.memory_slots, engine.embed_dim, engine.memory_threshold, dev)
        step = pooled_step(policy, memory)
        if compiled:
            step = compile_graph(step)
        chains.append(one_rank_chain(step, policy, obs, resets, policy.initial_state(n, dev), 3))
    for k, (eager, traced) in enumerate(zip(*chains, strict=True)):
        names = ["value", "emb", "sums", "err_mean", "err_var"] + ["loop"] * (k == 0)
        for name in names:
            torch.testing.assert_close(traced[name], eager[name], atol=2e-2, rtol=2e-2, msg=name)


@pytest.mark.parametrize("device", DEVICES)
def test_an_engine_reading_its_previous_action_gets_it_back_from_the_stored_rollout(device: str) -> None:
    """With EngineConfig.action_input the state carries the previous action: every minibatch's PPO pass
    (from each chunk's stored state, over the stored actions) gives back the log-probabilities and values
    the rollout recorded, across episode starts inside the rollout and across the rollout boundary."""
    torch.manual_seed(0)
    dev = torch.device(device)
    env = small_env(device)
    engine = EngineConfig.tiny(action_input=True)
    cfg = TrainConfig(n_actors=ACTORS, rollout_length=T_LEN, engine=engine, ppo=PPOConfig(bptt_chunk=CHUNK))
    policy = CognitiveMambaPolicy(env.obs_shape, engine).to(dev)
    assert policy.action_embed is not None
    torch.nn.init.normal_(policy.action_embed.weight)  # as training would leave it: the input matters
    buf, memory, stats, timers, carry = rollout_parts(env, policy, engine, dev)
    gen = torch.Generator().manual_seed(0)
    for _ in range(2):
        carry, _ = collect(policy, env, buf, memory, stats, cfg, carry, timers)
        assert bool(buf.resets[1:].any())  # episodes start inside the rollout
        for mb in buf.minibatches(2, gen):
            with torch.no_grad():
                ev = policy.evaluate(mb.obs, mb.resets, mb.state, mb.actions)
            torch.testing.assert_close(ev.logp, mb.logp, atol=1e-4, rtol=1e-4)
            torch.testing.assert_close(ev.value, mb.values, atol=1e-4, rtol=1e-4)
