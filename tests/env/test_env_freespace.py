"""Free space, its connected parts and true path lengths: the torch passes against breadth-first search
and Dijkstra on random grids (with and without random edge masks), the CPU's frontier relaxation against
the whole-grid passes bit for bit, the 26-neighbourhood metric in open
space, a wall with a doorway, the lattice sampled from a scene's distance field, and its edge test: a
wall thinner than the cell cuts the edges across it and paths go round it."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from navi.cli import build_app
from navi_bench.survey import flight_reward
from navi_compiler.dag.build import build_gmdag
from navi_compiler.gmdag import Gmdag
from navi_env.config import EnvConfig, RewardConfig
from navi_env.space.freespace import (
    EDGE_OFFSETS,
    Flight,
    FreeSpace,
    components,
    components_ref,
    edge_clearance_ref,
    free_space,
    geodesic,
    geodesic_many,
    geodesic_ref,
    greedy_coverage,
    open_edges,
    settle_frontier,
    settle_passes,
    surface_distance,
    surface_distance_ref,
)
from navi_env.tracer.analytic_scenes import AnalyticScene, Box, Room
from navi_env.tracer.scene import load_corpus

from .test_env_env import room_gmdag


def random_free(seed: int, shape: tuple[int, int, int] = (9, 7, 5), share: float = 0.55) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(shape, generator=g) < share  # (X, Y, Z) bool


def random_edges(free: torch.Tensor, seed: int, keep: float = 0.6) -> torch.Tensor:
    """A random share `keep` of the edges between free neighbours (O, X, Y, Z) bool: one entry per pair of
    neighbours, so both directions agree."""
    g = torch.Generator().manual_seed(seed)
    return open_edges(free) & (torch.rand(len(EDGE_OFFSETS), *free.shape, generator=g) < keep)


@pytest.mark.parametrize("seed", range(4))
def test_components_match_breadth_first_search(seed: int) -> None:
    free = random_free(seed, share=0.2)  # several parts
    labels = components(free)
    assert torch.equal(labels, components_ref(free))
    assert int(labels.unique().numel()) > 2  # blocked plus at least two parts


@pytest.mark.parametrize("seed", range(4))
def test_geodesic_matches_dijkstra(seed: int) -> None:
    free = random_free(seed)
    g = torch.Generator().manual_seed(100 + seed)
    candidates = free.nonzero()  # (F, 3)
    sources = candidates[torch.randperm(candidates.shape[0], generator=g)[:2]]  # (2, 3)
    fast, ref = geodesic(free, sources, 0.5), geodesic_ref(free, sources, 0.5)
    assert torch.equal(torch.isinf(fast), torch.isinf(ref)) and bool(torch.isinf(fast[~free]).all())
    finite = torch.isfinite(ref)
    assert torch.allclose(fast[finite], ref[finite], rtol=1e-5, atol=1e-5)
    assert bool(finite.sum() > sources.shape[0])


@pytest.mark.parametrize("seed", range(3))
def test_many_fields_at_once_are_the_single_fields(seed: int) -> None:
    free = random_free(seed)
    g = torch.Generator().manual_seed(200 + seed)
    candidates = free.nonzero()  # (F, 3)
    sources = candidates[torch.randperm(candidates.shape[0], generator=g)[:5]]  # (5, 3)
    many = geodesic_many(free, sources, 0.5)  # (5, X, Y, Z)
    for i in range(5):
        assert torch.equal(many[i], geodesic(free, sources[i : i + 1], 0.5))
    with pytest.raises(ValueError, match="must be free"):
        geodesic_many(free, (~free).nonzero()[:1], 0.5)


@pytest.mark.parametrize("seed", range(4))
def test_components_through_edges_match_breadth_first_search(seed: int) -> None:
    """Random edge masks on random grids: the torch labels are the search's, and cutting edges only ever
    splits parts (every part through the edges lies inside one part of the full neighbourhood)."""
    free = random_free(seed, share=0.5)
    edges = random_edges(free, 400 + seed, keep=0.35)
    labels = components(free, edges)
    assert torch.equal(labels, components_ref(free, edges))
    whole = components(free)
    assert labels.unique().numel() > whole.unique().numel()  # the cuts split some part
    for part in labels[labels >= 0].unique():
        assert whole[labels == part].unique().numel() == 1


@pytest.mark.parametrize("seed", range(4))
def test_geodesic_through_edges_matches_dijkstra(seed: int) -> None:
    free = random_free(seed)
    edges = random_edges(free, 500 + seed)
    g = torch.Generator().manual_seed(100 + seed)
    candidates = free.nonzero()  # (F, 3)
    sources = candidates[torch.randperm(candidates.shape[0], generator=g)[:2]]  # (2, 3)
    fast, ref = geodesic(free, sources, 0.5, edges), geodesic_ref(free, sources, 0.5, edges)
    assert torch.equal(torch.isinf(fast), torch.isinf(ref)) and bool(torch.isinf(fast[~free]).all())
    finite = torch.isfinite(ref)
    assert torch.allclose(fast[finite], ref[finite], rtol=1e-5, atol=1e-5)
    assert bool(finite.sum() > sources.shape[0])
    whole = geodesic(free, sources, 0.5)
    assert bool((fast >= whole).all()) and bool((fast > whole).any())  # fewer edges: never shorter


@pytest.mark.parametrize("seed", range(6))
def test_frontier_relaxation_is_the_whole_grid_passes(seed: int) -> None:
    """settle_frontier (what a CPU runs) ends where settle_passes (what a GPU runs) does, bit for bit: from
    single sources through edges, from several through every free pair, and from scattered start values
    with no free mask (as surface_distance starts); a start value inside a blocked voxel reads inf in both."""
    free = random_free(seed, shape=(11, 9, 6), share=0.7)
    edges = random_edges(free, 700 + seed, keep=0.8)
    g = torch.Generator().manual_seed(300 + seed)
    candidates = free.nonzero()  # (F, 3)
    sources = candidates[torch.randperm(candidates.shape[0], generator=g)[:4]]  # (4, 3)
    start = torch.full((4, *free.shape), math.inf)  # (4, X, Y, Z)
    start[torch.arange(4), sources[:, 0], sources[:, 1], sources[:, 2]] = 0.0
    blocked = (~free).nonzero()[0]  # (3,)
    start[0, blocked[0], blocked[1], blocked[2]] = 0.0
    for mask in (edges, None):
        passes = settle_passes(start.clone(), 0.37, free, mask)  # (4, X, Y, Z)
        assert torch.equal(settle_frontier(start.clone(), 0.37, free, mask), passes)
        assert bool(torch.isfinite(passes).sum() > 4 * 4) and math.isinf(float(passes[0, *blocked]))
    scattered = torch.rand(1, *free.shape, generator=g)  # (1, X, Y, Z)
    scattered = torch.where(scattered < 0.1, scattered * 4.0, math.inf)  # a tenth of the voxels start finite
    assert torch.equal(settle_frontier(scattered, 0.4), settle_passes(scattered, 0.4))


@pytest.mark.parametrize("seed", range(3))
def test_many_fields_through_edges_are_the_single_fields(seed: int) -> None:
    free = random_free(seed)
    edges = random_edges(free, 600 + seed)
    g = torch.Generator().manual_seed(200 + seed)
    candidates = free.nonzero()  # (F, 3)
    sources = candidates[torch.randperm(candidates.shape[0], generator=g)[:5]]  # (5, 3)
    many = geodesic_many(free, sources, 0.5, edges)  # (5, X, Y, Z)
    for i in range(5):
        single = geodesic(free, sources[i : i + 1], 0.5, edges)
        assert torch.equal(many[i], single)
        ref = geodesic_ref(free, sources[i : i + 1], 0.5, edges)
        assert torch.equal(torch.isinf(single), torch.isinf(ref))


@pytest.mark.parametrize("seed", range(3))
def test_open_edges_give_the_full_neighbourhood(seed: int) -> None:
    """Every edge between free neighbours passable is the lattice without the edge test: the same labels,
    path lengths (bit for bit) and planner flight; in a grid free throughout, one edge per neighbour pair."""
    free = random_free(seed)
    edges = open_edges(free)
    assert torch.equal(components(free, edges), components(free))
    sources = free.nonzero()[:3]  # (3, 3)
    assert torch.equal(geodesic_many(free, sources, 0.5, edges), geodesic_many(free, sources, 0.5))
    full = torch.ones(5, 4, 3, dtype=torch.bool)
    pairs = sum(math.prod(n - abs(d) for n, d in zip(full.shape, o, strict=True)) for o in EDGE_OFFSETS)
    assert int(open_edges(full).sum()) == pairs
    space = FreeSpace((0.0, 0.0, 0.0), 0.5, 0.3, free, torch.full(free.shape, 2.0))
    start = space.centre_of(sources[:1])[0]  # (3,)
    assert greedy_coverage(space, start, 3.0, lambda c: 1.0, 5.0, 2.0) == greedy_coverage(
        replace(space, edges=edges), start, 3.0, lambda c: 1.0, 5.0, 2.0
    )


def test_geodesic_in_open_space_is_the_26_neighbour_metric() -> None:
    """With nothing in the way the path length is sqrt3 c + sqrt2 (b - c) + (a - b) cells, a >= b >= c the
    sorted offsets."""
    free = torch.ones(8, 6, 5, dtype=torch.bool)
    dist = geodesic(free, torch.tensor([[1, 2, 0]]), 0.25)
    for i, j, k in [(0, 0, 0), (7, 5, 4), (4, 2, 3), (1, 2, 0)]:
        a, b, c = sorted((abs(i - 1), abs(j - 2), abs(k)), reverse=True)
        want = 0.25 * (math.sqrt(3) * c + math.sqrt(2) * (b - c) + (a - b))
        assert float(dist[i, j, k]) == pytest.approx(want, rel=1e-6)


def test_a_wall_with_a_doorway_lengthens_the_path_and_a_closed_one_cuts_it() -> None:
    free = torch.ones(11, 9, 1, dtype=torch.bool)
    free[5, :, 0] = False  # a wall across x = 5
    free[5, 8, 0] = True  # its doorway at the far end
    start, goal = (2, 0, 0), (8, 0, 0)
    dist = geodesic(free, torch.tensor([start]), 1.0)
    assert float(dist[goal]) > 6.0 + 8.0  # up to the doorway and back down: longer than the 6 straight
    assert float(dist[goal]) == pytest.approx(float(geodesic_ref(free, torch.tensor([start]), 1.0)[goal]))
    free[5, 8, 0] = False
    assert math.isinf(float(geodesic(free, torch.tensor([start]), 1.0)[goal]))
    labels = components(free)
    assert int(labels[start]) != int(labels[goal]) and int(labels[5, 3, 0]) == -1
    with pytest.raises(ValueError, match="must be free"):
        geodesic(free, torch.tensor([[5, 3, 0]]), 1.0)


def test_free_space_of_a_room_is_its_inside_less_the_radius() -> None:
    """The analytic room spans (1, 1, 1)-(15, 15, 7): voxel centres at least the radius from its walls are
    free, the rest not, and every free voxel is one part. Nothing stands between free centres, so every
    edge between free neighbours is passable."""
    corpus = load_corpus([room_gmdag()], "cpu")
    space = free_space(corpus, 0, cell=0.5, radius=0.3)
    every = torch.ones_like(space.free).nonzero()  # (V, 3) every voxel, in flat order
    centres = space.centre_of(every).reshape(*space.free.shape, 3)  # (X, Y, Z, 3)
    lo, hi = torch.tensor([1.0, 1.0, 1.0]), torch.tensor([15.0, 15.0, 7.0])
    inside = torch.minimum(centres - lo, hi - centres).amin(dim=-1)  # (X, Y, Z) distance to the nearest wall
    assert space.free.shape == (28, 28, 12)
    sure = (inside - 0.3).abs() > 0.05  # away from the radius, where trilinear rounding cannot flip it
    assert torch.equal(space.free[sure], (inside >= 0.3)[sure])
    assert bool(
        (space.clearance <= inside + 0.05).all()
    )  # the field is exact near walls, a lower bound beyond
    assert components(space.free).unique().numel() == 2  # blocked, and one room
    assert space.edges is not None and torch.equal(space.edges, open_edges(space.free))
    assert torch.equal(
        space.voxel(torch.tensor([[8.0, 8.0, 4.0], [-5.0, 99.0, 4.2]])),
        torch.tensor([[14, 14, 6], [0, 27, 6]]),
    )


@pytest.mark.parametrize("seed", range(3))
def test_surface_distance_matches_dijkstra(seed: int) -> None:
    g = torch.Generator().manual_seed(300 + seed)
    sampled = torch.rand(9, 7, 5, generator=g) * 3.5 - 0.5  # (X, Y, Z) meters, some solid, some sources
    fast, ref = surface_distance(sampled, 0.5), surface_distance_ref(sampled, 0.5)
    assert torch.allclose(fast, ref, rtol=1e-5, atol=1e-5)
    assert bool((fast >= sampled).all()) and torch.equal(fast[sampled < 0], sampled[sampled < 0])
    assert bool((fast > sampled).any())  # lower bounds were raised


def test_surface_distance_restores_the_room_s_open_space() -> None:
    """In the analytic room the field's samples fall up to 0.75 m short of the distance to the nearest
    wall in the open middle (a lower bound there); the surface distance is within 0.2 m of it everywhere."""
    corpus = load_corpus([room_gmdag()], "cpu")
    space = free_space(corpus, 0, cell=0.5, radius=0.3)
    every = torch.ones_like(space.free).nonzero()  # (V, 3)
    centres = space.centre_of(every).reshape(*space.free.shape, 3)  # (X, Y, Z, 3)
    lo, hi = torch.tensor([1.0, 1.0, 1.0]), torch.tensor([15.0, 15.0, 7.0])
    inside = torch.minimum(centres - lo, hi - centres).amin(dim=-1)  # (X, Y, Z) distance to the nearest wall
    room = inside > 0  # (X, Y, Z) bool
    found = surface_distance(space.clearance, space.cell)  # (X, Y, Z)
    assert float((inside - space.clearance)[room].max()) > 0.5  # the samples alone: cramped
    assert float((found - inside)[room].abs().max()) < 0.2
    assert torch.allclose(found, surface_distance_ref(space.clearance, space.cell), atol=1e-5)


@pytest.fixture(scope="module")
def small_corpus(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two procedural scenes (a room and a hall) at 64^3."""
    runner, root = CliRunner(), tmp_path_factory.mktemp("freespace")
    scenes, corpus = root / "scenes", root / "corpus"
    made = runner.invoke(build_app(), ["scenes", "generate", "--out", str(scenes), "--count", "2",
                                       "--families", "rooms,hall", "--seed", "3"])  # fmt: skip
    assert made.exit_code == 0, made.output
    built = runner.invoke(
        build_app(), ["corpus", "build", str(scenes), "--out", str(corpus), "--resolution", "64"]
    )
    assert built.exit_code == 0, built.output
    return corpus


