"""The scripted `reactive` baseline is a real avoider: on procedural scenes and on OpenArena maps it
collides less than `random` and covers more ground, flying the same spawns with the same env seed.

Each scene is its own env, so a win on one family cannot hide a loss on another.
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import pytest

from navi_compiler.compile import compile_scene
from navi_compiler.gmdag import Gmdag
from navi_compiler.ingest import load_scene
from navi_compiler.ingest.procedural import generate_scene
from navi_env.config import EnvConfig
from navi_env.sim.env import SdfDagEnv
from navi_env.tracer.scene import load_corpus
from navi_learner.evaluation.baselines import RandomPolicy, reactive_for_env
from navi_learner.evaluation.evaluate import EvalMetrics, evaluate

PK3 = Path(
    os.environ.get(
        "NAVI_OPENARENA_PK3", Path(__file__).resolve().parents[2] / "artifacts/data/openarena/pak1-maps.pk3"
    )
)
ACTORS, STEPS = 16, 300
CONFIG = replace(EnvConfig(), max_steps_per_episode=150)


def fly_both(scene: Gmdag) -> tuple[EvalMetrics, EvalMetrics]:
    """(random, reactive) on one scene: ACTORS drones for STEPS steps, env seed 11."""
    corpus = load_corpus([scene], "cpu")
    env = SdfDagEnv(corpus, ACTORS, "cpu", CONFIG, seed=11)
    rand = evaluate(env, RandomPolicy(11), STEPS, seed=11)
    env = SdfDagEnv(corpus, ACTORS, "cpu", CONFIG, seed=11)
    return rand, evaluate(env, reactive_for_env(env), STEPS, seed=11)


def assert_reactive_wins(rand: EvalMetrics, reactive: EvalMetrics) -> None:
    assert rand.collisions_per_1k > 0, rand  # random flight does hit walls here: the test can fail
    assert reactive.collisions_per_1k < 0.5 * rand.collisions_per_1k, (reactive, rand)
    assert reactive.coverage_per_1k > rand.coverage_per_1k, (reactive, rand)


@pytest.mark.parametrize(("family", "seed"), [("rooms", 3), ("caves", 5)])
def test_reactive_beats_random_on_procedural_scenes(family: str, seed: int) -> None:
    scene = compile_scene(generate_scene(family, seed), resolution=128)[0]
    assert_reactive_wins(*fly_both(scene))


@pytest.mark.data
@pytest.mark.skipif(
    not PK3.is_file(), reason=f"OpenArena maps pk3 not found at {PK3} (tests/data/fetch_openarena.sh)"
)
@pytest.mark.parametrize("name", ["aggressor", "oa_dm1"])
def test_reactive_beats_random_on_openarena_maps(name: str) -> None:
    scene = compile_scene(load_scene(PK3, map_name=name), resolution=256)[0]
    assert_reactive_wins(*fly_both(scene))
