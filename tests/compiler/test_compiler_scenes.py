"""Procedural scenes: deterministic, valid, enclosed, flyable by a 0.3 m drone; the corpus and its command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from navi.commands import scenes
from navi_compiler.ingest import load_scene, procedural
from navi_compiler.ingest.bsp import CLASS_NAMES as SURFACE_CLASS_NAMES
from navi_compiler.ingest.bsp import HORIZONTAL_NZ
from navi_compiler.ingest.procedural import (
    CLASS_NAMES,
    DEFAULT_ENTRIES,
    DRONE_RADIUS,
    FAMILIES,
    SEED_CLEARANCE,
    Box,
    Cylinder,
    Family,
    Layout,
    Semantics,
    Solid,
    air_grid,
    build_layout,
    cubes_in_air,
    generate_corpus,
    generate_scene,
    is_clear,
    mesh_layout,
    parse_entry,
    slab_between,
    solid_bounds,
    solid_distance,
)

SEEDS = (0, 1, 2)
OPEN = {Family.FOREST, Family.YARD, Family.PLATFORMS, Family.FLOATING, Family.FIELD}
WIDEST = {Family.FLOATING: 80.0, Family.FIELD: 140.0}  # meters across; 60 for the other families
FLIGHT_STEP = {
    Family.FIELD: 1.0
}  # voxel of the seed-to-seed flight test; 0.25 m elsewhere (its gaps are 8 m)
EXPECTED_CLASS = {
    Family.HALL: "pillar",
    Family.FOREST: "trunk",
    Family.BUILDING: "stairs",
    Family.YARD: "obstacle",
    Family.ARENA: "railing",
    Family.PLATFORMS: "pillar",
}


def point_triangle_distance(p: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Distance from one point (3,) to each triangle (F, 3, 3): (F,)."""
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    height = np.einsum("ij,ij->i", p - a, n)
    q = p - height[:, None] * n
    inside = np.ones(len(tris), dtype=bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(v - u, q - u), n) >= 0

    def segment(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        t = np.clip(np.einsum("ij,ij->i", p - u, v - u) / np.einsum("ij,ij->i", v - u, v - u), 0.0, 1.0)
        return np.linalg.norm(p - (u + t[:, None] * (v - u)), axis=1)

    edges = np.minimum(np.minimum(segment(a, b), segment(b, c)), segment(c, a))
    return np.where(inside, np.abs(height), edges)


def ray_crossings(origin: np.ndarray, direction: np.ndarray, tris: np.ndarray) -> int:
    """Number of triangles a ray crosses (Möller–Trumbore)."""
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    e1, e2 = b - a, c - a
    h = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > 1e-12
    f = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origin - a
    u = f * np.einsum("ij,ij->i", s, h)
    q = np.cross(s, e1)
    v = f * (q @ direction)
    t = f * np.einsum("ij,ij->i", e2, q)
    return int((ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)).sum())


