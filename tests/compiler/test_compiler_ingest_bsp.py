"""Quake 3 BSP ingestion on tiny synthetic maps built lump by lump: every rule, every error."""

from __future__ import annotations

import struct
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from navi_compiler.ingest import IngestError, list_pk3_maps, load_scene, read_entities
from navi_compiler.ingest import bsp as q3
from navi_compiler.ingest.patches import bernstein, tessellate_patches

SKY_FLAG, NODRAW, NONSOLID = 0x4, 0x80, 0x4000
SOLID, WATER, TRIGGER = 0x1, 0x20, 0x40000000


@dataclass
class TinyMap:
    """Lumps of a small map, appended to by the helpers below (map units)."""

    shaders: list[tuple[str, int, int]] = field(default_factory=list)
    vertices: list[tuple[tuple[float, ...], tuple[float, ...]]] = field(default_factory=list)  # (pos, normal)
    meshverts: list[int] = field(default_factory=list)
    faces: list[dict[str, object]] = field(default_factory=list)
    planes: list[tuple[tuple[float, float, float], float]] = field(default_factory=list)
    brushsides: list[tuple[int, int]] = field(default_factory=list)
    brushes: list[tuple[int, int, int]] = field(default_factory=list)
    entities: str = ""

    def shader(self, name: str, flags: int, contents: int) -> int:
        self.shaders.append((name, flags, contents))
        return len(self.shaders) - 1

    def quad(
        self,
        corners: list[tuple[float, float, float]],
        normal: tuple[float, float, float],
        shader: int,
        kind: int = 1,
    ) -> None:
        """A face of 4 corners (counter-clockwise about normal), triangles stored clockwise as Quake 3 does."""
        first = len(self.vertices)
        self.vertices += [(c, normal) for c in corners]
        start = len(self.meshverts)
        self.meshverts += [0, 2, 1, 0, 3, 2]
        self.faces.append(
            dict(shader=shader, type=kind, vertex=first, n_vertices=4, meshvert=start, n_meshverts=6)
        )

    def patch(self, grid: np.ndarray, shader: int) -> None:
        """A Bézier patch face from a (height, width, 3) control grid (normals +Z)."""
        h, w, _ = grid.shape
        first = len(self.vertices)
        self.vertices += [(tuple(p), (0.0, 0.0, 1.0)) for p in grid.reshape(-1, 3)]
        self.faces.append(dict(shader=shader, type=2, vertex=first, n_vertices=h * w, size=(w, h)))

    def billboard(self, at: tuple[float, float, float], shader: int) -> None:
        self.vertices.append((at, (0.0, 0.0, 1.0)))
        self.faces.append(dict(shader=shader, type=4, vertex=len(self.vertices) - 1, n_vertices=1))

    def brush(self, planes: list[tuple[tuple[float, float, float], float]], shader: int) -> None:
        first = len(self.brushsides)
        for normal, dist in planes:
            self.planes.append((normal, dist))
            self.brushsides.append((len(self.planes) - 1, shader))
        self.brushes.append((first, len(planes), shader))

    def build(self) -> bytes:
        def records(dtype: np.dtype, rows: list[dict[str, object]]) -> bytes:
            out = np.zeros(len(rows), dtype=dtype)
            for i, row in enumerate(rows):
                for key, value in row.items():
                    out[key][i] = value
            return out.tobytes()

        mins = np.min([v[0] for v in self.vertices], axis=0)
        maxs = np.max([v[0] for v in self.vertices], axis=0)
        lumps = {
            q3.LUMP_ENTITIES: self.entities.encode() + b"\0",
            q3.LUMP_SHADERS: records(
                q3.SHADER_DTYPE, [dict(name=n.encode(), flags=f, contents=c) for n, f, c in self.shaders]
            ),
            q3.LUMP_PLANES: records(q3.PLANE_DTYPE, [dict(normal=n, dist=d) for n, d in self.planes]),
            q3.LUMP_MODELS: records(
                q3.MODEL_DTYPE,
                [
                    dict(
                        mins=mins,
                        maxs=maxs,
                        face=0,
                        n_faces=len(self.faces),
                        brush=0,
                        n_brushes=len(self.brushes),
                    )
                ],
            ),
            q3.LUMP_BRUSHES: records(
                q3.BRUSH_DTYPE, [dict(side=s, n_sides=n, shader=sh) for s, n, sh in self.brushes]
            ),
            q3.LUMP_BRUSHSIDES: records(
                q3.BRUSHSIDE_DTYPE, [dict(plane=p, shader=sh) for p, sh in self.brushsides]
            ),
            q3.LUMP_VERTICES: records(
                q3.VERTEX_DTYPE, [dict(position=p, normal=n) for p, n in self.vertices]
            ),
            q3.LUMP_MESHVERTS: np.array(self.meshverts, dtype="<i4").tobytes(),
            q3.LUMP_FACES: records(q3.FACE_DTYPE, self.faces),
        }
        return pack_lumps(lumps)