def test_bench_freespace_reports_every_scene_with_a_sound_bound(small_corpus: Path) -> None:
    """`navi bench freespace` over a small procedural corpus: one row per scene, one part holding the
    spawns, a coverage bound no higher than the speed limit allows and no lower than one cell."""
    runner, corpus = CliRunner(), small_corpus
    result = runner.invoke(
        build_app(), ["bench", "freespace", "--corpus", str(corpus), "--goals", "4", "--json"]
    )
    assert result.exit_code == 0, result.output
    out = json.loads(result.stdout)
    speed = 1000.0 * (math.floor(500 * 0.5 * math.sqrt(3.0)) + 1) / 500
    assert out["step_m"] == pytest.approx(0.5) and len(out["scenes"]) == 2
    for row in out["scenes"]:
        assert row["parts"] >= 1 and 0.0 < row["free_share"] < 1.0
        assert 2.0 <= row["coverage_bound_per_1k"] <= speed
        assert row["coverage_bound_per_1k"] == pytest.approx(
            1000.0 * min(row["reachable_cells_median"], speed / 2) / 500, abs=0.11
        )
        assert row["farthest_path_m"] > 1.0 and row["grid_bytes"] == 30 * math.prod(row["grid"])
        assert 0.0 < row["planner_coverage_per_1k"] <= row["coverage_bound_per_1k"]
        assert 5.0 * 0.2 <= row["planner_speed_m_s"] <= 5.0  # between the limiter's floor and full speed
        assert row["goals"] == 4 and row["goal_pairs_per_spawn"] > 0 and row["cell_m"] == 0.5
        assert row["goal_bytes"] >= 4 * 4 * math.prod(row["grid"])  # four float32 fields
        # rooms and a hall at most 12 m high: no view is clear for 10 m all round
        assert row["open_share"] == 0.0 and 0.3 <= row["view_clearance_median_m"] <= 6.0


