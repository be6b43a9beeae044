"""`navi bench transfer`: arms parse or are refused, collisions are classed by the surface touched, and a
tiny job runs end to end on a CPU with every part, baseline and summary in its result."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from navi_bench.transfer import (
    WARMUP_UPDATES,
    Arm,
    TransferConfig,
    bench_transfer,
    parse_arm,
    pointgoal_scenes,
    report_markdown,
    summarise,
    verdict,
)
from navi_learner.config import TrainConfig, learning_recipe
from navi_learner.evaluation.competence import EvalProtocol
from navi_learner.evaluation.goal_flights import FLIGHTS
from navi_learner.evaluation.open_floor import OpenFloorConfig
from navi_learner.serving.checkpoint import read_meta
from navi_learner.serving.references import REFERENCES


def test_arms_parse_and_bad_ones_are_refused() -> None:
    assert parse_arm("openarena") == Arm("openarena", real=True)
    assert parse_arm("procedural") == Arm("procedural", real=False, semantics="object", families=())
    arm = parse_arm("procedural:surface:arena+maze")
    assert (arm.semantics, arm.families, arm.key) == (
        "surface",
        ("arena", "maze"),
        "procedural-surface-arena+maze",
    )
    assert parse_arm("procedural:object:rooms+arena@4").families == ("rooms", "arena@4")
    lever = parse_arm("procedural:surface:arena+maze/structure_weight=0,blind_weight=0.1")
    assert lever.reward == (("structure_weight", 0.0), ("blind_weight", 0.1)) and lever.engine == ()
    engine = parse_arm("procedural/action_input=1,structure_weight=0")
    assert engine.engine == (("action_input", True),) and engine.reward == (("structure_weight", 0.0),)
    assert engine.run_key == "procedural-object-all-structure_weight=0-action_input=1"
    assert parse_arm("procedural/attention=explicit,patch_el=8").run_key == (
        "procedural-object-all-attention=explicit-patch_el=8"
    )
    assert lever.key == arm.key  # the same corpus as the arm without the reward
    assert lever.run_key == "procedural-surface-arena+maze-structure_weight=0-blind_weight=0.1"
    assert lever.spec == "procedural:surface:arena+maze/structure_weight=0,blind_weight=0.1"
    assert parse_arm("openarena/collision_weight=5").reward == (("collision_weight", 5.0),)
    view = parse_arm("procedural/view_range=0.2")
    assert view.engine == (("view_range", 0.2),) and view.run_key == "procedural-object-all-view_range=0.2"
    warm = parse_arm("procedural/init_from=explore,structure_weight=0")
    assert (warm.init_from, warm.reward, warm.key) == (
        "explore",
        (("structure_weight", 0.0),),
        "procedural-object-all",
    )
    assert warm.run_key == "procedural-object-all-structure_weight=0-init_from=explore"
    for bad, why in (
        ("procedural/", "name KEY=VALUE after /"),
        ("procedural/action_input=maybe", "expects 1 or 0"),
        ("procedural/view_range=1.5", "view_range must lie in"),
        ("procedural/structure=0", "unknown reward weight"),
        ("procedural/structure_weight", "KEY=NUMBER"),
        ("quake", "expected openarena or procedural"),
        ("procedural:texture", "semantics must be one of"),
        ("procedural:object:castle", "unknown family 'castle'"),
        ("procedural:object:arena@0", "the scale after @"),
        ("openarena:surface", "expected openarena or procedural"),
        ("procedural/init_from=absent.pt", "init_from names one checkpoint"),
        ("procedural/init_from=explore,init_from=pointgoal", "init_from names one checkpoint"),
    ):
        with pytest.raises(ValueError, match=why):
            parse_arm(bad)


def test_a_point_goal_job_refuses_explore_s_collision_weight_before_building(tmp_path: Path) -> None:
    """Point-goal episodes price a contact with pointgoal_collision_weight: an arm naming explore's weight
    stops the job with the right name before any corpus is built."""
    train = replace(learning_recipe(TrainConfig(n_actors=4, rollout_length=16)), task="pointgoal")
    cfg = TransferConfig(arms=(parse_arm("procedural:object:maze/collision_weight=9"),), train=train)
    with pytest.raises(
        ValueError, match="do not read collision_weight; their collision weight is pointgoal_"
    ):
        bench_transfer(cfg, tmp_path / "out", "cpu", 32, tmp_path / "corpora", None, say=lambda _: None)
    assert not (tmp_path / "corpora").exists() and not (tmp_path / "out").exists()


def test_the_bar_on_real_maps() -> None:
    reactive = {"collisions_per_1k": 8.0, "coverage_per_1k": 200.0}
    assert verdict({"collisions_per_1k": 4.0, "coverage_per_1k": 300.0}, {"reactive": reactive}, "explore")
    assert not verdict(
        {"collisions_per_1k": 4.1, "coverage_per_1k": 300.0}, {"reactive": reactive}, "explore"
    )
    assert not verdict(
        {"collisions_per_1k": 1.0, "coverage_per_1k": 299.0}, {"reactive": reactive}, "explore"
    )
    safe = {"collisions_per_1k": 0.0, "coverage_per_1k": 200.0}  # no collisions: 0.5 per 1k allowed
    assert verdict({"collisions_per_1k": 0.5, "coverage_per_1k": 300.0}, {"reactive": safe}, "explore")
    greedy = {"greedy": {"collisions_per_episode": 2.0}}
    row = {"success_rate": 0.9, "spl": 0.8, "collisions_per_episode": 1.9}
    assert verdict(row, greedy, "pointgoal")
    assert not verdict(row | {"spl": 0.79}, greedy, "pointgoal")
    assert not verdict(row | {"collisions_per_episode": 2.0}, greedy, "pointgoal")


def test_bench_transfer_end_to_end_on_a_cpu(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two procedural arms (one family each, object and surface semantics; the first starting from the
    shipped explore reference's weights, the second scaled by up to 2 and trained with a reward weight
    replaced), one seed, no OpenArena package: the job says so, builds each
    arm's corpora, runs the untimed warm-up once, trains each arm with its own reward, flies the baselines
    and each final checkpoint on the unseen procedural scenes and the open floor, sampled as explore flies
    and, in a row of its own, with its mean action (the same checkpoint flying elsewhere), and its summary and report hold
    exactly those runs."""
    import navi_bench.transfer as transfer

    rewards: list[object] = []  # the reward replaced in each training env, in order

    def make_env(*args: Any, **kwargs: Any) -> Any:
        if kwargs.get("episode_steps", 0) == 0:  # a training env (evaluation envs set their episodes)
            rewards.append(kwargs.get("reward"))
        return real_make_env(*args, **kwargs)

    real_make_env = transfer.make_env
    monkeypatch.setattr(transfer, "make_env", make_env)
    train: TrainConfig = learning_recipe(TrainConfig(n_actors=4, rollout_length=16))
    cfg = TransferConfig(
        arms=(
            parse_arm("procedural:object:maze/init_from=explore"),
            parse_arm("procedural:surface:maze@2/structure_weight=0,action_input=1"),
        ),
        seeds=(3,),
        budget_s=2.0,
        train=train,
        protocol=EvalProtocol(actors=4, steps=40, episode_steps=20),
        procedural_train=1,
        procedural_unseen=2,
        open_floor=OpenFloorConfig(
            widths=(15.0,), heights=(1.0,), actors_per_start=1, steps=5, resolution=64
        ),
        action_noise=(1.0, 0.0),
    )
    out = tmp_path / "out"
    result = bench_transfer(
        cfg, out, "cpu", 32, tmp_path / "corpora", tmp_path / "absent.pk3", say=lambda _: None
    )
    saved = json.loads((out / "result.json").read_text())
    assert any("OpenArena maps not found" in note for note in saved["notes"])
    assert saved["scenes"] == {
        "train/procedural-object-maze": ["maze_0000"],
        "train/procedural-surface-maze@2": ["maze_0000"],
    }
    assert set(saved["baselines"]) == {"procedural"} and set(saved["baselines"]["procedural"]) == {
        "random",
        "reactive",
    }
    first, second = (
        "procedural:object:maze/init_from=explore",
        "procedural:surface:maze@2/structure_weight=0,action_input=1",
    )
    assert [(r["arm"], r["action_noise"], r["seed"]) for r in saved["runs"]] == [
        (first, 1.0, 3),
        (f"{first}, mean action", 0.0, 3),
        (second, 1.0, 3),
        (f"{second}, mean action", 0.0, 3),
    ]
    assert rewards == [None, None, {"structure_weight": 0.0}]  # the warm-up, then each arm's run
    engines = [read_meta(Path(r["checkpoint"])).config["engine"]["action_input"] for r in saved["runs"]]
    assert engines == [False, False, True, True]  # only the second arm's fresh engine reads its action
    for sampled, mean in zip(saved["runs"][::2], saved["runs"][1::2], strict=True):
        assert mean["trained_arm"] == sampled["arm"] and mean["checkpoint"] == sampled["checkpoint"]
        flew = [r["final_by_part"]["procedural"]["distance_per_1k"] for r in (sampled, mean)]
        assert flew[0] != flew[1]  # the same drone, flown its own mean and sampled, went elsewhere
    assert (out / "runs" / "procedural-surface-maze@2-structure_weight=0-action_input=1-seed3").is_dir()
    started = [
        json.loads((out / "runs" / f"{key}-seed3" / "manifests" / "run.json").read_text())["init_from"]
        for key in (
            "procedural-object-maze-init_from=explore",
            "procedural-surface-maze@2-structure_weight=0-action_input=1",
        )
    ]
    assert started == [str(REFERENCES["explore"]), None]  # only the first arm started from the reference
    for run in saved["runs"]:
        assert set(run["final_by_part"]) == {"procedural"} and run["steps"] > 0 and run["train_s"] >= 2.0
        (floor,) = run["open_floor"]  # each final checkpoint flew the probe's one floor and start
        assert floor["policy"] == f"{run['arm']} seed 3" and floor["starts"] == [1.0]
        assert result["summary"]["open_floor"][run["arm"]]["15"] == {
            "final_height": [floor["final_height"]],
            "on_floor": [floor["on_floor"]],
        }
        part = run["final_by_part"]["procedural"]
        assert part["actors"] == 4 and part["steps"] == 40
        arm = result["summary"]["parts"]["procedural"]["arms"][run["arm"]]
        assert arm["collisions_per_1k"]["seeds"] == [part["collisions_per_1k"]]
        base = saved["baselines"]["procedural"]
        assert arm["competent_seeds"] == int(verdict(part, base, "explore")) and arm["seeds_run"] == 1
    assert [(w["device"], w["updates"]) for w in saved["warmups"]] == [("cpu", WARMUP_UPDATES)]
    assert (out / "runs" / "warmup-0").is_dir()  # the untimed updates ran once, ahead of both runs
    report = (out / "report.md").read_text()
    assert (
        "| procedural:surface:maze@2/structure_weight=0,action_input=1 |" in report
        and "| reactive |" in report
    )
    assert f"Each worker first ran {WARMUP_UPDATES} untimed updates" in report
    assert "## Open floors" in report and f"| {first} | " in report
    assert result["summary"]["per_map"] == {} and not (out / "transfer.png").exists()


