"""The rewards cannot be farmed and stay within their documented bounds on real flights.

- Approach-retreat cycles at every speed earn no net shaping (escape + structure): their sum is at
  most Phi(end) - Phi(start), the potential difference of the end states, however many cycles.
- Long randomized CPU rollouts (random and reactive actions) over procedural and OpenArena scenes:
  every term lies within `term_bounds` on every step, and the clearance the rewards read changes by
  at most the distance flown plus one voxel. The old clearance (far-field lower bounds, and a field
  that jumped at Quake 3 sky barriers) broke both: escape paid up to 90 per step on unseen 512^3 maps.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

from navi_compiler.compile import compile_scene
from navi_compiler.ingest import load_scene
from navi_compiler.ingest.procedural import generate_scene
from navi_env.config import EnvConfig
from navi_env.sim.env import SdfDagEnv
from navi_env.sim.rewards import SHAPING_TERMS, escape_potential, structure_potential, term_bounds
from navi_env.tracer.scene import SceneCorpus, load_corpus
from navi_learner.evaluation.baselines import RandomPolicy, ReactivePolicy

from .test_env_env import room_gmdag

PK3 = Path(
    os.environ.get(
        "NAVI_OPENARENA_PK3", Path(__file__).resolve().parents[2] / "artifacts/data/openarena/pak1-maps.pk3"
    )
)
CFG = EnvConfig()  # the default 256 x 48 pattern: the clearance is as accurate as users get it


def potential(env: SdfDagEnv) -> torch.Tensor:
    """Phi_escape + Phi_structure of every actor's current view (N,)."""
    r, step = env.config.reward, env.config.max_speed * env.config.dt
    return escape_potential(env.clearance, step, r) + structure_potential(env.mid, env.front_mid, r)


@pytest.mark.parametrize("speed", [0.2, 0.5, 1.0])
def test_approach_retreat_cycles_earn_no_net_shaping(speed: float) -> None:
    """Fly at a wall until 0.6 m from it, back to the start, three times: the shaping summed over the
    flight is at most Phi(end) - Phi(start). The one-sided escape reward of the old env would have
    paid for every retreat."""
    corpus = load_corpus([room_gmdag()], "cpu")
    env = SdfDagEnv(corpus, 1, "cpu", CFG, spawns=[torch.tensor([[8.0, 8.0, 4.0]])])
    env.reset(seed=0)
    env.yaw.zero_()  # face the wall at x = 15
    env.step(torch.zeros(1, 4))  # hover once: the view is now traced facing the wall
    start = potential(env).clone()
    shaping, old_escape, cycles, forward = 0.0, 0.0, 0, True
    r, step = CFG.reward, CFG.max_speed * CFG.dt
    for _ in range(2000):
        before = float(env.clearance[0])
        out = env.step(torch.tensor([[speed if forward else -speed, 0.0, 0.0, 0.0]]))
        after = float(env.clearance[0])
        shaping += sum(float(out.reward_terms[name][0]) for name in SHAPING_TERMS)
        if before < r.proximity_distance:  # the old escape: clearance gained near geometry, never charged
            old_escape += r.escape_weight * max(after - before, 0.0) / step
        if forward and after < 0.6:
            forward = False
        elif not forward and float(env.position[0, 0]) <= 8.0:
            forward, cycles = True, cycles + 1
            if cycles == 3:
                break
    assert cycles == 3
    assert not bool(env.truncated.any())
    assert shaping <= float(potential(env)[0] - start[0]) + 1e-4
    assert old_escape > 1.0  # the cycles really went near the wall and back


def procedural_corpus() -> SceneCorpus:
    """A closed and an open family (the open one has an undrawn lid, a barrier) at 64^3."""
    scenes = [
        compile_scene(generate_scene(family, seed), resolution=64)[0]
        for family, seed in (("rooms", 3), ("yard", 4))
    ]
    return load_corpus(scenes, "cpu")


def openarena_corpus() -> SceneCorpus:
    """islanddm (open sky: barriers) and aggressor (a 7.6 cm voxel: far bounds below the drone radius)."""
    maps = (("islanddm", 256), ("aggressor", 512))
    return load_corpus(
        [compile_scene(load_scene(PK3, map_name=m), resolution=res)[0] for m, res in maps], "cpu"
    )


def check_rollout(corpus: SceneCorpus, steps: int, actors: int) -> None:
    """Random and reactive flights: every term within its bound on every step, and |change of the
    clearance| <= distance flown + one voxel for every actor that was not reset."""
    voxel = torch.tensor([info.voxel_size for info in corpus.infos])  # (S,)
    for policy in (RandomPolicy(5), ReactivePolicy()):
        env = SdfDagEnv(corpus, actors, "cpu", CFG, seed=7)
        policy.reset(actors, torch.device("cpu"))
        obs, resets = env.reset(seed=7), torch.ones(actors, dtype=torch.bool)
        for _ in range(steps):
            before, position, scene = env.clearance.clone(), env.position.clone(), env.scene.clone()
            out = env.step(policy.act(obs, resets))
            moved = (out.info["position"] - position).norm(dim=1)  # (N,)
            slack = moved + voxel[scene]  # (N,)
            change = (out.info["clearance"] - before).abs()  # (N,)
            kept = ~out.truncated
            assert bool((change[kept] <= slack[kept] + 1e-4).all()), (policy.name, change - slack)
            for name, value in out.reward_terms.items():
                lo, hi = term_bounds(CFG, float(slack.max()))[name]
                assert float(value.min()) >= lo - 1e-5 and float(value.max()) <= hi + 1e-5, (
                    policy.name,
                    name,
                )
            obs, resets = out.obs, out.done | out.truncated


def test_rollouts_on_procedural_scenes_stay_within_bounds(single_thread: None) -> None:
    check_rollout(procedural_corpus(), steps=250, actors=12)


@pytest.mark.data
@pytest.mark.skipif(
    not PK3.is_file(), reason=f"OpenArena maps pk3 not found at {PK3} (tests/data/fetch_openarena.sh)"
)
def test_rollouts_on_openarena_maps_stay_within_bounds() -> None:
    check_rollout(openarena_corpus(), steps=200, actors=12)