def test_a_scaled_entry_opens_space_its_family_lacks(tmp_path: Path) -> None:
    """The survey's openness: platforms as designed have no view clear for 10 m all round; the same scene
    scaled (platforms@4, a factor of 2.73 for this seed) has."""
    from navi_bench.survey import survey_corpus
    from navi_env.corpus.folder import build_default_corpus

    rows = {}
    for entry in ("platforms", "platforms@4"):
        build_default_corpus(tmp_path / entry, 64, 1, 3, families=[entry])
        rows[entry] = survey_corpus(tmp_path / entry, "cpu", cell=4.0)["scenes"][0]
    plain, scaled = rows["platforms"], rows["platforms@4"]
    assert plain["open_share"] == 0.0 and scaled["open_share"] > 0.1
    assert scaled["view_clearance_median_m"] > 2 * plain["view_clearance_median_m"]


def line(shape: tuple[int, int, int], clearance: float) -> FreeSpace:
    """A free line of voxels along the first axis with a wide axis (0.5 m voxels from the origin)."""
    free = torch.zeros(shape, dtype=torch.bool)
    free[(slice(None), 0, 0) if shape[0] > 1 else (0, 0, slice(None))] = True
    return FreeSpace((0.0, 0.0, 0.0), 0.5, 0.3, free, torch.full(shape, clearance))