def test_point_goal_summary_counts_competent_seeds_and_shows_each_map() -> None:
    """The summary and report of a point-goal job, from result rows: medians over seeds, the bar per seed
    against greedy, per-map success / SPL beside the seekers', the surfaces touched and how the episodes
    ended (each seed's flights over all maps: medians over seeds, episodes summed)."""
    keys = ("success_rate", "spl", "collisions_per_episode")

    def row(s: float, spl: float, c: float, maps: dict[str, tuple[float, float, float]]) -> dict[str, object]:
        return dict(zip(keys, (s, spl, c), strict=True)) | {
            "per_scene": {m: dict(zip(keys, v, strict=True)) for m, v in maps.items()}
        }

    maps = {"dm1": (1.0, 0.9, 0.0), "dm2": (0.8, 0.7, 1.0)}
    base = {
        "random": row(0.0, 0.0, 4.0, dict.fromkeys(maps, (0.0, 0.0, 4.0))),
        "greedy": row(0.88, 0.84, 4.4, dict.fromkeys(maps, (0.88, 0.84, 4.4))),
        "oracle": row(0.92, 0.86, 0.1, dict.fromkeys(maps, (0.92, 0.86, 0.1))),
    }
    base["greedy"]["collisions_by_surface"] = {
        "all": {"floor": 0, "ceiling": 0, "wall": 3, "slope": 1, "thin": 2}
    }
    flight = dict(zip(FLIGHTS, (10.0, 0.9, 0.95, 0.02, 0.03, 1.0, 0.5, 3.0), strict=True))
    base["greedy"]["goal_flights"] = {"dm1": flight, "all": flight}
    climbs = (25.0, 1.0, 18.0)  # one seed per entry
    runs = [
        {
            "arm": "procedural",
            "seed": seed,
            "final_by_part": {"openarena": row(s, spl, c, maps)},
            "collisions_by_surface": {
                "all": {"floor": 1, "ceiling": 0, "wall": 2, "slope": 0, "thin": seed, "pinned": 1}
            },
            "goal_flights": {"all": flight | {"episodes": 20.0, "climb_m": climbs[seed]}},
        }
        for seed, (s, spl, c) in enumerate(((0.95, 0.85, 0.3), (0.9, 0.79, 0.2), (0.7, 0.6, 5.0)))
    ]
    summary = summarise(runs, {"openarena": base}, "pointgoal")
    arm = summary["parts"]["openarena"]["arms"]["procedural"]
    assert arm["success_rate"] == {"median": 0.9, "seeds": [0.95, 0.9, 0.7]} and arm["spl"]["median"] == 0.79
    assert arm["competent_seeds"] == 1 and arm["seeds_run"] == 3  # seed 1 misses SPL 0.8, seed 2 everything
    assert summary["per_map"]["dm2"]["procedural"] == {
        "success_rate": 0.8,
        "spl": 0.7,
        "collisions_per_episode": 1.0,
    }
    assert summary["per_map"]["dm1"]["greedy"]["spl"] == 0.84
    assert summary["surfaces"]["procedural"] == {
        "floor": 3,
        "ceiling": 0,
        "wall": 6,
        "slope": 0,
        "thin": 3,
        "pinned": 3,
    }
    assert summary["surfaces"]["greedy"]["wall"] == 3
    assert summary["flights"]["procedural"] == flight | {"episodes": 60.0, "climb_m": 18.0}
    assert summary["flights"]["greedy"] == flight
    text = report_markdown(
        {
            "summary": summary,
            "task": "pointgoal",
            "device": "cpu",
            "date": "today",
            "config": {"budget_s": 60.0, "seeds": [0, 1, 2]},
        }
    )
    assert "| procedural | 0.9 (0.95, 0.9, 0.7) | 0.79 (0.85, 0.79, 0.6) | 0.3 (0.3, 0.2, 5) | 1/3 |" in text
    assert "| dm2 | 0 / 0 | 0.88 / 0.84 | 0.92 / 0.86 | 0.8 / 0.7 |" in text
    assert "| procedural | 3 | 0 | 6 | 0 | 3 | 3 |" in text and "| greedy | 0 | 0 | 3 | 1 | 2 | – |" in text
    assert "## How point-goal episodes on the OpenArena maps ended" in text
    assert "| procedural | 60 | 0.9 | 0.95 | 0.02 | 0.03 | 18 | 0.5 | 3 |" in text


