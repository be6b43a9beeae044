"""The open-floor probe: flat floors under an undrawn sky, drones started at several heights. It must tell a
drone that holds its height from one that sinks, and say which start ended where."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from navi.cli import build_app
from navi_learner.evaluation.open_floor import (
    OpenFloorConfig,
    build_open_floors,
    open_floor_env,
    open_floor_probe,
    probe_table,
)

CFG = OpenFloorConfig(widths=(15.0, 60.0), heights=(1.0, 4.0, 16.0), actors_per_start=2, steps=40, tail=10,
                      resolution=64)  # fmt: skip


class Constant:
    """Always the same action: [forward, vertical, lateral, yaw_rate]."""

    def __init__(self, name: str, action: tuple[float, float, float, float]) -> None:
        self.name, self.action = name, torch.tensor(action)

    def reset(self, n: int, device: torch.device) -> None:
        self.n = n

    def act(self, obs: torch.Tensor, resets: torch.Tensor) -> torch.Tensor:
        return self.action.to(obs.device).expand(obs.shape[0], 4).clone()  # (N, 4)


@pytest.fixture(scope="module")
def floors(tmp_path_factory: pytest.TempPathFactory) -> dict[float, Path]:
    return build_open_floors(tmp_path_factory.mktemp("open-floor"), CFG)


def test_the_starts_stay_a_meter_under_each_sky(tmp_path: Path) -> None:
    assert CFG.starts() == [(15.0, 1.0), (15.0, 4.0), (60.0, 1.0), (60.0, 4.0), (60.0, 16.0)]
    high = replace(CFG, widths=(15.0,), sky_ratio=1.0)
    assert high.starts() == [(15.0, 1.0), (15.0, 4.0)]  # 16 m is not 1 m under a 15 m sky
    (low,), (tall,) = (
        build_open_floors(tmp_path, replace(high, sky_ratio=0.2)).values(),
        build_open_floors(tmp_path, high).values(),
    )
    assert low.name == "open-floor-15m-sky3m-64.gmdag" and tall.name == "open-floor-15m-sky15m-64.gmdag"
    with pytest.raises(ValueError, match="no start height"):
        build_open_floors(Path("/nonexistent"), OpenFloorConfig(widths=(3.0,)))


def test_a_hovering_drone_ends_at_every_start_height_without_contact(floors: dict[float, Path]) -> None:
    env = open_floor_env(floors, CFG, "cpu")
    rows = open_floor_probe(Constant("hover", (0.0, 0.0, 0.0, 0.3)), env, CFG)
    assert [(r.width, r.starts) for r in rows] == [(15.0, [1.0, 4.0]), (60.0, [1.0, 4.0, 16.0])]
    for r in rows:
        assert r.final_by_start == pytest.approx(r.starts, abs=1e-3)
        assert r.on_floor == 0.0 and r.contacts_per_1k == 0.0 and r.episodes_ended == 0


def test_a_sinking_drone_ends_pressed_to_every_floor_it_reaches(floors: dict[float, Path]) -> None:
    """Full speed down: 2 m/s, slowed by the proximity limiter to a fifth of that in the last meters. From 1
    and 4 m the floor is reached within the 80 steps and the drone rests on it, pressed; from 16 m it is
    still on its way down at the end."""
    cfg = replace(CFG, steps=80)
    env = open_floor_env(floors, cfg, "cpu")
    rows = open_floor_probe(Constant("sink", (0.0, -1.0, 0.0, 0.0)), env, cfg)
    radius = env.config.drone_radius
    narrow, wide = rows
    assert narrow.on_floor == 1.0 and wide.on_floor == pytest.approx(2 / 3)  # two starts of three landed
    resting = [*narrow.final_by_start, *wide.final_by_start[:2]]
    assert all(radius - 0.05 < h < radius + 0.1 for h in resting), resting
    assert 1.0 < wide.final_by_start[2] < 16.0 - 2.0 * 0.1 * 40  # sinking, not yet down
    assert narrow.contacts_per_1k > wide.contacts_per_1k > 0.0  # the wide floor's highest start: no contact
    table = probe_table(rows)
    assert "| sink | 15 x 15, sky 5 |" in table and "| 100% |" in table


def test_bench_openfloor_flies_a_checkpoint_and_the_avoider(tmp_path: Path) -> None:
    """`navi bench openfloor --json`: one row per policy and floor, each start's final height, and the
    reactive avoider, which climbs to its minimum height over the floor and never touches it."""
    from navi_learner.evaluation.main_job import REFERENCE

    args = [
        "bench",
        "openfloor",
        str(REFERENCE),
        "--widths",
        "15",
        "--steps",
        "20",
        "--actors-per-start",
        "1",
    ]
    done = CliRunner().invoke(build_app(), [*args, "--scenes", str(tmp_path), "--json"])
    assert done.exit_code == 0, done.output
    result = json.loads(done.output)
    rows = result["rows"]
    shown = str(REFERENCE.relative_to(Path.cwd()) if REFERENCE.is_relative_to(Path.cwd()) else REFERENCE)
    assert [(r["policy"], r["width"], r["starts"]) for r in rows] == [
        (shown, 15.0, [1.0, 2.0, 4.0]),
        ("reactive", 15.0, [1.0, 2.0, 4.0]),
    ]
    assert rows[1]["contacts_per_1k"] == 0.0 and rows[1]["final_by_start"][0] > 1.0
    assert result["config"]["steps"] == 20
    bad = CliRunner().invoke(build_app(), ["bench", "openfloor", "--widths", "2", "--scenes", str(tmp_path)])
    assert bad.exit_code != 0 and "no start height" in bad.output
    goal = REFERENCE.with_name("mamba2-pointgoal.pt")
    bad = CliRunner().invoke(build_app(), ["bench", "openfloor", str(goal), "--scenes", str(tmp_path)])
    assert bad.exit_code != 0 and "trained for pointgoal" in bad.output


@pytest.mark.gpu
def test_the_probe_flies_the_same_on_cuda_as_on_the_cpu(floors: dict[float, Path]) -> None:
    """The same scripted descent, eager on both devices: the same final heights, floors and contacts."""
    cfg = replace(CFG, steps=60)
    sink = Constant("sink", (0.3, -0.5, 0.0, 0.2))
    cpu = open_floor_probe(sink, open_floor_env(floors, cfg, "cpu"), cfg)
    cuda = open_floor_probe(sink, open_floor_env(floors, cfg, "cuda"), cfg)
    for a, b in zip(cpu, cuda, strict=True):
        assert b.final_by_start == pytest.approx(a.final_by_start, abs=0.02)
        assert (b.on_floor, b.contacts_per_1k) == pytest.approx((a.on_floor, a.contacts_per_1k), abs=25.0)