def test_the_planner_flies_a_corridor_at_the_speed_its_clearance_allows() -> None:
    """Along x at 5 m/s a 0.5 m move takes 0.1 s and a new 1 m cell comes every second move; at half
    the speed (the limiter) it takes twice as long; up a shaft the 2 m/s climb rate is the limit."""
    full = greedy_coverage(
        line((40, 1, 1), 9.0), torch.tensor([0.1, 0.1, 0.1]), 1.05, lambda c: 1.0, 5.0, 2.0
    )
    assert (full.cells, full.meters) == (6, pytest.approx(5.0)) and full.seconds == pytest.approx(1.0)
    half = greedy_coverage(
        line((40, 1, 1), 9.0), torch.tensor([0.1, 0.1, 0.1]), 1.05, lambda c: 0.5, 5.0, 2.0
    )
    assert (half.cells, half.meters) == (3, pytest.approx(2.5))
    shaft = greedy_coverage(
        line((1, 1, 40), 9.0), torch.tensor([0.1, 0.1, 0.1]), 1.05, lambda c: 1.0, 5.0, 2.0
    )
    assert shaft.cells == 3 and shaft.meters == pytest.approx(2.0)  # 4 climbs of 0.25 s


def test_the_planner_flies_only_through_passable_edges() -> None:
    """A corridor cut between voxels 9 and 10: the planner with the map enters the 5 cells before the cut
    (flying 4 m, to voxel 8, the first of the fifth cell) and stops, where the full neighbourhood lets it
    fly on."""
    space = line((40, 1, 1), 9.0)
    edges = open_edges(space.free)
    edges[EDGE_OFFSETS.index((1, 0, 0)), 9, 0, 0] = False
    start = torch.tensor([0.1, 0.1, 0.1])
    cut = greedy_coverage(replace(space, edges=edges), start, 60.0, lambda c: 1.0, 5.0, 2.0)
    assert cut.cells == 5 and cut.meters == pytest.approx(4.0)
    assert greedy_coverage(space, start, 60.0, lambda c: 1.0, 5.0, 2.0).cells == 20


