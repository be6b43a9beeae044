"""GoalFlights: every ended point-goal episode's record from the steps it took, medians per scene, and
the observers joined for one evaluation."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from navi.cli import build_app
from navi_env.corpus.folder import build_default_corpus
from navi_learner.envs.protocol import StepOut
from navi_learner.evaluation.evaluate import observers
from navi_learner.evaluation.goal_flights import COLUMNS, FLIGHTS, GoalFlights, flight_table


def step(
    z: list[float],
    d: list[float],
    speed: list[float],
    ends: list[bool],
    success: list[bool],
    scene: list[int],
) -> StepOut:
    """One step of two actors whose episodes started 10 m (actor 0) and 20 m (actor 1) from the goal."""
    n = len(z)
    position = torch.zeros(n, 3)  # (N, 3)
    position[:, 2] = torch.tensor(z)
    info = {
        "position": position,
        "goal_distance": torch.tensor(d),
        "start_distance": torch.tensor([10.0, 20.0]),
        "speed": torch.tensor(speed),
        "success": torch.tensor(success),
        "scene_id": torch.tensor(scene),
    }
    return StepOut(
        obs=torch.zeros(n, 3, 4, 2),
        reward=torch.zeros(n),
        done=torch.tensor(success),
        truncated=torch.tensor(ends) & ~torch.tensor(success),
        info=info,
    )


def test_each_ended_episode_is_recorded_from_its_own_steps() -> None:
    """Actor 0 reaches its goal at step 2 and starts again; actor 1 climbs away and times out at step 3.
    The records are exactly what their steps say, the new episode of actor 0 starts afresh, and the
    episode still running at the end is not recorded."""
    flights = GoalFlights()
    flights(step([1.0, 2.0], [6.0, 19.0], [2.0, 1.0], [False, False], [False, False], [0, 1]))
    flights(step([0.5, 5.0], [0.3, 22.0], [1.0, 1.0], [True, False], [True, False], [0, 1]))
    flights(step([3.0, 4.0], [9.0, 30.0], [4.0, 1.0], [False, True], [False, False], [0, 1]))
    flights(step([3.5, 1.0], [1.0, 18.0], [3.0, 2.0], [False, False], [False, False], [0, 1]))
    rec = flights.records()  # (2, 8): actor 0's first episode, actor 1's
    assert rec.shape == (2, len(COLUMNS))
    reached = (0, 1, 1, 0.03, 0.03, 0.0, 0.5, 1.5)  # COLUMNS: scene 0, at the goal, sunk 0.5 m on the way
    away = (1, 0, 0, 0.95, 1.5, 3.0, 0.0, 1.0)  # scene 1, never near, ends 1.5 x as far, climbed 3 m
    assert rec.tolist() == [pytest.approx(reached), pytest.approx(away)]
    rows = flights.summary(("room", "hall", "yard"))
    assert set(rows) == {"room", "hall", "all"}  # yard ended no episode
    assert rows["all"]["episodes"] == 2 and rows["all"]["success"] == 0.5 and rows["all"]["near"] == 0.5
    assert rows["hall"]["climb_m"] == pytest.approx(3.0) and rows["room"]["final"] == pytest.approx(0.03)
    table = flight_table(rows).splitlines()
    assert table[0] == "| scene | " + " | ".join(FLIGHTS) + " |"
    assert [line.split(" | ")[0] for line in table[2:]] == ["| hall", "| room", "| all"]


def test_no_ended_episode_gives_an_empty_all_row_and_observers_join() -> None:
    calls: list[str] = []
    flights = GoalFlights()
    joined = observers(None, flights, lambda out, action: calls.append("second"))
    assert joined is not None and observers(None, None) is None
    joined(
        step([1.0, 1.0], [5.0, 5.0], [1.0, 1.0], [False, False], [False, False], [0, 0]), torch.zeros(2, 4)
    )
    assert calls == ["second"] and flights.records().shape == (0, len(COLUMNS))
    empty = flights.summary(("room",))
    assert list(empty) == ["all"] and empty["all"]["episodes"] == 0.0
    assert all(math.isnan(empty["all"][k]) for k in FLIGHTS[1:])


def test_navi_evaluate_goal_flights_records_every_ended_episode_once(tmp_path: Path) -> None:
    """`navi evaluate --task pointgoal --goal-flights` on a small maze: the episodes it records are the
    episodes the metrics count, and its success share is their success rate; explore is refused."""
    corpus = tmp_path / "maze"
    build_default_corpus(corpus, resolution=32, count=1, seed=0, families=["maze"])
    common = ["--corpus", str(corpus), "--actors", "4", "--steps", "120", "--episode-steps", "40"]
    common += ["--device", "cpu", "--goal-flights"]
    args = ["evaluate", "--policy", "greedy", "--task", "pointgoal", *common]
    out = CliRunner().invoke(build_app(), [*args, "--json"])
    assert out.exit_code == 0, out.stdout + out.stderr
    result = json.loads(out.stdout)
    metrics, flights = result["results"][0], result["goal_flights"]
    assert flights["all"]["episodes"] == metrics["episodes"] >= 4 * 3  # 3 episode limits per actor
    assert flights["all"]["success"] == pytest.approx(metrics["success_rate"])
    (scene,) = [k for k in flights if k != "all"]
    assert flights[scene] == flights["all"] and scene.startswith("maze")
    assert flights["all"]["nearest"] <= flights["all"]["final"] + 1e-6
    text = CliRunner().invoke(build_app(), args).stdout
    assert f"| {scene} | " in text and "| climb_m | sink_m | speed |" in text
    explore = CliRunner().invoke(
        build_app(), ["evaluate", "--policy", "reactive", "--task", "explore", *common]
    )
    assert (
        explore.exit_code != 0
        and "--goal-flights needs point-goal episodes" in explore.stdout + explore.stderr
    )
