"""The previous action as an input of the temporal core (EngineConfig.action_input).

Its meaning: a drone pressed against a wall sees the same view whether it hovers or pushes, so only the
action it took tells the two apart. The tests check that the engine reads it (two action histories
under one constant view give different values, and without the input they cannot), that a fresh engine
acts as one without it, and that the PPO pass over stored rollouts reproduces what `act` computed,
across episode starts and BPTT chunks, for each temporal core.
"""

from __future__ import annotations

from dataclasses import asdict

import pytest
import torch

from navi_learner.config import EngineConfig, engine_overrides
from navi_learner.engine.policy import CognitiveMambaPolicy

OBS = (3, 16, 8)  # (C, Az, El) for EngineConfig.tiny()
T_LEN, N = 12, 5


def engine(core: str = "mamba2", action_input: bool = True) -> EngineConfig:
    return EngineConfig.tiny(temporal_core=core, action_input=action_input)


def trained_looking(policy: CognitiveMambaPolicy, seed: int) -> CognitiveMambaPolicy:
    """Give the action embedding non-zero weights, as training would."""
    g = torch.Generator().manual_seed(seed)
    assert policy.action_embed is not None
    with torch.no_grad():
        policy.action_embed.weight.copy_(torch.randn(policy.action_embed.weight.shape, generator=g))
        policy.action_embed.bias.copy_(torch.randn(policy.action_embed.bias.shape, generator=g) * 0.1)
    return policy


@pytest.mark.parametrize("core", ["mamba2", "gru", "mambapy"])
def test_the_ppo_pass_reproduces_what_act_computed_across_resets_and_chunks(core: str) -> None:
    """Roll T steps with sampled actions and episode starts inside; the sequence pass over the first
    half from the initial state and over the second from the state `act` carried into it gives the
    rollout's log-probabilities and values, and the same final state."""
    torch.manual_seed(0)
    policy = trained_looking(CognitiveMambaPolicy(OBS, engine(core)), 1).eval()
    g = torch.Generator().manual_seed(2)
    obs = torch.rand(T_LEN, N, *OBS, generator=g)  # (T, N, 3, Az, El)
    resets = torch.rand(T_LEN, N, generator=g) < 0.2  # (T, N) bool
    resets[0] = True
    state = policy.initial_state(N, torch.device("cpu"))
    assert state[-1].shape == (N, 4)
    actions, logps, values, states = [], [], [], [state]
    with torch.no_grad():
        for t in range(T_LEN):
            out = policy.act(obs[t], resets[t], states[-1])
            actions.append(out.action)
            logps.append(out.logp)
            values.append(out.value)
            states.append(out.state)
        acts = torch.stack(actions)  # (T, N, 4)
        assert bool((acts.abs() > 1.0).any())  # some samples lie outside [-1, 1]: the input clips them
        half = T_LEN // 2
        first = policy.evaluate(obs[:half], resets[:half], states[0], acts[:half])
        second = policy.evaluate(obs[half:], resets[half:], states[half], acts[half:])
        _, _, final = policy.sequence(obs, resets, states[0], acts)
    torch.testing.assert_close(torch.cat((first.logp, second.logp)), torch.stack(logps), atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(
        torch.cat((first.value, second.value)), torch.stack(values), atol=1e-4, rtol=1e-4
    )
    for got, want in zip(final, states[-1], strict=True):
        torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-4)