def test_point_goal_parts_leave_out_the_maps_where_no_goal_can_be_posed(tmp_path: Path) -> None:
    """A closet 3 m across has no goal 5-30 m from any spawn: the point-goal parts keep the maze beside it
    and say why the closet is left out, instead of failing the whole job when its env is built."""
    import numpy as np
    import trimesh

    from navi_compiler.ingest.procedural import write_scene_mesh
    from navi_compiler.scene import Scene
    from navi_env.corpus.folder import build_corpus, build_default_corpus, merge_corpora

    build_default_corpus(tmp_path / "maze", resolution=32, count=1, seed=0, families=["maze"])
    box = trimesh.creation.box((3.0, 3.0, 3.0))
    closet = Scene(
        name="closet",
        vertices=np.asarray(box.vertices, np.float64),
        faces=np.asarray(box.faces, np.int64),
        face_class=np.zeros(len(box.faces), np.uint8),
        class_names=("unknown",),
        seeds=np.zeros((1, 3), np.float64),
    )
    build_corpus([write_scene_mesh(closet, tmp_path / "closet.obj")], tmp_path / "closet", 32, "cpu")
    merge_corpora([tmp_path / "maze", tmp_path / "closet"], tmp_path / "both")
    keep, notes = pointgoal_scenes(tmp_path / "both", "cpu")
    assert keep == ["maze_0000"], (keep, notes)
    assert len(notes) == 1 and "closet" in notes[0] and "left out" in notes[0], notes