def clear_voxels(layout: Layout, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Grid points (step apart) with DRONE_RADIUS of free space: (mask (Nx, Ny, Nz), origin (3,))."""
    grid = air_grid(layout.air)
    lo = np.array([grid.xs[0], grid.ys[0], grid.zs[0]]) + step / 2
    hi = np.array([grid.xs[-1], grid.ys[-1], grid.zs[-1]])
    axes = [np.arange(lo[k], hi[k], step) for k in range(3)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    clear = cubes_in_air(grid, points.reshape(-1, 3), DRONE_RADIUS).reshape(points.shape[:3])
    for solid in layout.solids:
        box_lo, box_hi = solid_bounds(solid)
        first = np.maximum(np.floor((box_lo - DRONE_RADIUS - lo) / step).astype(int), 0)
        last = np.ceil((box_hi + DRONE_RADIUS - lo) / step).astype(int) + 1
        window = tuple(slice(f, t) for f, t in zip(first, last, strict=True))
        near = points[window]
        clear[window] &= (solid_distance(solid, near.reshape(-1, 3)) > DRONE_RADIUS).reshape(near.shape[:3])
    return clear, lo


@pytest.fixture(scope="module")
def layouts() -> dict[tuple[Family, int], Layout]:
    return {(f, s): build_layout(f, s) for f in FAMILIES for s in SEEDS}


def test_scenes_are_deterministic_and_vary_with_the_seed() -> None:
    for family in FAMILIES:
        a, b, c = generate_scene(family, 5), generate_scene(family.value, 5), generate_scene(family, 6)
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)
        np.testing.assert_array_equal(a.face_class, b.face_class)
        np.testing.assert_array_equal(a.seeds, b.seeds)
        assert a.vertices.shape != c.vertices.shape or not np.array_equal(a.vertices, c.vertices)


@pytest.mark.parametrize("family", FAMILIES)
def test_every_family_is_valid(family: Family, layouts: dict[tuple[Family, int], Layout]) -> None:
    for seed in SEEDS:
        layout = layouts[family, seed]
        scene = mesh_layout(layout)
        tris = scene.vertices[scene.faces]
        area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
        assert np.isfinite(scene.vertices).all() and area.min() > 1e-6
        lo, hi = scene.bounds
        assert 10.0 <= (hi - lo)[:2].max() <= WIDEST.get(family, 60.0) and (hi - lo)[2] >= 2.5, hi - lo
        assert len(scene.seeds) >= 4
        assert ((scene.seeds > lo) & (scene.seeds < hi)).all()
        assert is_clear(air_grid(layout.air), layout.solids, scene.seeds, SEED_CLEARANCE - 1e-6).all()
        names = {CLASS_NAMES[k] for k in np.unique(scene.face_class)}
        assert {"floor", "wall"} <= names and "unknown" not in names
        assert ("ceiling" in names) == (family not in OPEN)
        assert (len(scene.barrier_faces) > 0) == (family in OPEN)
        if family in EXPECTED_CLASS:
            assert EXPECTED_CLASS[family] in names


@pytest.mark.parametrize("family", FAMILIES)
def test_seeds_are_enclosed_and_clear_of_the_mesh(family: Family) -> None:
    scene = generate_scene(family, 11)
    surfaces = scene.vertices[np.concatenate([scene.faces, scene.barrier_faces])]
    directions = np.array([[0.3141, 0.2718, 0.9101], [-0.5772, 0.6931, -0.4312], [0.8660, -0.1234, 0.4848]])
    for seed in scene.seeds:
        assert point_triangle_distance(seed, surfaces).min() >= DRONE_RADIUS
        for d in directions:  # closed: every ray from a seed leaves through an odd number of surfaces
            assert ray_crossings(seed, d / np.linalg.norm(d), surfaces) % 2 == 1


@pytest.mark.parametrize("family", FAMILIES)
def test_a_drone_can_fly_between_all_seeds(family: Family, layouts: dict[tuple[Family, int], Layout]) -> None:
    from scipy import ndimage  # labels the connected free space (requirements-dev.txt)

    step = FLIGHT_STEP.get(family, 0.25)
    for seed in SEEDS[:2]:
        layout = layouts[family, seed]
        clear, origin = clear_voxels(layout, step)
        labels, _ = ndimage.label(clear)
        index = np.round((layout.seeds - origin) / step).astype(int)
        seed_labels = labels[index[:, 0], index[:, 1], index[:, 2]]
        assert (seed_labels > 0).all() and len(set(seed_labels.tolist())) == 1, (family, seed, seed_labels)


def test_solid_distance_matches_geometry() -> None:
    box = Box((0.0, 0.0, 0.0), (1.0, 2.0, 3.0))
    cyl = Cylinder(0.0, 0.0, 1.0, 0.0, 2.0)
    points = np.array([[0.5, 1.0, 1.0], [2.0, 1.0, 1.0], [2.0, 3.0, 3.0]])  # inside, beside, off a corner
    np.testing.assert_allclose(solid_distance(Solid(box, 0), points), [0.0, 1.0, np.sqrt(2.0)])
    np.testing.assert_allclose(
        solid_distance(Solid(cyl, 0), points),
        [np.hypot(0.5, 1) - 1, np.hypot(2, 1) - 1, np.hypot(np.hypot(2, 3) - 1, 1)],
    )


def test_slab_distance_matches_its_mesh() -> None:
    """An oriented slab (a 25 degree ramp) measures the same distance as its 12 triangles from outside."""
    ramp = Solid(slab_between((0.0, 0.0, 0.0), (4.0, 1.0, 2.0), 2.0, 0.3), 8)
    tris, _ = procedural._solid_triangles(ramp.shape)
    rng = np.random.default_rng(0)
    points = rng.uniform(-2.0, 6.0, (400, 3))  # (P, 3)
    want = np.array([point_triangle_distance(p, tris).min() for p in points])  # (P,) to the surface
    got = solid_distance(ramp, points)  # (P,)
    outside = got > 1e-9
    assert outside.sum() > 300
    np.testing.assert_allclose(got[outside], want[outside], atol=1e-9)
    lo, hi = solid_bounds(ramp)
    np.testing.assert_allclose(lo, tris.reshape(-1, 3).min(0))
    np.testing.assert_allclose(hi, tris.reshape(-1, 3).max(0))
    normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])  # (12, 3) outward when wound right
    centre = np.array(ramp.shape.centre)  # type: ignore[union-attr]
    assert (np.einsum("ij,ij->i", normal, tris.mean(1) - centre) > 0).all()


@pytest.mark.parametrize("family", FAMILIES)
def test_surface_semantics_class_faces_as_a_quake_map_does(family: Family) -> None:
    """The same triangles; classes from {floor, wall, ceiling, patch} by the face normal, as ingest.bsp does."""
    layout = build_layout(family, 3)
    by_object, by_surface = mesh_layout(layout), mesh_layout(layout, Semantics.SURFACE)
    np.testing.assert_array_equal(by_object.vertices, by_surface.vertices)
    np.testing.assert_array_equal(by_object.faces, by_surface.faces)
    assert by_surface.class_names == SURFACE_CLASS_NAMES
    tris = by_surface.vertices[by_surface.faces]
    normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    nz = normal[:, 2] / np.linalg.norm(normal, axis=1)
    names = np.array(SURFACE_CLASS_NAMES)[by_surface.face_class]
    assert (nz[names == "floor"] >= HORIZONTAL_NZ).all() and (nz[names == "ceiling"] <= -HORIZONTAL_NZ).all()
    assert (np.abs(nz[names == "wall"]) < HORIZONTAL_NZ).all() and "unknown" not in set(names)
    round_solids = any(isinstance(s.shape, Cylinder) for s in layout.solids)
    assert ("patch" in set(names)) == round_solids


def test_corpus_cycles_families_and_is_deterministic(tmp_path: Path) -> None:
    n = len(DEFAULT_ENTRIES) + 2
    a = generate_corpus(tmp_path / "a", n, seed=4)
    b = generate_corpus(tmp_path / "b", n, seed=4)
    c = generate_corpus(tmp_path / "c", 3, seed=5, families=["maze"])
    entries = [parse_entry(e) for e in (*DEFAULT_ENTRIES, *DEFAULT_ENTRIES[:2])]
    assert [p.name.split("_")[0] for p in a] == [family.value for family, _ in entries]
    assert [scale for _, scale in entries] == [1.0] * 10 + [4.0] * 3 + [
        1.0
    ] * 2  # open entries scaled by up to 4
    for pa, pb in zip(a, b, strict=True):
        assert pa.read_bytes() == pb.read_bytes()
        assert (
            pa.with_name(pa.stem + ".scene.json").read_bytes()
            == pb.with_name(pb.stem + ".scene.json").read_bytes()
        )
    assert a[0].read_bytes() != a[8].read_bytes()  # different families
    assert a[0].read_bytes() != a[len(DEFAULT_ENTRIES)].read_bytes()  # same family, different scene
    assert [p.name for p in c] == ["maze_0000.obj", "maze_0001.obj", "maze_0002.obj"]
    sizes = {tuple(np.round(np.subtract(*load_scene(p).bounds[::-1]), 1)) for p in a}
    assert len(sizes) == n


def test_scaled_entries_repeat_and_scale_each_scene_with_its_seeds(tmp_path: Path) -> None:
    """An entry FAMILY@S: each scene is the unscaled one times a factor in [1, S] drawn from (seed, index)."""
    plain = generate_corpus(tmp_path / "plain", 6, seed=2, families=["hall", "arena"])
    scaled = generate_corpus(tmp_path / "scaled", 6, seed=2, families=["hall@3", "arena@3"])
    again = generate_corpus(tmp_path / "again", 6, seed=2, families=["hall@3", "arena@3"])
    assert [p.name for p in scaled] == [p.name for p in plain]
    factors = []
    for p, s, a in zip(plain, scaled, again, strict=True):
        assert s.read_bytes() == a.read_bytes()
        one, big = load_scene(p), load_scene(s)
        factor = float(np.ptp(big.vertices[:, 0]) / np.ptp(one.vertices[:, 0]))
        np.testing.assert_allclose(big.vertices, one.vertices * factor, atol=1e-5)
        np.testing.assert_allclose(big.seeds, one.seeds * factor, atol=1e-5)
        np.testing.assert_array_equal(big.faces, one.faces)
        factors.append(factor)
    assert all(1.0 <= f <= 3.0 for f in factors) and max(factors) - min(factors) > 0.3, factors
    mixed = generate_corpus(tmp_path / "mixed", 2, seed=2, families=["hall", "arena@3"])
    assert mixed[0].read_bytes() == plain[0].read_bytes() and mixed[1].read_bytes() == scaled[1].read_bytes()
    for bad, why in (
        ("hall@0.5", "from 1 to 100"),
        ("hall@big", "from 1 to 100"),
        ("castle@2", "unknown family"),
    ):
        with pytest.raises(ValueError, match=why):
            generate_corpus(tmp_path / "bad", 1, seed=2, families=[bad])


def test_scenes_generate_command(tmp_path: Path) -> None:
    app = typer.Typer()
    app.add_typer(scenes.app, name="scenes")
    runner = CliRunner()
    result = runner.invoke(
        app, ["scenes", "generate", "--out", str(tmp_path), "--count", "3", "--seed", "2", "--json"]
    )
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["count"] == 3 and len(summary["files"]) == 3
    assert summary["families"] == sorted(f.value for f in FAMILIES[:3])
    assert all(Path(f).is_file() for f in summary["files"])
    result = runner.invoke(
        app, ["scenes", "generate", "--out", str(tmp_path), "--families", "maze,caves", "--count", "2"]
    )
    assert result.exit_code == 0 and "caves, maze" in result.stdout
    bad = runner.invoke(app, ["scenes", "generate", "--out", str(tmp_path), "--families", "castle"])
    assert bad.exit_code == 2 and "castle" in bad.output
    bad = runner.invoke(app, ["scenes", "generate", "--out", str(tmp_path), "--families", "hall@0"])
    assert bad.exit_code == 2 and "the scale after @" in bad.output
    big = runner.invoke(
        app,
        [
            "scenes",
            "generate",
            "--out",
            str(tmp_path / "big"),
            "--families",
            "hall@4",
            "--count",
            "1",
            "--json",
        ],
    )
    assert big.exit_code == 0 and json.loads(big.stdout)["families"] == ["hall"], big.output
    surface = tmp_path / "surface"
    args = ["scenes", "generate", "--out", str(surface), "--families", "arena", "--count", "1", "--semantics"]
    result = runner.invoke(app, [*args, "surface", "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["semantics"] == "surface"
    assert load_scene(surface / "arena_0000.obj").class_names == SURFACE_CLASS_NAMES
    bad = runner.invoke(app, [*args, "texture"])
    assert bad.exit_code == 2 and "texture" in bad.output


def floor_only_share(layout: Layout, rng: np.random.Generator, points: int = 2000) -> float:
    """Share of random points 1-10 m over the floor of a single-box layout with no surface but the floor
    within 10 m: no wall of the box, no sky, no solid."""
    grid = air_grid(layout.air)
    lo = np.array([grid.xs[0], grid.ys[0], grid.zs[0]])  # (3,)
    hi = np.array([grid.xs[-1], grid.ys[-1], grid.zs[-1]])  # (3,)
    p = np.column_stack(
        [rng.uniform(lo[0], hi[0], points), rng.uniform(lo[1], hi[1], points), rng.uniform(1.0, 10.0, points)]
    )  # (P, 3)
    walls = np.minimum(
        np.minimum(p[:, 0] - lo[0], hi[0] - p[:, 0]), np.minimum(p[:, 1] - lo[1], hi[1] - p[:, 1])
    )
    other = np.minimum(walls, hi[2] - p[:, 2])  # (P,) to the box's walls and sky
    for solid in layout.solids:
        other = np.minimum(other, solid_distance(solid, p))
    return float((other >= 10.0).mean())


def test_the_field_leaves_open_floor_where_the_open_families_do_not() -> None:
    """The field's reason to be: a third of its air at flying height (1-10 m) has nothing but the floor
    within 10 m, the drone's view clearance; in the platforms, forest and yard none does."""
    rng = np.random.default_rng(0)
    for seed in SEEDS:
        assert floor_only_share(build_layout(Family.FIELD, seed), rng) > 0.25
        for family in (Family.PLATFORMS, Family.FOREST, Family.YARD):
            assert floor_only_share(build_layout(family, seed), rng) < 0.02