def pack_lumps(lumps: dict[int, bytes], magic: bytes = b"IBSP", version: int = 46) -> bytes:
    """Header + lumps, each lump 4-byte aligned, in directory order."""
    header = bytearray(magic + struct.pack("<i", version) + bytes(8 * 17))
    body = bytearray()
    for lump in range(17):
        data = lumps.get(lump, b"")
        struct.pack_into("<ii", header, 8 + 8 * lump, len(header) + len(body), len(data))
        body += data + bytes(-len(data) % 4)
    return bytes(header + body)


def _square(
    z: float, x0: float = 0.0, size: float = 64.0, up: bool = True
) -> list[tuple[float, float, float]]:
    corners = [(x0, 0.0, z), (x0 + size, 0.0, z), (x0 + size, size, z), (x0, size, z)]
    return corners if up else corners[::-1]


def _cube_planes(
    lo: tuple[float, float, float], hi: tuple[float, float, float]
) -> list[tuple[tuple[float, float, float], float]]:
    planes = []
    for axis in range(3):
        n = [0.0, 0.0, 0.0]
        n[axis] = 1.0
        planes.append((tuple(n), hi[axis]))
        n = [0.0, 0.0, 0.0]
        n[axis] = -1.0
        planes.append((tuple(n), -lo[axis]))
    return planes  # type: ignore[return-value]


CURVED = np.array(
    [[[100 + 16 * c, 16 * r, 32.0 if r == 1 else 0.0] for c in range(3)] for r in range(3)], dtype=np.float64
)  # (3, 3, 3) control grid bulging up along its middle row


