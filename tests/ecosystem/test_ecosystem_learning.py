"""Stock trainers learn on Navi: the examples' skrl PPO and TorchRL PPO, trained for a short CPU budget
on the small procedural corpus, beat the random pilot on Navi's own evaluation (navi_learner.evaluation:
collisions and coverage per 1,000 steps, 64 drones for 400 steps from the same spawns)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path
from types import ModuleType

import pytest

from .conftest import SMALL_VIEW

pytestmark = [pytest.mark.usefixtures("single_thread"), pytest.mark.slow]
EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
ACTORS, STEPS = 64, 3072
"""64 drones for 3,072 steps (96 rollouts of 32): 197k env-steps."""


def example(name: str, monkeypatch: pytest.MonkeyPatch) -> ModuleType:
    monkeypatch.syspath_prepend(str(EXAMPLES))
    sys.modules.pop(name, None)
    return importlib.import_module(name)


@pytest.mark.parametrize(("name", "label"), [("train_skrl", "skrl PPO"), ("train_torchrl", "TorchRL PPO")])
def test_stock_ppo_beats_random_flight(
    name: str, label: str, corpus: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The stock trainer's policy collides far less and covers more than random flight."""
    act = example(name, monkeypatch).train(str(corpus), ACTORS, STEPS, SMALL_VIEW)
    trained, rand = example("common", monkeypatch).against_random(corpus, label, act, SMALL_VIEW)
    assert rand.collisions_per_1k > 5.0, rand  # random flight does hit walls here: the test can fail
    assert trained.collisions_per_1k < 0.25 * rand.collisions_per_1k, (trained, rand)
    assert trained.coverage_per_1k > 1.25 * rand.coverage_per_1k, (trained, rand)