def test_the_planner_stops_when_every_cell_is_entered_and_never_beats_the_bound() -> None:
    short = greedy_coverage(
        line((6, 1, 1), 9.0), torch.tensor([0.1, 0.1, 0.1]), 60.0, lambda c: 1.0, 5.0, 2.0
    )
    assert short.cells == 3 and short.meters == pytest.approx(2.0)  # 3 m of corridor: every cell, then done
    corpus = load_corpus([room_gmdag()], "cpu")
    space = free_space(corpus, 0, cell=0.5, radius=0.3)
    flight = greedy_coverage(space, torch.tensor([8.0, 8.0, 4.0]), 50.0, lambda c: 1.0, 5.0, 2.0)
    assert 0 < flight.cells <= math.floor(flight.meters * math.sqrt(3.0)) + 1 and flight.seconds <= 50.0
    assert flight.meters <= 5.0 * 50.0 + 1e-6


def test_a_lattice_too_large_is_refused_and_a_coarser_cell_found(monkeypatch: pytest.MonkeyPatch) -> None:
    from navi_env.space import freespace

    corpus = load_corpus([room_gmdag()], "cpu")  # 28 x 28 x 12 voxels of 0.5 m
    monkeypatch.setattr(freespace, "MAX_VOXELS", 1000)
    with pytest.raises(ValueError, match="9,408 voxels"):
        free_space(corpus, 0, cell=0.5)
    cell = freespace.lattice_cell(corpus, 0, 0.5, max_voxels=1000)
    assert cell == pytest.approx(0.5 * 1.5**3) and free_space(corpus, 0, cell=cell).free.numel() <= 1000


