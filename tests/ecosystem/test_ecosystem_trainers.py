"""The trainers table (navi_bench.trainers.bench_trainers) on a tiny budget: every trainer trains within its
budget, is evaluated on the unseen split against the reactive avoider from the same spawns, and its row
agrees with its own curve (the first evaluation that beat the avoider, the best one, the env-steps per
second) in one JSON-able dict."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from navi_bench.trainers import TRAINERS, beats_reactive, bench_trainers, best_point
from navi_learner.evaluation.competence import EvalProtocol
from navi_learner.evaluation.evaluate import EvalMetrics

from .conftest import SMALL_VIEW

pytestmark = pytest.mark.usefixtures("single_thread")
BUDGET_S, EVERY_S = 3.0, 1.5


def test_bench_trainers_rows_agree_with_their_curves(
    corpus: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    protocol = EvalProtocol(actors=8, steps=60, episode_steps=30, seed=3)
    lines: list[str] = []
    out = bench_trainers(
        corpus, corpus, tmp_path, device="cpu", config=SMALL_VIEW, actors=8, budget_s=BUDGET_S,
        eval_every_s=EVERY_S, protocol=protocol, navi_core="gru", say=lines.append,
    )  # fmt: skip
    # the libraries print while they train (rsl_rl's runner does); none of it reaches stdout, which
    # `navi bench trainers --json` keeps for its one JSON object
    printed = capsys.readouterr()
    assert printed.out == "" and "Actor Model" in printed.err
    assert json.loads(json.dumps(out)) == out  # plain JSON values throughout
    assert list(out["trainers"]) == list(TRAINERS) and out["settings"]["view"] == [16, 4]
    reactive = EvalMetrics(**out["baselines"]["reactive"])
    assert reactive.steps == 60 and reactive.actors == 8
    for name, row in out["trainers"].items():
        curve = row["curve"]
        assert curve, name
        steps = [p["step"] for p in curve]
        assert steps == sorted(steps) and steps[-1] == row["env_steps"] > 0, name
        assert all(p["train_s"] <= row["train_s"] + 1e-9 for p in curve), name
        assert row["env_steps_per_s"] == pytest.approx(row["env_steps"] / row["train_s"]), name
        for p in curve:
            measured = {k: p[k] for k in ("collisions_per_1k", "coverage_per_1k")}
            m = EvalMetrics(**(out["baselines"]["reactive"] | measured))
            assert p["beats_reactive"] == beats_reactive(m, reactive), (name, p)
        first = next((p for p in curve if p["beats_reactive"]), None)
        if first is None:  # trained the whole budget
            assert row["beat_reactive"] is None and row["train_s"] >= BUDGET_S, name
        else:  # stopped there
            assert row["beat_reactive"]["env_steps"] == first["step"] and curve[-1] is first, name
        assert row["best"] == best_point(curve), name
        assert ("pooled 16 x 4 view" in row["encoder"]) == (name != "navi"), row["encoder"]
        assert any(line.startswith(f"[bench trainers] {name}:") for line in lines), name
    assert "full 16 x 4 view" in out["trainers"]["navi"]["encoder"]
