"""PPO loss on hand-computed numbers and the non-finite update guard."""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import pytest
import torch

from navi_learner.config import EngineConfig, PPOConfig, TemporalCoreName, TrainConfig
from navi_learner.engine.policy import CognitiveMambaPolicy
from navi_learner.engine.tokens import CompactFrames
from navi_learner.ppo.compile import compile_graph, make_objective, ppo_objective, update_graphs
from navi_learner.ppo.loss import mean_bound_loss, ppo_loss
from navi_learner.ppo.rollout import RolloutStorage, decode
from navi_learner.ppo.train import adapt_lr, update


def test_ppo_loss_hand_computed() -> None:
    # ratios e^0.5 = 1.6487 (clipped to 1.2) with A = +1, and e^-0.5 = 0.6065 (clipped to 0.8) with A = -1.
    new_logp, old_logp = torch.tensor([0.5, -0.5]), torch.tensor([0.0, 0.0])
    adv = torch.tensor([1.0, -1.0])
    new_v, old_v, ret = torch.tensor([1.0, 0.0]), torch.tensor([0.0, 0.0]), torch.tensor([2.0, 1.0])
    loss, m = ppo_loss(
        new_logp,
        old_logp,
        adv,
        new_v,
        old_v,
        ret,
        torch.tensor(0.7),
        clip_coef=0.2,
        value_clip_coef=0.5,
        vf_coef=0.5,
        ent_coef=0.1,
        norm_adv=False,
    )
    # policy: max(-A r, -A clip(r)) per sample = max(-1.6487, -1.2) = -1.2 ; max(0.6065, 0.8) = 0.8 -> mean -0.2
    pg = (-1.2 + 0.8) / 2
    # value: unclipped (1-2)^2 = 1, clipped 0.5 -> (0.5-2)^2 = 2.25 -> 2.25 ; sample 2: (0-1)^2 = 1 both -> 0.5*mean
    vl = 0.5 * (2.25 + 1.0) / 2
    assert math.isclose(float(m["policy_loss"]), pg, abs_tol=1e-6)
    assert math.isclose(float(m["value_loss"]), vl, abs_tol=1e-6)
    assert math.isclose(float(loss), pg + 0.5 * vl - 0.1 * 0.7, abs_tol=1e-6)
    kl = ((math.exp(0.5) - 1 - 0.5) + (math.exp(-0.5) - 1 + 0.5)) / 2
    assert math.isclose(float(m["approx_kl"]), kl, abs_tol=1e-6)
    assert math.isclose(float(m["clipfrac"]), 1.0)


def test_ppo_loss_advantage_normalisation() -> None:
    same = torch.zeros(4)
    adv = torch.tensor([1.0, 2.0, 3.0, 4.0])
    _, m1 = ppo_loss(
        same,
        same,
        adv,
        same,
        same,
        same,
        torch.tensor(0.0),
        clip_coef=0.2,
        value_clip_coef=0,
        vf_coef=0.5,
        ent_coef=0.0,
        norm_adv=True,
    )
    # ratio 1 everywhere: policy loss = -mean(normalised A) = 0
    assert abs(float(m1["policy_loss"])) < 1e-6


def test_mean_bound_loss_is_zero_inside_and_pulls_outside_means_back() -> None:
    """Σ_a relu(|μ_a| − 1)² averaged over samples: nothing for means within [-1, 1], the squared excess
    beyond it (either side), a gradient that moves each outside mean towards the bound and leaves the
    inside ones alone; the share it reports counts the entries outside."""
    mean = torch.tensor([[0.5, -1.0, 1.5, -3.0], [0.0, 0.9, -0.2, 1.0]], requires_grad=True)  # (2, 4)
    loss, outside = mean_bound_loss(mean)
    assert float(loss.detach()) == pytest.approx((0.5**2 + 2.0**2) / 2)  # two samples
    assert float(outside) == pytest.approx(2 / 8)
    loss.backward()
    assert mean.grad is not None
    expected = torch.tensor([[0.0, 0.0, 0.5, -2.0], [0.0, 0.0, 0.0, 0.0]])  # d/dμ of excess² / 2 samples
    torch.testing.assert_close(mean.grad, expected)
    inside, none_outside = mean_bound_loss(torch.rand(5, 3, 4) * 2 - 1)
    assert float(inside) == 0.0 and float(none_outside) == 0.0