def test_bench_freespace_flies_the_reactive_baseline_on_each_scene(small_corpus: Path) -> None:
    """--evaluate: the reactive baseline flown on each scene alone, its coverage beside the bound."""
    runner, corpus = CliRunner(), small_corpus
    args = [
        "bench",
        "freespace",
        "--corpus",
        str(corpus),
        "--evaluate",
        "2",
        "--episode-steps",
        "50",
        "--json",
    ]
    result = runner.invoke(build_app(), args)
    assert result.exit_code == 0, result.output
    rows = json.loads(result.stdout)["scenes"]
    assert len(rows) == 2
    top = 1000 * EnvConfig().max_speed * EnvConfig().dt  # meters 1,000 steps at the speed limit can fly
    for row in rows:
        flown = row["evaluated"]["reactive"]
        assert 0.0 < flown["coverage_per_1k"] <= row["coverage_bound_per_1k"]
        assert 0.0 < flown["distance_per_1k"] <= top
        assert flown["m_per_new_cell"] == pytest.approx(
            flown["distance_per_1k"] / flown["coverage_per_1k"], abs=0.01
        )
        assert flown["mean_clearance"] > 0.0 and math.isfinite(flown["reward_per_step"])
    assert rows[0]["evaluated"] != rows[1]["evaluated"]  # each scene flown alone


def test_bench_freespace_scores_the_same_flights_with_another_reward(small_corpus: Path) -> None:
    """--reward rescores the --evaluate flights: the same moves (coverage, meters, clearance) and a reward
    per step that moves by exactly the replaced constant, the planner's as well; an unknown weight is
    refused."""
    runner, app = CliRunner(), build_app()
    base = [
        "bench",
        "freespace",
        "--corpus",
        str(small_corpus),
        "--evaluate",
        "2",
        "--episode-steps",
        "50",
        "--json",
    ]
    plain = runner.invoke(app, base)
    taxed = runner.invoke(app, [*base, "--reward", "existential_tax=-0.5"])
    assert plain.exit_code == 0 and taxed.exit_code == 0, plain.output + taxed.output
    assert json.loads(taxed.stdout)["reward"] == {"existential_tax": -0.5}
    shift = -0.5 - RewardConfig().existential_tax
    for a, b in zip(json.loads(plain.stdout)["scenes"], json.loads(taxed.stdout)["scenes"], strict=True):
        before, after = a["evaluated"]["reactive"], b["evaluated"]["reactive"]
        for key in ("coverage_per_1k", "collisions_per_1k", "distance_per_1k", "mean_clearance"):
            assert after[key] == before[key]
        assert after["reward_per_step"] == pytest.approx(before["reward_per_step"] + shift, abs=2e-4)
        assert b["planner_reward_per_step"] == pytest.approx(a["planner_reward_per_step"] + shift, abs=2e-4)
        assert b["planner_coverage_per_1k"] == a["planner_coverage_per_1k"]
    refused = runner.invoke(app, ["bench", "freespace", "--corpus", str(small_corpus), "--reward", "speed=2"])
    assert refused.exit_code != 0 and "unknown reward weight" in refused.output