def tiny_map() -> TinyMap:
    m = TinyMap()
    concrete = m.shader("textures/test/concrete", 0, SOLID)
    m.quad(_square(0.0), (0.0, 0.0, 1.0), concrete)  # floor
    m.quad(_square(128.0, up=False), (0.0, 0.0, -1.0), concrete)  # ceiling
    wall = [(0.0, 0.0, 0.0), (0.0, 64.0, 0.0), (0.0, 64.0, 64.0), (0.0, 0.0, 64.0)]
    m.quad(wall, (1.0, 0.0, 0.0), concrete, kind=3)  # a mesh face standing as a wall
    m.quad(
        _square(200.0, up=False), (0.0, 0.0, -1.0), m.shader("textures/test/space", SKY_FLAG | 0x10, SOLID)
    )
    m.quad(_square(210.0, up=False), (0.0, 0.0, -1.0), m.shader("textures/skies/night", 0, SOLID))
    m.quad(_square(220.0), (0.0, 0.0, 1.0), m.shader("textures/test/hidden", NODRAW, SOLID))
    m.quad(_square(230.0), (0.0, 0.0, 1.0), m.shader("textures/common/trigger", NODRAW, TRIGGER))
    m.quad(_square(240.0), (0.0, 0.0, 1.0), m.shader("textures/liquids/calm_water", NONSOLID, WATER))
    m.quad(_square(250.0), (0.0, 0.0, 1.0), m.shader("textures/test/decal", NONSOLID, 0))
    m.quad(_square(260.0), (0.0, 0.0, 1.0), m.shader("textures/test/fog_thick", 0, SOLID))
    m.patch(CURVED, concrete)
    flat = np.array([[[300 + 8 * c, 8 * r, 16.0] for c in range(5)] for r in range(3)], dtype=np.float64)
    m.patch(flat, concrete)  # 5 × 3 grid: two patches side by side
    m.billboard((50.0, 50.0, 999.0), m.shader("textures/sfx/flare", 0, SOLID))
    m.brush([*_cube_planes((200.0, 0.0, 0.0), (264.0, 64.0, 64.0)), ((1.0, 0.0, 0.0), 264.0)], concrete)
    m.brush(
        _cube_planes((400.0, 0.0, 0.0), (464.0, 64.0, 64.0)),
        m.shader(
            "textures/common/trigger", NODRAW, SOLID
        ),  # as OpenArena ships it: solid contents, trigger name
    )
    m.brush(
        _cube_planes((500.0, 0.0, 0.0), (564.0, 64.0, 64.0)), m.shader("textures/liquids/water2", 0, WATER)
    )
    m.entities = (
        '{\n"classname" "worldspawn"\n"message" "tiny"\n}\n'
        '{\n"classname" "info_player_deathmatch"\n"origin" "32 32 24"\n"angle" "90"\n}\n'
        '{\n"classname" "team_CTF_redspawn"\n"origin" "40 40 24"\n}\n'
        '{\n"classname" "team_CTF_blueplayer"\n"origin" "20 20 24"\n}\n'
        '{\n"classname" "info_player_start"\n"origin" "10 10 24"\n}\n'
        '{\n"classname" "info_player_deathmatch"\n"origin" "232 32 8"\n}\n'
        '{\n"classname" "weapon_rocketlauncher"\n"origin" "16 16 16"\n}\n'
    )
    return m