def tiny_setup(
    core: TemporalCoreName = "mamba2",
    action_input: bool = False,
    compact: bool = False,
    device: torch.device | None = None,
) -> tuple[CognitiveMambaPolicy, RolloutStorage, TrainConfig]:
    """A tiny policy and a filled rollout of 8 steps × 3 actors on `device` (CPU by default): random
    float32 observations, or compact ones (random depths, semantic codes and episode starts)."""
    dev = device or torch.device("cpu")
    eng = EngineConfig(
        temporal_core=core,
        action_input=action_input,
        embed_dim=16,
        patch_size=4,
        encoder_layers=1,
        encoder_heads=2,
        ssm_head_dim=8,
        ssm_chunk=4,
        memory_slots=4,
        head_hidden=16,
        rnd_dim=8,
    )
    cfg = TrainConfig(
        n_actors=3, rollout_length=8, engine=eng, ppo=PPOConfig(bptt_chunk=4, num_minibatches=2)
    )
    policy = CognitiveMambaPolicy((3, 8, 8), eng).to(dev)
    buf = RolloutStorage(8, 3, (3, 8, 8), policy.initial_state(3, dev), 4, dev, compact=compact)
    g = torch.Generator().manual_seed(0)
    if compact:
        buf.depth16.copy_(torch.rand(buf.depth16.shape, generator=g))  # (T+1, N, Az, El) float16
        buf.semantic.copy_(torch.randint(0, 256, buf.semantic.shape, generator=g))  # (T, N, Az, El) uint8
        buf.resets.copy_(torch.rand(8, 3, generator=g) < 0.2)  # (T, N) bool
    else:
        buf.obs.copy_(torch.rand(buf.obs.shape, generator=g))
    buf.actions.copy_(torch.randn(buf.actions.shape, generator=g))
    buf.advantages.copy_(torch.randn(8, 3, generator=g))
    buf.returns.copy_(torch.randn(8, 3, generator=g))
    return policy, buf, cfg


def adam(policy: CognitiveMambaPolicy, fused: bool) -> torch.optim.Adam:
    """The learner's optimizer: fused (skips a step on the device, as on CUDA) or the host-checked one."""
    return torch.optim.Adam(
        [p for p in policy.parameters() if p.requires_grad], lr=1e-2, eps=1e-5, fused=fused
    )


def untouched(opt: torch.optim.Optimizer) -> bool:
    """No step taken: no state, or (fused) state that is still the fresh one (step 0, zero moments)."""
    return all(
        float(st["step"]) == 0 and not st["exp_avg"].any() and not st["exp_avg_sq"].any()
        for st in opt.state.values()
    )


@pytest.mark.parametrize("fused", [False, True])
def test_non_finite_loss_skips_the_update_and_is_counted(fused: bool) -> None:
    torch.manual_seed(0)
    policy, buf, cfg = tiny_setup()
    buf.advantages[2, 1] = float("nan")
    opt = adam(policy, fused)
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    _, skipped = update(policy, opt, buf, cfg, torch.Generator().manual_seed(0))
    assert skipped >= 1
    poisoned_all = skipped == cfg.ppo.num_minibatches * cfg.ppo.ppo_epochs
    for k, v in policy.state_dict().items():
        assert torch.isfinite(v).all(), k
        if poisoned_all:
            assert torch.equal(v, before[k]), k