def test_only_the_action_tells_pushing_into_a_wall_from_hovering() -> None:
    """One view held for 8 steps (the drone does not move); one history hovers (zero actions), the
    other pushes forward at full command. With the input the two end with different values and action
    means; without it (the same weights otherwise) they are identical."""
    torch.manual_seed(0)
    with_input = trained_looking(CognitiveMambaPolicy(OBS, engine()), 3).eval()
    without = CognitiveMambaPolicy(OBS, engine(action_input=False)).eval()
    without.load_state_dict(
        {k: v for k, v in with_input.state_dict().items() if not k.startswith("action_embed")}
    )
    view = torch.rand(1, *OBS).expand(8, 2, *OBS)  # (T, 2, 3, Az, El) the same view every step
    resets = torch.zeros(8, 2, dtype=torch.bool)  # (T, 2)
    resets[0] = True
    history = torch.zeros(8, 2, 4)  # (T, 2, 4) actor 0 hovers
    history[:, 1, 0] = 1.0  # actor 1 commands full forward every step
    for policy, differ in ((with_input, True), (without, False)):
        with torch.no_grad():
            feat, _, _ = policy.sequence(view, resets, policy.initial_state(2, torch.device("cpu")), history)
            mean, value = policy.heads(feat[-1])  # (2, 4), (2,)
        assert bool(torch.ne(value[0], value[1])) is differ
        assert bool(torch.ne(mean[0], mean[1]).any()) is differ


def test_a_fresh_engine_acts_as_one_without_the_input() -> None:
    torch.manual_seed(0)
    fresh = CognitiveMambaPolicy(OBS, engine()).eval()
    plain = CognitiveMambaPolicy(OBS, engine(action_input=False)).eval()
    plain.load_state_dict({k: v for k, v in fresh.state_dict().items() if not k.startswith("action_embed")})
    obs = torch.rand(N, *OBS)  # (N, 3, Az, El)
    resets = torch.zeros(N, dtype=torch.bool)  # (N,)
    state = fresh.initial_state(N, torch.device("cpu"))
    state = (*state[:-1], torch.rand(N, 4) * 2 - 1)  # a previous action, which zero weights ignore
    with torch.no_grad():
        a = fresh.act(obs, resets, state, deterministic=True)
        b = plain.act(obs, resets, state[:-1], deterministic=True)
    assert torch.equal(a.action, b.action) and torch.equal(a.value, b.value)
    assert torch.equal(a.state[-1], a.action.clamp(-1.0, 1.0))  # the next step reads this action


def test_the_flag_is_an_engine_override_and_old_checkpoints_read_it_as_off() -> None:
    assert engine_overrides(["action_input=1"]) == {"action_input": True}
    assert engine_overrides(["action_input=off"]) == {"action_input": False}
    with pytest.raises(ValueError, match="expects 1 or 0"):
        engine_overrides(["action_input=maybe"])
    stored = asdict(EngineConfig(action_input=True))
    assert EngineConfig.from_dict(stored).action_input is True
    stored.pop("action_input")  # a checkpoint written before the field existed
    assert EngineConfig.from_dict(stored).action_input is False


def test_sampled_actions_spread_by_the_noise_scale_and_the_state_keeps_what_was_flown() -> None:
    """With the same random draws, an action sampled at noise S lies S times as far from the mean as one
    sampled at the training spread (1), at 0 it is the mean, and the previous-action state holds the
    action actually taken (clipped), not the mean."""
    policy = trained_looking(CognitiveMambaPolicy(OBS, engine()), 3).eval()
    g = torch.Generator().manual_seed(4)
    obs = torch.rand(N, *OBS, generator=g)  # (N, 3, Az, El)
    resets = torch.ones(N, dtype=torch.bool)  # (N,)
    state = policy.initial_state(N, torch.device("cpu"))
    with torch.no_grad():
        mean = policy.act(obs, resets, state, deterministic=True).action  # (N, 4)
        flown = {}
        for noise in (1.0, 0.5, 0.0):
            torch.manual_seed(7)
            flown[noise] = policy.act(obs, resets, state, noise=noise)
    full = flown[1.0].action - mean  # (N, 4)
    assert float(full.abs().min()) > 0.0
    torch.testing.assert_close(flown[0.5].action - mean, 0.5 * full)
    torch.testing.assert_close(flown[0.0].action, mean)
    torch.testing.assert_close(flown[0.5].state[-1], flown[0.5].action.clamp(-1.0, 1.0))