@pytest.fixture(scope="module")
def tiny_bsp(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("bsp") / "tiny.bsp"
    path.write_bytes(tiny_map().build())
    return path


def _centroids(scene_vertices: np.ndarray, tris: np.ndarray) -> np.ndarray:
    return scene_vertices[tris].mean(axis=1)  # (T, 3)


def _normals(vertices: np.ndarray, tris: np.ndarray) -> np.ndarray:
    a, b, c = (vertices[tris[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_record_sizes_match_the_format() -> None:
    sizes = [q3.SHADER_DTYPE, q3.PLANE_DTYPE, q3.NODE_DTYPE, q3.LEAF_DTYPE, q3.MODEL_DTYPE, q3.BRUSH_DTYPE]
    sizes += [q3.BRUSHSIDE_DTYPE, q3.VERTEX_DTYPE, q3.EFFECT_DTYPE, q3.FACE_DTYPE]
    assert [d.itemsize for d in sizes] == [72, 16, 36, 48, 40, 12, 8, 44, 72, 104]


def test_drawn_set_holds_polygons_meshes_and_patches_only(tiny_bsp: Path) -> None:
    scene = load_scene(tiny_bsp, scale=1.0)
    level = q3.BspOptions().patch_level
    patch_tris = 3 * 2 * level * level  # one 3×3 patch + one 5×3 face (two patches)
    assert len(scene.faces) == 2 + 2 + 2 + patch_tris  # floor, ceiling, mesh wall, patches
    z = _centroids(scene.vertices, scene.faces)[:, 2]
    assert z.max() < 200.0  # no sky, nodraw, trigger, water, decal or fog face is drawn
    assert not np.isclose(scene.vertices[:, 2], 999.0).any()  # the billboard is skipped


def test_classes_follow_normals_and_winding_faces_the_normal(tiny_bsp: Path) -> None:
    scene = load_scene(tiny_bsp, scale=1.0)
    names = scene.class_names
    assert names[:5] == ("unknown", "floor", "wall", "ceiling", "patch")
    centre = _centroids(scene.vertices, scene.faces)
    normal = _normals(scene.vertices, scene.faces)
    label = np.array(names)[scene.face_class]
    floor = np.isclose(centre[:, 2], 0.0) & (centre[:, 0] < 64)
    ceiling = np.isclose(centre[:, 2], 128.0)
    wall = np.isclose(centre[:, 0], 0.0)
    assert floor.sum() == ceiling.sum() == wall.sum() == 2
    assert (label[floor] == "floor").all() and np.allclose(normal[floor], [0, 0, 1])
    assert (label[ceiling] == "ceiling").all() and np.allclose(normal[ceiling], [0, 0, -1])
    assert (label[wall] == "wall").all() and np.allclose(normal[wall], [1, 0, 0])
    patches = centre[:, 0] >= 100
    assert (label[patches] == "patch").all() and (normal[patches][:, 2] > 0).all()


def test_sky_by_flag_or_name_and_nodraw_solids_become_barriers(tiny_bsp: Path) -> None:
    scene = load_scene(tiny_bsp, scale=1.0)
    centre = _centroids(scene.vertices, scene.barrier_faces)
    heights = set(np.round(centre[centre[:, 0] < 100, 2], 3))
    assert heights == {
        200.0,
        210.0,
        220.0,
    }  # sky by flag, sky by name, nodraw solid; not trigger/water/decal/fog


def test_name_words_are_whole_parts_less_their_end_digits() -> None:
    names = [
        "textures/gothic_block/blocks17slime",  # a brick texture: solid and drawn, not a slime volume
        "textures/liquids/slime1_2000",  # slime by name, whatever the flags say
        "env/sky1/sky001_bk",  # sky by name (no sky flag)
        "textures/common/trigger",
        "textures/test/waterstain",
        "textures/test/2lava",
    ]
    shaders = np.array([(n.encode(), 0, SOLID) for n in names], dtype=q3.SHADER_DTYPE)  # (6,)
    rules = q3.shader_rules(shaders)
    assert rules.drawn.tolist() == [True, False, False, False, True, False]
    assert rules.blocking.tolist() == [True, False, True, False, True, False]
    assert rules.barrier.tolist() == [False, False, True, False, False, False]


def test_solid_world_brush_becomes_a_closed_barrier_box(tiny_bsp: Path) -> None:
    scene = load_scene(tiny_bsp, scale=1.0)
    tris = scene.vertices[scene.barrier_faces]  # (Fb, 3, 3)
    in_cube = (tris[:, :, 0] >= 200 - 1e-6).all(axis=1) & (tris[:, :, 0] <= 264 + 1e-6).all(axis=1)
    cube = tris[in_cube]
    assert len(cube) == 12  # the duplicated side adds nothing
    area = 0.5 * np.linalg.norm(np.cross(cube[:, 1] - cube[:, 0], cube[:, 2] - cube[:, 0]), axis=1).sum()
    assert area == pytest.approx(6 * 64 * 64)
    outward = _normals(scene.vertices, scene.barrier_faces[in_cube])
    to_face = cube.mean(axis=1) - np.array([232.0, 32.0, 32.0])
    assert (np.einsum("ij,ij->i", outward, to_face) > 0).all()
    assert not (tris[:, :, 0] >= 400).any()  # trigger and water brushes are not barriers


def test_spawns_become_lifted_seeds_and_spawns_inside_solids_are_dropped(tiny_bsp: Path) -> None:
    scene = load_scene(tiny_bsp)  # default: inches -> meters
    expected = np.array([[32, 32, 24], [40, 40, 24], [20, 20, 24], [10, 10, 24]]) * 0.0254 + [0, 0, 0.5]
    np.testing.assert_allclose(scene.seeds, expected)
    extra = load_scene(tiny_bsp, seeds=[(1.0, 2.0, 3.0)])
    np.testing.assert_allclose(extra.seeds[-1], [1.0, 2.0, 3.0])
    names = [e["classname"] for e in read_entities(tiny_bsp)]
    assert names[0] == "worldspawn" and names.count("info_player_deathmatch") == 2


def test_scale_converts_every_coordinate(tiny_bsp: Path) -> None:
    inches = load_scene(tiny_bsp, scale=1.0)
    meters = load_scene(tiny_bsp)
    np.testing.assert_allclose(meters.vertices, inches.vertices * 0.0254)
    np.testing.assert_array_equal(meters.faces, inches.faces)
    _, hi = meters.bounds
    assert hi[0] == pytest.approx(332 * 0.0254)  # the far edge of the flat patch


def test_patch_tessellation_matches_the_bezier_formula() -> None:
    level = 8
    points, _, tris, owner = tessellate_patches(CURVED[None], np.zeros_like(CURVED)[None], level)
    grid = points.reshape(level + 1, level + 1, 3)
    np.testing.assert_allclose(grid[[0, 0, -1, -1], [0, -1, 0, -1]], CURVED[[0, 0, -1, -1], [0, -1, 0, -1]])
    half = np.array([0.25, 0.5, 0.25])  # quadratic Bernstein weights at t = 1/2
    np.testing.assert_allclose(grid[level // 2, level // 2], np.einsum("i,j,ijc->c", half, half, CURVED))
    assert grid[level // 2, level // 2, 2] == pytest.approx(16.0)  # half the control point's lift
    assert tris.shape == (2 * level * level, 3) and (owner == 0).all()
    np.testing.assert_allclose(bernstein(level).sum(axis=1), 1.0)


def test_loading_is_deterministic(tiny_bsp: Path) -> None:
    a, b = load_scene(tiny_bsp), load_scene(tiny_bsp)
    for field_name in ("vertices", "faces", "face_class", "barrier_faces", "seeds"):
        np.testing.assert_array_equal(getattr(a, field_name), getattr(b, field_name))


def _random_convex_brush(rng: np.random.Generator, k: int) -> list[tuple[tuple[float, float, float], float]]:
    normals = rng.normal(size=(k, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    planes = [
        (tuple(float(x) for x in n), float(d)) for n, d in zip(normals, rng.uniform(20, 60, k), strict=True)
    ]
    return planes + _cube_planes((-50.0, -50.0, -50.0), (50.0, 50.0, 50.0))  # type: ignore[operator]


def _assert_same_polygons(fast: q3.BrushFaces, ref: q3.BrushFaces) -> None:
    """Same sides, same vertex cycles up to the starting vertex."""
    np.testing.assert_array_equal(fast.side, ref.side)
    np.testing.assert_array_equal(fast.counts, ref.counts)
    for poly_fast, poly_ref in zip(
        np.split(fast.vertices, np.cumsum(fast.counts)[:-1]),
        np.split(ref.vertices, np.cumsum(ref.counts)[:-1]),
        strict=True,
    ):
        shift = int(np.argmin(np.linalg.norm(poly_ref - poly_fast[0], axis=1)))
        np.testing.assert_allclose(np.roll(poly_ref, -shift, axis=0), poly_fast, atol=1e-6)


def test_brush_faces_match_the_clipping_reference() -> None:
    rng = np.random.default_rng(7)
    m = TinyMap()
    m.shader("textures/test/concrete", 0, SOLID)
    for k in (0, 1, 3, 8, 20, 60):
        m.brush(_random_convex_brush(rng, k), 0)
    planes = np.array([(n, d) for n, d in m.planes], dtype=q3.PLANE_DTYPE)
    brushes = np.array(m.brushes, dtype=q3.BRUSH_DTYPE)
    sides = np.array(m.brushsides, dtype=q3.BRUSHSIDE_DTYPE)
    fast = q3.brush_faces(planes, brushes, sides, 1e4)
    ref = q3.brush_faces_ref(planes, brushes, sides, 1e4)
    _assert_same_polygons(fast, ref)
    # every brush is closed: its polygons' vector areas sum to zero
    for b in range(len(brushes)):
        mine = (fast.side >= brushes["side"][b]) & (fast.side < brushes["side"][b] + brushes["n_sides"][b])
        total = np.zeros(3)
        starts = np.cumsum(fast.counts) - fast.counts
        for s, c in zip(starts[mine], fast.counts[mine], strict=True):
            p = fast.vertices[s : s + c]
            total += np.cross(p[1:-1] - p[0], p[2:] - p[0]).sum(axis=0)
        np.testing.assert_allclose(total, 0.0, atol=1e-6)


def test_huge_brushes_fall_back_to_clipping() -> None:
    rng = np.random.default_rng(3)
    m = TinyMap()
    m.brush(_random_convex_brush(rng, q3.ENUMERATE_MAX_SIDES), 0)
    m.brush(_random_convex_brush(rng, 4), 0)
    planes = np.array([(n, d) for n, d in m.planes], dtype=q3.PLANE_DTYPE)
    brushes = np.array(m.brushes, dtype=q3.BRUSH_DTYPE)
    sides = np.array(m.brushsides, dtype=q3.BRUSHSIDE_DTYPE)
    mixed = q3.brush_faces(planes, brushes, sides, 1e4)
    ref = q3.brush_faces_ref(planes, brushes, sides, 1e4)
    _assert_same_polygons(mixed, ref)


def test_entity_parser_handles_comments_and_rejects_garbage() -> None:
    text = '// note\n{\n"classname" "info_player_start"\n"origin" "1 2 3"\n}\n'
    assert q3.parse_entities(text) == [{"classname": "info_player_start", "origin": "1 2 3"}]
    for bad in ('{ "a" }', '{ "a" "b"', '"a" "b"', "{ junk }", "{ { } }"):
        with pytest.raises(IngestError):
            q3.parse_entities(bad)
    with pytest.raises(IngestError, match="origin"):
        q3.spawn_origins([{"classname": "info_player_deathmatch", "origin": "1 two 3"}])


def _directory(raw: bytes) -> np.ndarray:
    return np.frombuffer(raw, "<i4", 34, 8).reshape(17, 2).copy()


def _with_directory(raw: bytes, directory: np.ndarray) -> bytes:
    return raw[:8] + directory.astype("<i4").tobytes() + raw[8 + 17 * 8 :]


def _with_face_field(m: TinyMap, index: int, **values: object) -> bytes:
    m.faces[index] = {**m.faces[index], **values}
    return m.build()


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda raw: b"VBSP" + raw[4:], "magic"),
        (lambda raw: raw[:4] + struct.pack("<i", 47) + raw[8:], "version 47"),
        (lambda raw: raw[:100], "shorter than"),
        (lambda raw: raw[: len(raw) - 64], "outside"),
    ],
)
def test_corrupt_files_raise_ingest_errors(tmp_path: Path, mutate: object, message: str) -> None:
    path = tmp_path / "bad.bsp"
    path.write_bytes(mutate(tiny_map().build()))  # type: ignore[operator]
    with pytest.raises(IngestError, match=message):
        load_scene(path)


def test_lump_directory_errors(tmp_path: Path) -> None:
    raw = tiny_map().build()
    path = tmp_path / "bad.bsp"
    directory = _directory(raw)
    directory[q3.LUMP_FACES, 1] -= 4  # faces lump no longer a whole number of records
    path.write_bytes(_with_directory(raw, directory))
    with pytest.raises(IngestError, match="whole number"):
        load_scene(path)
    directory = _directory(raw)
    directory[q3.LUMP_VERTICES, 0] = len(raw) + 1000
    path.write_bytes(_with_directory(raw, directory))
    with pytest.raises(IngestError, match="outside"):
        load_scene(path)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (dict(n_vertices=10_000), "face vertices"),
        (dict(shader=99), "face shader"),
        (dict(meshvert=10_000), "face meshverts"),
        (dict(n_meshverts=5), "not triangles"),
    ],
)
def test_out_of_range_references_raise(tmp_path: Path, change: dict[str, object], message: str) -> None:
    path = tmp_path / "bad.bsp"
    path.write_bytes(_with_face_field(tiny_map(), 0, **change))
    with pytest.raises(IngestError, match=message):
        load_scene(path)


def test_bad_patch_grid_and_bad_brush_raise(tmp_path: Path) -> None:
    m = tiny_map()
    patch = next(i for i, f in enumerate(m.faces) if f["type"] == 2)
    path = tmp_path / "bad.bsp"
    path.write_bytes(_with_face_field(m, patch, size=(4, 3)))
    with pytest.raises(IngestError, match="odd"):
        load_scene(path)
    m = tiny_map()
    m.brushes[0] = (m.brushes[0][0], 500, m.brushes[0][2])
    path.write_bytes(m.build())
    with pytest.raises(IngestError, match="brush sides"):
        load_scene(path)


def test_meshvert_pointing_outside_its_face_raises(tmp_path: Path) -> None:
    m = tiny_map()
    m.meshverts[0] = 40
    path = tmp_path / "bad.bsp"
    path.write_bytes(m.build())
    with pytest.raises(IngestError, match="meshvert out of range"):
        load_scene(path)


def test_a_map_with_nothing_drawn_raises(tmp_path: Path) -> None:
    m = TinyMap()
    m.quad(_square(0.0), (0.0, 0.0, 1.0), m.shader("textures/skies/only", SKY_FLAG, SOLID))
    path = tmp_path / "sky.bsp"
    path.write_bytes(m.build())
    with pytest.raises(IngestError, match="no drawn surfaces"):
        load_scene(path)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(st.integers(0, 10**9), st.integers(0, 255)), min_size=1, max_size=8))
def test_mutated_maps_load_or_raise_ingest_error(edits: list[tuple[int, int]]) -> None:
    raw = bytearray(TINY_RAW)
    for where, value in edits:
        raw[where % len(raw)] = value
    try:
        scene = q3.bsp_to_scene(q3.parse_bsp(bytes(raw)), "fuzz", q3.BspOptions())
    except IngestError:
        return
    assert np.isfinite(scene.vertices).all() and len(scene.faces) > 0


TINY_RAW = tiny_map().build()


# --- sources: .bsp paths, .pk3 archives, errors -------------------------------------------------


@pytest.fixture(scope="module")
def archive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("pk3") / "maps.pk3"
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("maps/Tiny.bsp", TINY_RAW)
        z.writestr("maps/other.bsp", TINY_RAW)
        z.writestr("levelshots/tiny.jpg", b"not a map")
    return path


def test_pk3_lists_maps_and_loads_by_name_or_member(archive: Path, tiny_bsp: Path) -> None:
    assert list_pk3_maps(archive) == ["other", "tiny"]
    reference = load_scene(tiny_bsp)
    for scene in (
        load_scene(archive, map_name="tiny"),
        load_scene(archive, map_name="maps/TINY.bsp"),
        load_scene(f"{archive}:maps/Tiny.bsp"),
    ):
        assert scene.name == "Tiny"
        np.testing.assert_array_equal(scene.faces, reference.faces)
        np.testing.assert_array_equal(scene.vertices, reference.vertices)
    assert read_entities(archive, map_name="other")[0]["classname"] == "worldspawn"


def test_pk3_with_one_map_needs_no_name(tmp_path: Path) -> None:
    path = tmp_path / "one.pk3"
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("maps/solo.bsp", TINY_RAW)
    assert load_scene(path).name == "solo"


def test_source_errors_are_clear(archive: Path, tmp_path: Path, tiny_bsp: Path) -> None:
    with pytest.raises(IngestError, match=r"choose one.*other, tiny"):
        load_scene(archive)
    with pytest.raises(IngestError, match=r"'nope' is not in .*other, tiny"):
        load_scene(archive, map_name="nope")
    with pytest.raises(IngestError, match="not found"):
        load_scene(tmp_path / "missing.bsp")
    with pytest.raises(IngestError, match="not found"):
        load_scene(tmp_path / "missing.pk3:maps/x.bsp")
    (tmp_path / "scene.fbx").write_bytes(b"x")
    with pytest.raises(IngestError, match=r"unknown scene format '\.fbx'"):
        load_scene(tmp_path / "scene.fbx")
    (tmp_path / "broken.pk3").write_bytes(b"PK\x03\x04 definitely not a zip")
    with pytest.raises(IngestError, match="not a readable pk3"):
        load_scene(tmp_path / "broken.pk3", map_name="x")
    with pytest.raises(IngestError, match=r"only applies to \.pk3"):
        load_scene(tiny_bsp, map_name="tiny")
    with pytest.raises(IngestError, match="positive"):
        load_scene(tiny_bsp, scale=0.0)
    assert issubclass(IngestError, ValueError)


def test_every_face_kind_is_covered_by_the_tiny_map() -> None:
    assert {f["type"] for f in tiny_map().faces} == {1, 2, 3, 4}