@pytest.mark.parametrize("fused", [False, True])
def test_non_finite_gradient_never_reaches_the_weights(fused: bool, caplog: pytest.LogCaptureFixture) -> None:
    torch.manual_seed(0)
    policy, buf, cfg = tiny_setup()
    buf.returns[:] = float("inf")
    opt = adam(policy, fused)
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    with caplog.at_level(logging.WARNING):
        _, skipped = update(
            policy, opt, buf, cfg, torch.Generator().manual_seed(0), logging.getLogger("guard")
        )
    warned = [r.message for r in caplog.records if "non-finite" in r.message]
    if fused:  # counted on the device, read and reported once per update
        assert len(warned) == 1 and f"{skipped} optimizer step(s) skipped" in warned[0]
    else:  # read on the host after every minibatch
        assert len(warned) == skipped
    assert skipped == cfg.ppo.num_minibatches
    for k, v in policy.state_dict().items():
        assert torch.equal(v, before[k]), k
    assert untouched(opt)
    assert getattr(opt, "found_inf", None) is None  # nothing left behind for a later step


@pytest.mark.parametrize("fused", [False, True])
def test_finite_update_changes_the_weights(fused: bool) -> None:
    torch.manual_seed(0)
    policy, buf, cfg = tiny_setup()
    opt = adam(policy, fused)
    before = policy.heads.log_std.detach().clone()
    _, skipped = update(policy, opt, buf, cfg, torch.Generator().manual_seed(0))
    assert skipped == 0
    assert not torch.equal(before, policy.heads.log_std.detach())


@pytest.mark.parametrize("poison", [False, True])
def test_fused_update_matches_the_host_checked_one(poison: bool) -> None:
    """The CUDA learner's fused Adam with its on-device skip takes the same steps as plain Adam with a
    host read per minibatch: same weights after an update, clean or with one poisoned minibatch."""
    results = []
    for fused in (False, True):
        torch.manual_seed(0)
        policy, buf, cfg = tiny_setup()
        if poison:
            buf.advantages[2, 1] = float("nan")
        _, skipped = update(policy, adam(policy, fused), buf, cfg, torch.Generator().manual_seed(0))
        results.append((skipped, policy.state_dict()))
    (skip_a, a), (skip_b, b) = results
    assert skip_a == skip_b and (skip_a > 0) == poison
    for k in a:
        torch.testing.assert_close(b[k], a[k], rtol=1e-5, atol=1e-6, msg=k)


@pytest.mark.parametrize(
    ("kl", "expected"),
    [(0.05, 1e-4 / 1.5), (0.001, 1.5e-4), (0.01, 1e-4), (float("nan"), 1e-4), (1.0, 1e-4 / 1.5)],
)
def test_adaptive_rate_follows_the_kl_rule(kl: float, expected: float) -> None:
    """Target 0.01: above 0.02 the rate falls by 1.5, below 0.005 it rises by 1.5, between (or for a
    non-finite KL) it stays."""
    p = torch.nn.Parameter(torch.zeros(2))
    opt = torch.optim.Adam([p], lr=torch.tensor(1e-4))
    adapt_lr(opt, torch.tensor(kl), 0.01, 1e-5, 1e-3)
    assert float(opt.param_groups[0]["lr"]) == pytest.approx(expected, rel=1e-6)


def test_adaptive_rate_stays_within_its_bounds() -> None:
    p = torch.nn.Parameter(torch.zeros(2))
    opt = torch.optim.Adam([p], lr=torch.tensor(9e-4))
    adapt_lr(opt, torch.tensor(0.0), 0.01, 1e-5, 1e-3)
    assert float(opt.param_groups[0]["lr"]) == pytest.approx(1e-3)
    opt.param_groups[0]["lr"].fill_(1.2e-5)
    adapt_lr(opt, torch.tensor(1.0), 0.01, 1e-5, 1e-3)
    assert float(opt.param_groups[0]["lr"]) == pytest.approx(1e-5)