@pytest.mark.parametrize("clearance", [3.0, 0.5])
def test_flight_reward_pays_the_env_terms_per_step(clearance: float) -> None:
    """Ten 0.1 s moves into new cells at one clearance, then hovering to the end of a 100-step episode: the
    tax, the proximity cost and the escape drain on every step, the bonus once per new cell above the gate."""
    cfg = EnvConfig()
    r, step = cfg.reward, cfg.max_speed * cfg.dt
    flight = Flight(11, 1.0, 5.0, [(cfg.dt, clearance, True)] * 10)
    near = (1.0 - min(clearance / r.proximity_distance, 1.0)) ** 2
    phi = r.escape_weight * min(clearance, r.proximity_distance) / step
    bonus = 10 * r.exploration_weight if clearance >= r.exploration_min_clearance else 0.0
    expected = r.existential_tax - r.proximity_weight * near - (1.0 - r.shaping_gamma) * phi + bonus / 100
    assert flight_reward(flight, 100, cfg) == pytest.approx(expected, abs=1e-9)


THIN = 0.1  # meters: the wall's thickness, far below the 1.5 m cell
WALL_CELL = 1.5
ROOM_LO, ROOM_HI = (1.0, 1.0, 1.0), (15.0, 15.0, 5.0)


def thin_wall_gmdag(wall_x: float, door: float | None) -> Gmdag:
    """A room (ROOM_LO-ROOM_HI) split across x = wall_x by a solid plate THIN meters thick, open from
    y = `door` to the far wall (None: closed), on a 0.5 m distance-field lattice over a 16 m cube."""
    top = ROOM_HI[1] + 0.5 if door is None else door
    scene = AnalyticScene(
        (Room(ROOM_LO, ROOM_HI), Box((wall_x - THIN / 2, 0.5, 0.5), (wall_x + THIN / 2, top, 5.5))),
        resolution=32,
        voxel_size=0.5,
    )
    return build_gmdag(scene.lattice(), origin=(0.0, 0.0, 0.0), voxel_size=0.5, bounds=(ROOM_LO, ROOM_HI))


BEFORE, AFTER = (4, 1, 0), (5, 1, 0)  # the voxels centred 0.75 m either side of x = 8.5, at y = 3.25


@pytest.mark.parametrize("wall_x", [8.5, 8.6])  # on a plane of the field's lattice, and between two
def test_a_thin_wall_cuts_the_edges_across_it(wall_x: float) -> None:
    """At 1.5 m cells the centres either side of a 0.1 m wall are free neighbours, so the lattice alone
    joins the two halves of the room; the edge test cuts every edge across the wall, and the halves are
    two parts."""
    corpus = load_corpus([thin_wall_gmdag(wall_x, None)], "cpu")
    space = free_space(corpus, 0, WALL_CELL, 0.3)
    assert space.edges is not None
    assert bool(space.free[BEFORE]) and bool(space.free[AFTER])
    x = space.centre_of(torch.tensor([BEFORE, AFTER]))[:, 0]  # (2,) either side of the wall
    assert float(x[0]) < wall_x - THIN / 2 and float(x[1]) > wall_x + THIN / 2
    across = EDGE_OFFSETS.index((1, 0, 0))
    assert bool(open_edges(space.free)[across][BEFORE]) and not bool(space.edges[across][BEFORE])
    whole = components(space.free)
    assert int(whole[BEFORE]) == int(whole[AFTER])  # without the edge test: through the wall
    labels = components(space.free, space.edges)
    assert torch.equal(labels, components_ref(space.free, space.edges))
    centres = space.centre_of(space.free.nonzero())  # (F, 3)
    side = centres[:, 0] > wall_x  # (F,) bool
    part = labels[space.free]  # (F,) in nonzero order
    assert part[~side].unique().numel() == 1 and part[side].unique().numel() == 1
    assert int(labels[BEFORE]) != int(labels[AFTER])


@pytest.mark.parametrize("wall_x", [8.5, 8.6])
def test_a_path_past_a_thin_wall_goes_through_its_doorway(wall_x: float) -> None:
    """With a doorway from y = 11 m the path between the centres either side of the wall is no shorter
    than the shortest one that crosses the wall's plane in the doorway (straight to the doorway's edge
    and on), where the lattice without the edge test reads the 1.5 m straight through."""
    door = 11.0
    corpus = load_corpus([thin_wall_gmdag(wall_x, door)], "cpu")
    space = free_space(corpus, 0, WALL_CELL, 0.3)
    a, b = space.centre_of(torch.tensor([BEFORE, AFTER])).double()  # (3,), (3,)
    plane = torch.tensor([wall_x, door, float(a[2])], dtype=torch.float64)  # where the shortest path crosses
    bound = float((plane - a).norm() + (b - plane).norm())
    field = geodesic(space.free, torch.tensor([BEFORE]), WALL_CELL, space.edges)
    assert bound <= float(field[AFTER]) < math.inf
    assert float(field[AFTER]) == pytest.approx(
        float(geodesic_ref(space.free, torch.tensor([BEFORE]), WALL_CELL, space.edges)[AFTER]), rel=1e-6
    )
    assert float(geodesic(space.free, torch.tensor([BEFORE]), WALL_CELL)[AFTER]) == pytest.approx(WALL_CELL)
    many = geodesic_many(space.free, torch.tensor([BEFORE, AFTER]), WALL_CELL, space.edges)  # (2, X, Y, Z)
    assert torch.equal(many[0], field) and float(many[1][BEFORE]) == pytest.approx(float(field[AFTER]))
    labels = components(space.free, space.edges)
    assert int(labels[BEFORE]) == int(labels[AFTER]) and labels.unique().numel() == 2


@pytest.mark.parametrize("door", [None, 11.0])
def test_edges_agree_with_the_field_sampled_densely_along_them(door: float | None) -> None:
    """Against the distance field sampled at 65 points along every edge: a passable edge keeps half the
    radius from every surface all along (it never crosses one), and a cut one comes within the radius
    of one (up to the samples' spacing); the cut edges here are the wall's."""
    radius = 0.3
    corpus = load_corpus([thin_wall_gmdag(8.6, door)], "cpu")
    space = free_space(corpus, 0, WALL_CELL, radius)
    assert space.edges is not None
    least = edge_clearance_ref(corpus, 0, space, samples=64)  # (O, X, Y, Z)
    cut = open_edges(space.free) & ~space.edges  # (O, X, Y, Z)
    spacing = WALL_CELL * math.sqrt(3.0) / 64
    assert bool((least[space.edges] >= radius / 2).all())
    assert bool((least[cut] < radius + spacing / 2).all()) and bool(cut.any())
    assert bool(torch.isinf(least[~open_edges(space.free)]).all())
    every = torch.ones_like(space.free).nonzero()  # (V, 3)
    x = space.centre_of(every)[:, 0].reshape(space.free.shape)  # (X, Y, Z) voxel centres' x
    for o, offset in enumerate(EDGE_OFFSETS):  # each cut edge joins the two sides of the wall
        far = x + offset[0] * WALL_CELL  # (X, Y, Z) the neighbour's x
        assert bool(((x[cut[o]] < 8.6) != (far[cut[o]] < 8.6)).all())