@pytest.mark.parametrize("fused", [False, True])
def test_update_adapts_the_rate_once_per_minibatch(fused: bool) -> None:
    """A KL target far above any step's KL raises the rate by 1.5 before each of the minibatches' steps,
    the fused and host-checked optimizers alike, and the metrics report the mean rate."""
    torch.manual_seed(0)
    policy, buf, cfg = tiny_setup()
    cfg.ppo.target_kl, cfg.ppo.lr_max = (
        1e3,
        1.0,
    )  # the buffer's log-probs are not the policy's: KL of a few nats
    opt = adam(policy, fused)
    opt.param_groups[0]["lr"] = torch.tensor(1e-3)
    metrics, skipped = update(policy, opt, buf, cfg, torch.Generator().manual_seed(0))
    steps = cfg.ppo.num_minibatches * cfg.ppo.ppo_epochs
    assert skipped == 0
    assert float(opt.param_groups[0]["lr"]) == pytest.approx(1e-3 * 1.5**steps, rel=1e-5)
    mean_rate = sum(1e-3 * 1.5**k for k in range(1, steps + 1)) / steps
    assert float(metrics["lr"]) == pytest.approx(mean_rate, rel=1e-5)


@pytest.mark.parametrize(
    ("core", "action_input", "compact"),
    [("mamba2", False, False), ("gru", False, False), ("mamba2", True, False), ("mamba2", False, True)],
)
def test_the_compiled_objective_updates_as_the_eager_one_does(
    core: TemporalCoreName, action_input: bool, compact: bool
) -> None:
    """`--compile-update` traces each minibatch's objective (sequence pass, PPO and RND losses; one graph
    with mamba2, the gru's per-episode segments break it) and its backward, also with the previous action
    as an input, and with compact frames read by the input stage's operator: traced here with the aot_eager backend
    (the CPU runs the same graphs without code generation), one update (2 minibatches) leaves the same
    weights and metrics as eager."""
    results = []
    for compiled in (False, True):
        torch.manual_seed(0)
        policy, buf, cfg = tiny_setup(core, action_input, compact)
        objective = ppo_objective(policy, cfg, norm_adv=True)
        if compiled:
            objective = compile_graph(objective, backend="aot_eager", fullgraph=core == "mamba2")
        metrics, skipped = update(
            policy, adam(policy, False), buf, cfg, torch.Generator().manual_seed(0), objective=objective
        )
        results.append((skipped, metrics, policy.state_dict()))
    (skip_a, ma, a), (skip_b, mb, b) = results
    assert skip_a == skip_b == 0
    assert ma.keys() == mb.keys() and "rnd_loss" in ma
    for k in ma:
        torch.testing.assert_close(mb[k], ma[k], rtol=1e-5, atol=1e-6, msg=k)
    for k in a:
        torch.testing.assert_close(b[k], a[k], rtol=1e-5, atol=1e-6, msg=k)


def test_compact_frames_reach_the_objective_undecoded_and_update_as_their_float32_frames() -> None:
    """A compact rollout's minibatch hands the objective its frames still compact (the encoder's input
    stage reads them as they are): an update over them leaves exactly the weights and metrics of an
    update over a float32 rollout that holds the decoded frames."""
    cpu = torch.device("cpu")
    results = []
    for compact in (True, False):
        torch.manual_seed(0)
        policy, buf, cfg = tiny_setup(compact=True)
        if compact:
            mb = buf.minibatch(buf.minibatch_ids(2, torch.Generator().manual_seed(0))[0])
            assert isinstance(mb.frames, CompactFrames)
            obs = mb.obs  # (L, M, 3, Az, El) float32
            assert torch.equal(decode(mb.frames), obs) and decode(obs) is obs
            assert bool(mb.resets.any()) and bool((obs[:, :, 2] != 0).any())  # starts and deltas
        else:
            flat = RolloutStorage(8, 3, (3, 8, 8), policy.initial_state(3, cpu), 4, cpu)
            for t in range(8):
                flat.obs[t].copy_(buf.obs_at(t))  # (N, 3, Az, El) float32
            for name in ("actions", "advantages", "returns", "resets"):
                getattr(flat, name).copy_(getattr(buf, name))
            buf = flat
        metrics, skipped = update(policy, adam(policy, False), buf, cfg, torch.Generator().manual_seed(0))
        assert skipped == 0
        results.append((metrics, policy.state_dict()))
    (ma, a), (mb_, b) = results
    for k in ma:
        assert torch.equal(mb_[k], ma[k]), k
    for k in a:
        assert torch.equal(b[k], a[k]), k


def test_the_update_objective_is_compiled_by_default_on_cuda_only() -> None:
    """By default the objective is compiled on CUDA; the CPU, --no-compile and --no-compile-update keep
    it eager. A data-parallel run leaves the advantage normalisation to the ranks' pooled statistics."""
    policy, _, cfg = tiny_setup()
    assert cfg.compile and cfg.compile_update
    assert hasattr(make_objective(policy, cfg, torch.device("cuda"), False), "_torchdynamo_orig_callable")
    assert not hasattr(make_objective(policy, cfg, torch.device("cpu"), False), "_torchdynamo_orig_callable")
    for off in (replace(cfg, compile=False), replace(cfg, compile_update=False)):
        assert not hasattr(
            make_objective(policy, off, torch.device("cuda"), False), "_torchdynamo_orig_callable"
        )
    # norm_adv inside the objective only for a single process: advantages 1..4 against constant ones
    same = torch.zeros(1, 4)  # (L, M)
    obs = torch.rand(1, 4, 3, 8, 8)  # (L, M, 3, Az, El)
    state = policy.initial_state(4, torch.device("cpu"))
    args = (obs, torch.zeros(1, 4, dtype=torch.bool), state, torch.zeros(1, 4, 4), same)
    adv = torch.tensor([[1.0, 2.0, 3.0, 4.0]])  # (L, M)
    with torch.no_grad():
        _, single = make_objective(policy, cfg, torch.device("cpu"), False)(*args, adv, same, same)
        _, ranked = make_objective(policy, cfg, torch.device("cpu"), True)(*args, adv, same, same)
        _, normed = make_objective(policy, cfg, torch.device("cpu"), True)(
            *args, (adv - adv.mean()) / adv.std(unbiased=False), same, same
        )
    torch.testing.assert_close(single["policy_loss"], normed["policy_loss"])
    assert not torch.allclose(single["policy_loss"], ranked["policy_loss"])


def test_update_graphs_are_asked_for_and_need_the_compiled_update_on_cuda() -> None:
    """CUDA graphs replay the update by default where the objective is compiled on CUDA as one graph: the
    CPU, --no-compile, --no-compile-update, --no-update-graphs and the gru (its objective splits where it
    reads episode starts on the host) leave them off."""
    on = TrainConfig()
    cuda, cpu = torch.device("cuda"), torch.device("cpu")
    assert on.update_graphs and on.engine.temporal_core == "mamba2"
    assert update_graphs(on, cuda) and update_graphs(on, torch.device("cuda:1"))
    assert not update_graphs(on, cpu)
    assert not update_graphs(replace(on, update_graphs=False), cuda)
    assert not update_graphs(replace(on, compile=False), cuda)
    assert not update_graphs(replace(on, compile_update=False), cuda)
    assert not update_graphs(replace(on, engine=replace(on.engine, temporal_core="gru")), cuda)
    results = []  # on a CPU the option changes nothing: the same eager update
    for graphs in (False, True):
        torch.manual_seed(0)
        policy, buf, tiny = tiny_setup()
        mine = replace(tiny, update_graphs=graphs)
        objective = make_objective(policy, mine, cpu, False)
        assert not hasattr(objective, "_torchdynamo_orig_callable")
        update(policy, adam(policy, False), buf, mine, torch.Generator().manual_seed(0), objective=objective)
        results.append(policy.state_dict())
    for k in results[0]:
        torch.testing.assert_close(results[1][k], results[0][k], rtol=0, atol=0, msg=k)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_the_inductor_compiled_objective_matches_the_eager_one_on_cuda() -> None:
    """On CUDA, with bf16 autocast and the default engine, the compiled objective's loss, metrics and
    gradients are as close to the float32 eager objective's as the eager bf16 objective's are: compiling
    adds no error beyond bf16's own (measured here on the same minibatch, per tensor)."""
    from navi_learner.config import EngineConfig as Engine

    torch.manual_seed(0)
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    dev = torch.device("cuda")
    cfg = TrainConfig(n_actors=64, compile=True, compile_update=True)
    policy = CognitiveMambaPolicy((3, 256, 48), Engine()).to(dev).train()
    policy.encoder.compile(dynamic=False)
    l_len, m = 32, 64
    obs = torch.rand(l_len, m, 3, 256, 48, device=dev)  # (L, M, 3, Az, El)
    resets = torch.rand(l_len, m, device=dev) < 0.05  # (L, M) bool
    state = tuple(s.normal_() * 0.1 for s in policy.initial_state(m, dev))
    actions = torch.randn(l_len, m, 4, device=dev)  # (L, M, 4)
    logp, adv, values, returns = (torch.randn(l_len, m, device=dev) for _ in range(4))  # (L, M) each
    runs = {}
    for name, objective, amp in (
        ("compiled", make_objective(policy, cfg, dev, False), True),
        ("eager", ppo_objective(policy, cfg, True), True),
        ("float32", ppo_objective(policy, cfg, True), False),
    ):
        policy.amp = amp
        policy.zero_grad(set_to_none=True)
        total, metrics = objective(obs, resets, state, actions, logp, adv, values, returns)
        total.backward()
        grads = [q.grad.clone() for q in policy.parameters() if q.grad is not None]
        runs[name] = ([total.detach(), *(metrics[k] for k in sorted(metrics))], grads)
    assert len(runs["compiled"][1]) == len(runs["eager"][1]) == len(runs["float32"][1]) > 0
    for part in (0, 1):  # the loss and metrics, then the gradients
        for got, eager, exact in zip(*(runs[k][part] for k in ("compiled", "eager", "float32")), strict=True):
            bf16_error = float((eager.float() - exact).norm())
            floor = (
                1e-5 * float(exact.norm()) + 1e-7
            )  # float32 reassociation where bf16 leaves a tensor alone
            assert float((got.float() - exact).norm()) <= 2.0 * bf16_error + floor, (part, exact.shape)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("compact", [False, True])
def test_update_graphs_replay_the_compiled_update_on_cuda(compact: bool) -> None:
    """Update graphs on CUDA: two updates of two minibatches each, the compiled objective and its
    backward replayed as CUDA graphs (compact frames read in place, from the rollout's own buffers), leave
    the weights and metrics that the same compiled objective launched kernel by kernel leaves (the same
    kernels: equal within float32 rounding), and inductor skipped none of the graphs."""
    from torch._dynamo.utils import counters

    dev = torch.device("cuda")
    results = []
    for graphs in (False, True):
        torch._dynamo.reset()
        counters.clear()
        torch.manual_seed(0)
        policy, buf, tiny = tiny_setup(compact=compact, device=dev)
        cfg = replace(tiny, device="cuda", update_graphs=graphs)
        objective = make_objective(policy, cfg, dev, False)
        optimizer = adam(policy, True)
        gen = torch.Generator().manual_seed(0)
        metrics = [update(policy, optimizer, buf, cfg, gen, objective=objective)[0] for _ in range(2)]
        if graphs:
            assert counters["inductor"]["cudagraph_skips"] == 0  # every graph was captured, none skipped
        results.append(({k: v.detach().cpu() for k, v in policy.state_dict().items()}, metrics))
    (plain, plain_metrics), (graphed, graphed_metrics) = results
    for k in plain:
        torch.testing.assert_close(graphed[k], plain[k], rtol=1e-5, atol=1e-6, msg=k)
    for ma, mb in zip(plain_metrics, graphed_metrics, strict=True):
        for k in ma:
            torch.testing.assert_close(mb[k], ma[k], rtol=1e-5, atol=1e-6, msg=k)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_the_compiled_objective_reads_compact_frames_as_the_gathered_ones_on_cuda() -> None:
    """On CUDA, with the default engine and bf16 autocast, the compiled objective handed a compact
    minibatch (the input stage's kernel reads it as stored): its loss, metrics and gradients are those of
    the same compiled objective handed the float32 frames that the compiled gather writes out (equal
    within float32 rounding)."""
    from navi_learner.config import EngineConfig as Engine

    torch.manual_seed(0)
    dev = torch.device("cuda")
    cfg = TrainConfig(n_actors=16, compile=True, compile_update=True)
    policy = CognitiveMambaPolicy((3, 256, 48), Engine()).to(dev).train()
    buf = RolloutStorage(16, 16, (3, 256, 48), policy.initial_state(16, dev), 8, dev, compact=True)
    buf.depth16.copy_(torch.rand(buf.depth16.shape, device=dev))  # (T+1, N, Az, El) float16
    buf.semantic.copy_(torch.randint(0, 256, buf.semantic.shape, device=dev))  # (T, N, Az, El) uint8
    buf.resets.copy_(torch.rand(16, 16, device=dev) < 0.1)  # (T, N) bool
    mb = buf.minibatch(buf.minibatch_ids(1, torch.Generator().manual_seed(0))[0])  # L 8, M 32
    assert isinstance(mb.frames, CompactFrames)
    l_len, m = mb.resets.shape
    actions = torch.randn(l_len, m, 4, device=dev)  # (L, M, 4)
    logp, adv, values, returns = (torch.randn(l_len, m, device=dev) for _ in range(4))  # (L, M) each
    objective = make_objective(policy, cfg, dev, False)
    runs = []
    for frames in (mb.frames, mb.obs):
        policy.zero_grad(set_to_none=True)
        total, metrics = objective(frames, mb.resets, mb.state, actions, logp, adv, values, returns)
        total.backward()
        grads = [q.grad.clone() for q in policy.parameters() if q.grad is not None]
        runs.append(([total.detach(), *(metrics[k] for k in sorted(metrics))], grads))
    (fused_out, fused_grads), (plain_out, plain_grads) = runs
    assert len(fused_grads) == len(plain_grads) > 0
    for got, want in zip(fused_out + fused_grads, plain_out + plain_grads, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)


def test_the_objective_adds_the_weighted_mean_bound_and_reports_the_share_outside() -> None:
    """`mean_bound_coef` adds exactly coef × mean_bound_loss of the minibatch's action means to the
    objective, and nothing at 0; `mean_outside` is reported either way, the same for both."""
    policy, buf, cfg = tiny_setup()
    mean_out = policy.heads.actor[-1]
    assert isinstance(mean_out, torch.nn.Linear)
    with torch.no_grad():
        mean_out.bias.fill_(1.4)  # every mean near 1.4 (its weights start near 0): all outside
    mb = buf.minibatch(buf.minibatch_ids(2, torch.Generator().manual_seed(0))[0])
    args = (mb.frames, mb.resets, mb.state, mb.actions, mb.logp, mb.advantages, mb.values, mb.returns)
    plain, m0 = ppo_objective(policy, cfg, norm_adv=True)(*args)
    bounded = replace(cfg, ppo=replace(cfg.ppo, mean_bound_coef=2.0))
    total, m2 = ppo_objective(policy, bounded, norm_adv=True)(*args)
    ev = policy.evaluate(mb.frames, mb.resets, mb.state, mb.actions)
    expected, outside = mean_bound_loss(ev.mean)
    assert float(expected) > 0.1
    torch.testing.assert_close(total - plain, 2.0 * expected.detach(), rtol=1e-5, atol=1e-6)
    assert float(m0["mean_outside"]) == float(m2["mean_outside"]) == float(outside) == 1.0
