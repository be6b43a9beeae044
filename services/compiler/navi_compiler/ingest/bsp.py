"""Quake 3 IBSP version 46 maps: parse the lumps and turn them into a `Scene` in meters.

The file is a 4-byte magic `IBSP`, an int32 version (46) and 17 lump directory entries
(int32 offset, int32 length), followed by the lumps. Every lump except the entities and the
visibility data is an array of fixed-size little-endian records, read here as numpy structured
arrays. See docs/SCENES.md for the rules that decide which surfaces are drawn.

Shapes: Sh shaders, P planes, B brushes, Bs brush sides, Vq BSP vertices, M mesh vertices,
Fq BSP faces, T triangles, S seeds.
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from navi_compiler.ingest.errors import IngestError
from navi_compiler.ingest.patches import patch_control_grids, tessellate_patches
from navi_compiler.scene import Scene

MAGIC = b"IBSP"
VERSION = 46
LUMP_COUNT = 17
HEADER_BYTES = 8 + LUMP_COUNT * 8

# Lump indices in the directory.
LUMP_ENTITIES = 0
LUMP_SHADERS = 1
LUMP_PLANES = 2
LUMP_NODES = 3
LUMP_LEAFS = 4
LUMP_LEAFFACES = 5
LUMP_LEAFBRUSHES = 6
LUMP_MODELS = 7
LUMP_BRUSHES = 8
LUMP_BRUSHSIDES = 9
LUMP_VERTICES = 10
LUMP_MESHVERTS = 11
LUMP_EFFECTS = 12
LUMP_FACES = 13
LUMP_LIGHTMAPS = 14
LUMP_LIGHTVOLS = 15
LUMP_VISDATA = 16

SHADER_DTYPE = np.dtype([("name", "S64"), ("flags", "<i4"), ("contents", "<i4")])  # 72 bytes
PLANE_DTYPE = np.dtype([("normal", "<f4", (3,)), ("dist", "<f4")])  # 16 bytes
NODE_DTYPE = np.dtype(
    [("plane", "<i4"), ("children", "<i4", (2,)), ("mins", "<i4", (3,)), ("maxs", "<i4", (3,))]
)
LEAF_DTYPE = np.dtype(
    [
        ("cluster", "<i4"),
        ("area", "<i4"),
        ("mins", "<i4", (3,)),
        ("maxs", "<i4", (3,)),
        ("leafface", "<i4"),
        ("n_leaffaces", "<i4"),
        ("leafbrush", "<i4"),
        ("n_leafbrushes", "<i4"),
    ]
)  # 48 bytes
INDEX_DTYPE = np.dtype("<i4")  # leaffaces, leafbrushes, meshverts
MODEL_DTYPE = np.dtype(
    [
        ("mins", "<f4", (3,)),
        ("maxs", "<f4", (3,)),
        ("face", "<i4"),
        ("n_faces", "<i4"),
        ("brush", "<i4"),
        ("n_brushes", "<i4"),
    ]
)  # 40 bytes
BRUSH_DTYPE = np.dtype([("side", "<i4"), ("n_sides", "<i4"), ("shader", "<i4")])  # 12 bytes
BRUSHSIDE_DTYPE = np.dtype([("plane", "<i4"), ("shader", "<i4")])  # 8 bytes
VERTEX_DTYPE = np.dtype(
    [("position", "<f4", (3,)), ("texcoord", "<f4", (2, 2)), ("normal", "<f4", (3,)), ("color", "u1", (4,))]
)  # 44 bytes
EFFECT_DTYPE = np.dtype([("name", "S64"), ("brush", "<i4"), ("unknown", "<i4")])  # 72 bytes
FACE_DTYPE = np.dtype(
    [
        ("shader", "<i4"),
        ("effect", "<i4"),
        ("type", "<i4"),
        ("vertex", "<i4"),
        ("n_vertices", "<i4"),
        ("meshvert", "<i4"),
        ("n_meshverts", "<i4"),
        ("lm_index", "<i4"),
        ("lm_start", "<i4", (2,)),
        ("lm_size", "<i4", (2,)),
        ("lm_origin", "<f4", (3,)),
        ("lm_vecs", "<f4", (2, 3)),
        ("normal", "<f4", (3,)),
        ("size", "<i4", (2,)),
    ]
)  # 104 bytes
LIGHTMAP_BYTES = 128 * 128 * 3
LIGHTVOL_BYTES = 8

FACE_POLYGON = 1
FACE_PATCH = 2
FACE_MESH = 3
FACE_BILLBOARD = 4

# Surface flags (shader `surfaceparm`s, as q3map2 writes them).
SURF_SKY = 0x4
SURF_NODRAW = 0x80
SURF_HINT = 0x100
SURF_SKIP = 0x200
SURF_NONSOLID = 0x4000
# Content flags.
CONTENTS_SOLID = 0x1
CONTENTS_LAVA = 0x8
CONTENTS_SLIME = 0x10
CONTENTS_WATER = 0x20
CONTENTS_FOG = 0x40
CONTENTS_AREAPORTAL = 0x8000
CONTENTS_PLAYERCLIP = 0x10000
CONTENTS_MONSTERCLIP = 0x20000
CONTENTS_TELEPORTER = 0x40000
CONTENTS_JUMPPAD = 0x80000
CONTENTS_CLUSTERPORTAL = 0x100000
CONTENTS_DONOTENTER = 0x200000
CONTENTS_BOTCLIP = 0x400000
CONTENTS_ORIGIN = 0x1000000
CONTENTS_TRIGGER = 0x40000000

EXCLUDED_SURFACE_FLAGS = SURF_SKY | SURF_NODRAW | SURF_HINT | SURF_SKIP | SURF_NONSOLID
EXCLUDED_CONTENTS = (
    CONTENTS_LAVA
    | CONTENTS_SLIME
    | CONTENTS_WATER
    | CONTENTS_FOG
    | CONTENTS_AREAPORTAL
    | CONTENTS_PLAYERCLIP
    | CONTENTS_MONSTERCLIP
    | CONTENTS_TELEPORTER
    | CONTENTS_JUMPPAD
    | CONTENTS_CLUSTERPORTAL
    | CONTENTS_DONOTENTER
    | CONTENTS_BOTCLIP
    | CONTENTS_ORIGIN
    | CONTENTS_TRIGGER
)
# Shader-name fallbacks: a word of the name that marks a surface as sky, or as not drawn. Some sky
# shaders carry no flags in the BSP. A word is a part of the name between '/', '_', '-', '.' or
# whitespace, less the digits at its ends (a variant number: `sky1`, `slime1`); digits inside a part
# do not split it (`blocks17slime` is a brick texture, solid in the BSP, not a slime volume).
SKY_WORDS = frozenset({"sky", "skies", "skybox", "skyportal"})
# Not drawn but solid to the fill unless also passable (e.g. caulk / nodraw solids).
HIDDEN_WORDS = frozenset({"nodraw", "caulk"})
# Not drawn and not blocking: volumes, tool brushes and player-only clips a drone flies through.
PASSABLE_WORDS = frozenset(
    {
        "clip",
        "playerclip",
        "monsterclip",
        "botclip",
        "weapclip",
        "fullclip",
        "trigger",
        "water",
        "fog",
        "lava",
        "slime",
        "hint",
        "skip",
        "areaportal",
        "clusterportal",
        "donotenter",
        "origin",
    }
)
EXCLUDED_WORDS = HIDDEN_WORDS | PASSABLE_WORDS
_WORD_SPLIT = re.compile(r"[/_\-.\s]+")
_DIGITS = "0123456789"

CLASS_NAMES = ("unknown", "floor", "wall", "ceiling", "patch")
CLASS_FLOOR = 1
CLASS_WALL = 2
CLASS_CEILING = 3
CLASS_PATCH = 4
# |normal.z| at or above this makes a surface a floor (facing up) or a ceiling (facing down).
HORIZONTAL_NZ = 0.7

# Brush geometry tolerances, in map units (and square map units).
BRUSH_EPS = 1e-3
MIN_POLYGON_AREA = 1e-3
MAX_BRUSH_SIDES = 1024  # q3map2's own limit per brush
ENUMERATE_MAX_SIDES = 64  # larger brushes are clipped (brush_faces_ref): enumeration grows as k⁴
BRUSH_CHUNK_ELEMENTS = 1 << 22  # (G, C, k) residual entries per vectorised batch

SPAWN_CLASS = re.compile(r"^(info_player_.+|team_ctf_\w*(spawn|player))$", re.IGNORECASE)


@dataclass(frozen=True)
class BspOptions:
    """How a Quake 3 map becomes a scene."""

    scale: float = 0.0254
    """Meters per map unit (Quake 3 units are inches)."""
    patch_level: int = 8
    """Subdivisions per side of each 3×3 Bézier patch (level² × 2 triangles per patch)."""
    spawn_lift: float = 0.5
    """Meters added to a spawn point's Z (spawn origins sit close to the floor)."""


@dataclass(frozen=True)
class BspData:
    """Every lump of an IBSP v46 file, as structured arrays (record dtypes above)."""

    entities: str
    shaders: np.ndarray  # (Sh,) SHADER_DTYPE
    planes: np.ndarray  # (P,) PLANE_DTYPE
    nodes: np.ndarray  # (Nn,) NODE_DTYPE
    leafs: np.ndarray  # (Nl,) LEAF_DTYPE
    leaffaces: np.ndarray  # (Nlf,) int32
    leafbrushes: np.ndarray  # (Nlb,) int32
    models: np.ndarray  # (Nm,) MODEL_DTYPE
    brushes: np.ndarray  # (B,) BRUSH_DTYPE
    brushsides: np.ndarray  # (Bs,) BRUSHSIDE_DTYPE
    vertices: np.ndarray  # (Vq,) VERTEX_DTYPE
    meshverts: np.ndarray  # (M,) int32
    effects: np.ndarray  # (Ne,) EFFECT_DTYPE
    faces: np.ndarray  # (Fq,) FACE_DTYPE
    lightmap_count: int
    lightvol_count: int
    vis_clusters: int


def _lump_bytes(raw: bytes, directory: np.ndarray, lump: int) -> bytes:
    offset, length = int(directory[lump, 0]), int(directory[lump, 1])
    if offset < 0 or length < 0 or offset + length > len(raw) or (length and offset < HEADER_BYTES):
        raise IngestError(
            f"BSP lump {lump} (offset {offset}, length {length}) lies outside the {len(raw)}-byte file"
        )
    return raw[offset : offset + length]


def _records(raw: bytes, directory: np.ndarray, lump: int, dtype: np.dtype) -> np.ndarray:
    data = _lump_bytes(raw, directory, lump)
    if len(data) % dtype.itemsize:
        raise IngestError(
            f"BSP lump {lump} is {len(data)} bytes, not a whole number of {dtype.itemsize}-byte records"
        )
    return np.frombuffer(data, dtype=dtype).copy()


def parse_bsp(raw: bytes) -> BspData:
    """Read and validate an IBSP v46 file; raises IngestError on anything malformed."""
    if len(raw) < HEADER_BYTES:
        raise IngestError(f"file is {len(raw)} bytes, shorter than the {HEADER_BYTES}-byte BSP header")
    if raw[:4] != MAGIC:
        raise IngestError(f"not a Quake 3 BSP: magic {raw[:4]!r}, expected {MAGIC!r}")
    version = int(np.frombuffer(raw, "<i4", 1, 4)[0])
    if version != VERSION:
        raise IngestError(f"unsupported BSP version {version}; only IBSP version {VERSION} (Quake 3) is read")
    directory = np.frombuffer(raw, "<i4", LUMP_COUNT * 2, 8).reshape(LUMP_COUNT, 2)  # (17, 2) offset, length
    entities = _lump_bytes(raw, directory, LUMP_ENTITIES).split(b"\0", 1)[0].decode("latin-1")
    lightmaps = _lump_bytes(raw, directory, LUMP_LIGHTMAPS)
    lightvols = _lump_bytes(raw, directory, LUMP_LIGHTVOLS)
    if len(lightmaps) % LIGHTMAP_BYTES or len(lightvols) % LIGHTVOL_BYTES:
        raise IngestError("BSP lightmap or lightvol lump is not a whole number of records")
    visdata = _lump_bytes(raw, directory, LUMP_VISDATA)
    vis_clusters = 0
    if visdata:
        if len(visdata) < 8:
            raise IngestError("BSP visdata lump is shorter than its 8-byte header")
        n_vecs, sz_vecs = (int(x) for x in np.frombuffer(visdata, "<i4", 2))
        if n_vecs < 0 or sz_vecs < 0 or 8 + n_vecs * sz_vecs > len(visdata):
            raise IngestError(f"BSP visdata declares {n_vecs}×{sz_vecs} bytes but holds {len(visdata) - 8}")
        vis_clusters = n_vecs
    data = BspData(
        entities=entities,
        shaders=_records(raw, directory, LUMP_SHADERS, SHADER_DTYPE),
        planes=_records(raw, directory, LUMP_PLANES, PLANE_DTYPE),
        nodes=_records(raw, directory, LUMP_NODES, NODE_DTYPE),
        leafs=_records(raw, directory, LUMP_LEAFS, LEAF_DTYPE),
        leaffaces=_records(raw, directory, LUMP_LEAFFACES, INDEX_DTYPE),
        leafbrushes=_records(raw, directory, LUMP_LEAFBRUSHES, INDEX_DTYPE),
        models=_records(raw, directory, LUMP_MODELS, MODEL_DTYPE),
        brushes=_records(raw, directory, LUMP_BRUSHES, BRUSH_DTYPE),
        brushsides=_records(raw, directory, LUMP_BRUSHSIDES, BRUSHSIDE_DTYPE),
        vertices=_records(raw, directory, LUMP_VERTICES, VERTEX_DTYPE),
        meshverts=_records(raw, directory, LUMP_MESHVERTS, INDEX_DTYPE),
        effects=_records(raw, directory, LUMP_EFFECTS, EFFECT_DTYPE),
        faces=_records(raw, directory, LUMP_FACES, FACE_DTYPE),
        lightmap_count=len(lightmaps) // LIGHTMAP_BYTES,
        lightvol_count=len(lightvols) // LIGHTVOL_BYTES,
        vis_clusters=vis_clusters,
    )
    _validate_references(data)
    return data


def _check_ranges(label: str, start: np.ndarray, count: np.ndarray, size: int) -> None:
    """Every [start, start + count) must lie inside [0, size)."""
    start64, count64 = start.astype(np.int64), count.astype(np.int64)  # (K,) int64 each
    bad = (start64 < 0) | (count64 < 0) | (start64 + count64 > size)  # (K,) bool
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise IngestError(
            f"BSP {label} {i} references records [{start64[i]}, {start64[i] + count64[i]}) of {size}"
        )


def _check_indices(label: str, index: np.ndarray, size: int) -> None:
    bad = (index < 0) | (index >= size)  # (K,) bool
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise IngestError(f"BSP {label} {i} references record {int(index[i])} of {size}")


def _validate_references(data: BspData) -> None:
    """Cross-lump references the scene conversion follows must stay in range."""
    faces, n_shaders = data.faces, len(data.shaders)
    if len(data.models) == 0:
        raise IngestError("BSP has no models (model 0 is the world)")
    _check_indices("face shader of face", faces["shader"], n_shaders)
    _check_ranges("face vertices of face", faces["vertex"], faces["n_vertices"], len(data.vertices))
    _check_ranges("face meshverts of face", faces["meshvert"], faces["n_meshverts"], len(data.meshverts))
    _check_ranges("model faces of model", data.models["face"], data.models["n_faces"], len(faces))
    _check_ranges("model brushes of model", data.models["brush"], data.models["n_brushes"], len(data.brushes))
    _check_ranges("brush sides of brush", data.brushes["side"], data.brushes["n_sides"], len(data.brushsides))
    _check_indices("brush shader of brush", data.brushes["shader"], n_shaders)
    _check_indices("brushside plane of side", data.brushsides["plane"], len(data.planes))
    if not (
        np.isfinite(data.vertices["position"]).all()
        and np.isfinite(data.planes["normal"]).all()
        and np.isfinite(data.planes["dist"]).all()
    ):
        raise IngestError("BSP holds non-finite vertex positions or planes")
    world = data.models[0]
    world_sides = data.brushes["n_sides"][
        int(world["brush"]) : int(world["brush"] + world["n_brushes"])
    ]  # (Bw,)
    if world_sides.size and int(world_sides.max()) > MAX_BRUSH_SIDES:
        raise IngestError(
            f"BSP world brush with {int(world_sides.max())} sides; at most {MAX_BRUSH_SIDES} are read"
        )


_TOKEN = re.compile(r'\s*(?:(\{)|(\})|"([^"]*)"|(//[^\n]*)|(\S))')


def parse_entities(text: str) -> list[dict[str, str]]:
    """The entity lump as a list of key/value dicts, in file order (later duplicate keys win)."""
    entities: list[dict[str, str]] = []
    current: dict[str, str] | None = None
    key: str | None = None
    for match in _TOKEN.finditer(text):
        open_brace, close_brace, quoted, comment, stray = match.groups()
        if comment is not None:
            continue
        if stray is not None:
            raise IngestError(f"BSP entity lump: unexpected {stray!r} at character {match.start(5)}")
        if open_brace is not None:
            if current is not None:
                raise IngestError("BSP entity lump: '{' inside an entity")
            current = {}
        elif close_brace is not None:
            if current is None or key is not None:
                raise IngestError("BSP entity lump: unbalanced '}' or a key without a value")
            entities.append(current)
            current = None
        else:
            if current is None:
                raise IngestError("BSP entity lump: a string outside an entity")
            if key is None:
                key = quoted
            else:
                current[key] = quoted
                key = None
    if current is not None:
        raise IngestError("BSP entity lump: the last entity is not closed")
    return entities


def spawn_origins(entities: list[dict[str, str]]) -> np.ndarray:
    """Origins (map units) of player spawn entities: info_player_*, team_CTF_*spawn / *player."""
    points: list[tuple[float, float, float]] = []
    for entity in entities:
        if not SPAWN_CLASS.match(entity.get("classname", "")) or "origin" not in entity:
            continue
        parts = entity["origin"].split()
        try:
            xyz = tuple(float(p) for p in parts)
        except ValueError as err:
            raise IngestError(f"BSP entity origin {entity['origin']!r} is not three numbers") from err
        if len(xyz) != 3 or not all(np.isfinite(xyz)):
            raise IngestError(f"BSP entity origin {entity['origin']!r} is not three finite numbers")
        points.append((xyz[0], xyz[1], xyz[2]))
    return np.array(points, dtype=np.float64).reshape(-1, 3)  # (S, 3) float64, map units


def _name_words(name: bytes) -> set[str]:
    """The words of a shader name: its parts between separators, leading and trailing digits dropped."""
    return {w.strip(_DIGITS) for w in _WORD_SPLIT.split(name.decode("latin-1").lower())} - {""}


@dataclass(frozen=True)
class ShaderRules:
    """Per-shader decisions, each a (Sh,) bool mask."""

    drawn: np.ndarray  # (Sh,) surfaces distances are measured to
    barrier: np.ndarray  # (Sh,) undrawn surfaces that still bound the flood fill
    blocking: np.ndarray  # (Sh,) brushes that are solid to the fill


def shader_rules(shaders: np.ndarray) -> ShaderRules:
    """Decide, per shader, what its faces and brushes become.

    Drawn: solid, and neither sky, nodraw, non-solid, liquid, fog, clip nor trigger (by surface
    flags, content flags or a name word). Blocking: solid content with no liquid / fog / clip /
    trigger / tool content flag and no passable name word (sky and caulk are blocking). Barrier:
    an undrawn face that is sky (by flag or name) or blocking (e.g. nodraw solids).
    """
    flags = shaders["flags"].astype(np.int64)  # (Sh,)
    contents = shaders["contents"].astype(np.int64)  # (Sh,)
    words = [_name_words(n) for n in shaders["name"]]
    sky_name = np.array([bool(w & SKY_WORDS) for w in words], dtype=bool)  # (Sh,)
    excluded_name = np.array([bool(w & EXCLUDED_WORDS) for w in words], dtype=bool)  # (Sh,)
    passable_name = np.array([bool(w & PASSABLE_WORDS) for w in words], dtype=bool)  # (Sh,)
    solid = (contents & CONTENTS_SOLID) != 0  # (Sh,)
    sky = ((flags & SURF_SKY) != 0) | sky_name  # (Sh,)
    blocking = solid & ((contents & EXCLUDED_CONTENTS) == 0) & ~passable_name  # (Sh,)
    excluded = (
        ~solid
        | sky
        | excluded_name
        | ((flags & EXCLUDED_SURFACE_FLAGS) != 0)
        | ((contents & EXCLUDED_CONTENTS) != 0)
    )  # (Sh,)
    return ShaderRules(drawn=~excluded, barrier=excluded & (sky | blocking), blocking=blocking)


def face_triangles(data: BspData, face_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of polygon/mesh faces: ((T, 3) int64 into data.vertices, (T,) int64 face id)."""
    faces = data.faces[face_ids]  # (K,) FACE_DTYPE
    counts = faces["n_meshverts"].astype(np.int64)  # (K,)
    if (counts % 3).any():
        bad = int(face_ids[np.flatnonzero(counts % 3)[0]])
        raise IngestError(
            f"BSP face {bad} has {int(data.faces['n_meshverts'][bad])} meshverts, not triangles"
        )
    total = int(counts.sum())
    owner = np.repeat(np.arange(len(faces)), counts)  # (3T,) index into faces
    within = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)  # (3T,) position in its face
    corner = data.meshverts[faces["meshvert"][owner].astype(np.int64) + within].astype(np.int64)  # (3T,)
    bad = (corner < 0) | (corner >= faces["n_vertices"][owner])  # (3T,) bool
    if bad.any():
        raise IngestError(
            f"BSP face {int(face_ids[owner[np.flatnonzero(bad)[0]]])} has a meshvert out of range"
        )
    index = faces["vertex"][owner].astype(np.int64) + corner  # (3T,) into data.vertices
    return index.reshape(-1, 3), face_ids[owner[::3]].astype(np.int64)


def _orient(vertices: np.ndarray, normals: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Reorder each triangle so its right-hand normal agrees with its vertices' normals: (T, 3) int64."""
    a, b, c = (vertices[tris[:, k]] for k in range(3))  # (T, 3) each
    geometric = np.cross(b - a, c - a)  # (T, 3)
    shading = normals[tris].sum(axis=1)  # (T, 3)
    flip = np.einsum("ij,ij->i", geometric, shading) < 0  # (T,) bool
    out = tris.copy()  # (T, 3) int64
    out[flip] = tris[flip][:, [0, 2, 1]]
    return out


def classify_by_normal(vertices: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Floor / wall / ceiling class id per triangle from its unit normal's Z: (T,) uint8."""
    a, b, c = (vertices[tris[:, k]] for k in range(3))  # (T, 3) each
    normal = np.cross(b - a, c - a)  # (T, 3)
    length = np.linalg.norm(normal, axis=1)  # (T,)
    nz = np.divide(normal[:, 2], length, out=np.zeros_like(length), where=length > 0)  # (T,)
    classes = np.full(len(tris), CLASS_WALL, dtype=np.uint8)  # (T,) uint8
    classes[nz >= HORIZONTAL_NZ] = CLASS_FLOOR
    classes[nz <= -HORIZONTAL_NZ] = CLASS_CEILING
    return classes


@dataclass(frozen=True)
class BrushFaces:
    """Convex polygons of brush sides, concatenated; each polygon counter-clockwise about its outward normal."""

    vertices: np.ndarray  # (Vb, 3) float64 map units, polygon after polygon
    counts: np.ndarray  # (Np,) int64 vertices per polygon, each >= 3
    side: np.ndarray  # (Np,) int64 brushside index the polygon lies on


def _unit_planes(planes: np.ndarray, plane_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (K, 3) and distances (K,) of planes normal·p = dist (zero normals stay zero)."""
    normal = planes["normal"][plane_ids].astype(np.float64)  # (K, 3)
    length = np.linalg.norm(normal, axis=-1)  # (K,)
    safe = np.where(length > 1e-9, length, 1.0)  # (K,)
    return normal / safe[..., None], planes["dist"][plane_ids].astype(np.float64) / safe


def _plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-plane axes (u, v) with u × v = normal, for unit normals (K, 3): two (K, 3) arrays."""
    helper = np.zeros_like(normal)  # (K, 3)
    use_z = np.abs(normal[:, 2]) < 0.9  # (K,)
    helper[use_z, 2] = 1.0
    helper[~use_z, 0] = 1.0
    u = np.cross(normal, helper)  # (K, 3)
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
    return u, np.cross(normal, u)


def _repeated_sides(normal: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Sides whose plane repeats an earlier side of the same brush: (G, k) bool from (G, k, 3), (G, k)."""
    same_normal = np.abs(normal[:, :, None, :] - normal[:, None, :, :]).max(axis=-1) < 1e-6  # (G, k, k)
    same_dist = np.abs(dist[:, :, None] - dist[:, None, :]) < BRUSH_EPS  # (G, k, k)
    earlier = np.tril(np.ones(normal.shape[1:2] * 2, dtype=bool), k=-1)  # (k, k) j < i
    return (same_normal & same_dist & earlier).any(axis=2)


def clip_polygon(polygon: np.ndarray, normal: np.ndarray, dist: float, eps: float) -> np.ndarray:
    """Keep the part of a convex polygon with normal·p <= dist + eps (Sutherland–Hodgman): (K', 3)."""
    side = polygon @ normal - dist  # (K,)
    if (side <= eps).all():
        return polygon
    if (side > eps).all():
        return polygon[:0]
    out: list[np.ndarray] = []
    for i in range(len(polygon)):
        p, q = polygon[i], polygon[(i + 1) % len(polygon)]
        sp, sq = side[i], side[(i + 1) % len(polygon)]
        if sp <= eps:
            out.append(p)
        if (sp <= eps) != (sq <= eps):
            t = min(max(sp / (sp - sq), 0.0), 1.0)
            out.append(p + t * (q - p))
    return np.array(out, dtype=np.float64).reshape(-1, 3)  # (K', 3)


def _polygon_area(polygon: np.ndarray) -> float:
    edges = np.cross(polygon[1:-1] - polygon[0], polygon[2:] - polygon[0])  # (K-2, 3)
    return 0.5 * float(np.linalg.norm(edges.sum(axis=0)))


def _drop_repeats(polygon: np.ndarray, eps: float) -> np.ndarray:
    """Remove vertices within eps of their predecessor (cyclically): (K', 3)."""
    gap = np.linalg.norm(polygon - np.roll(polygon, 1, axis=0), axis=1)  # (K,)
    return polygon[gap > eps] if len(polygon) > 1 else polygon


def brush_faces_ref(
    planes: np.ndarray, brushes: np.ndarray, brushsides: np.ndarray, extent: float
) -> BrushFaces:
    """Slow twin of `brush_faces`: clip a large square on each side's plane by every other side."""
    eps = BRUSH_EPS
    polygons: list[np.ndarray] = []
    sides: list[int] = []
    for brush in brushes:
        side_ids = np.arange(int(brush["side"]), int(brush["side"] + brush["n_sides"]))  # (k,)
        normal, dist = _unit_planes(planes, brushsides["plane"][side_ids])  # (k, 3), (k,)
        u, v = _plane_basis(normal)  # (k, 3) each
        repeated = _repeated_sides(normal[None], dist[None])[0]  # (k,) bool
        for i in range(len(side_ids)):
            if not normal[i].any() or repeated[i]:
                continue
            corners = np.array(
                [[1.0, -1.0], [1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0]]
            )  # (4, 2) counter-clockwise
            polygon = normal[i] * dist[i] + extent * (corners[:, :1] * u[i] + corners[:, 1:] * v[i])  # (4, 3)
            for j in range(len(side_ids)):
                if j != i and len(polygon):
                    polygon = clip_polygon(polygon, normal[j], float(dist[j]), eps)
            polygon = _drop_repeats(polygon, 10 * eps)
            if len(polygon) >= 3 and _polygon_area(polygon) > MIN_POLYGON_AREA:
                polygons.append(polygon)
                sides.append(int(side_ids[i]))
    return BrushFaces(
        vertices=np.concatenate(polygons) if polygons else np.zeros((0, 3)),
        counts=np.array([len(p) for p in polygons], dtype=np.int64),
        side=np.array(sides, dtype=np.int64),
    )


def _merge(parts: Sequence[BrushFaces]) -> BrushFaces:
    """Concatenate polygon sets and order the polygons by brushside index."""
    counts = np.concatenate([p.counts for p in parts])  # (Np,)
    side = np.concatenate([p.side for p in parts])  # (Np,)
    vertices = np.concatenate([p.vertices for p in parts])  # (Vb, 3)
    order = np.argsort(side, kind="stable")  # (Np,)
    starts = np.cumsum(counts) - counts  # (Np,)
    gather = np.repeat(starts[order], counts[order]) + (
        np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts[order]) - counts[order], counts[order])
    )  # (Vb,)
    return BrushFaces(vertices=vertices[gather], counts=counts[order], side=side[order])


def brush_faces(planes: np.ndarray, brushes: np.ndarray, brushsides: np.ndarray, extent: float) -> BrushFaces:
    """Faces of convex brushes, vectorised by vertex enumeration (huge brushes by clipping).

    A brush is the intersection of the half-spaces normal·p <= dist of its sides. Its corners are
    the intersections of three side planes that satisfy every side; the polygon of side i is the
    set of corners on plane i, ordered by angle about their centroid. Brushes are processed in
    groups of equal side count, all three-plane combinations at once. Brushes with more than
    ENUMERATE_MAX_SIDES sides go through `brush_faces_ref` (a square of half-size `extent` clipped).
    """
    big = brushes["n_sides"] > ENUMERATE_MAX_SIDES  # (B,)
    fast = _enumerate_brush_faces(planes, brushes[~big], brushsides)
    if not big.any():
        return fast
    return _merge([fast, brush_faces_ref(planes, brushes[big], brushsides, extent)])


def _enumerate_brush_faces(planes: np.ndarray, brushes: np.ndarray, brushsides: np.ndarray) -> BrushFaces:
    """Vertex-enumeration half of `brush_faces`."""
    eps = BRUSH_EPS
    out_points: list[np.ndarray] = []
    out_side: list[np.ndarray] = []
    n_sides = brushes["n_sides"].astype(np.int64)  # (B,)
    for k in np.unique(n_sides[n_sides >= 4]):
        combos = np.array(list(itertools.combinations(range(int(k)), 3)), dtype=np.int64)  # (C, 3)
        members = np.flatnonzero(n_sides == k)  # (G,)
        chunk = max(1, BRUSH_CHUNK_ELEMENTS // (len(combos) * int(k)))
        for begin in range(0, len(members), chunk):
            group = brushes[members[begin : begin + chunk]]  # (G,)
            side_ids = group["side"].astype(np.int64)[:, None] + np.arange(k)  # (G, k)
            normal, dist = _unit_planes(planes, brushsides["plane"][side_ids])  # (G, k, 3), (G, k)
            system = normal[:, combos]  # (G, C, 3, 3)
            solvable = np.abs(np.linalg.det(system)) > 1e-6  # (G, C)
            system[~solvable] = np.eye(3)
            point = np.linalg.solve(system, dist[:, combos][..., None])[..., 0]  # (G, C, 3)
            residual = point @ normal.transpose(0, 2, 1) - dist[:, None, :]  # (G, C, k)
            inside = solvable & (residual <= eps).all(axis=2)  # (G, C)
            on_side = (np.abs(residual) <= eps) & ~_repeated_sides(normal, dist)[:, None, :]  # (G, C, k)
            g, c, i = np.nonzero(inside[..., None] & on_side)  # (R,) each
            out_points.append(point[g, c])
            out_side.append(side_ids[g, i])
    if not out_points:
        return BrushFaces(np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64))
    points = np.concatenate(out_points)  # (R, 3) one row per (corner, side it lies on)
    side = np.concatenate(out_side)  # (R,)
    # Merge corners found by several plane triples: same side, same position within the tolerance.
    cell = np.round(points / (10 * eps)).astype(np.int64)  # (R, 3)
    _, first = np.unique(np.column_stack([side, cell]), axis=0, return_index=True)  # (R',)
    points, side = points[first], side[first]  # (R', 3), (R',)
    normal, _ = _unit_planes(planes, brushsides["plane"][side])  # (R', 3)
    u, v = _plane_basis(normal)  # (R', 3) each
    keys, slot, counts = np.unique(side, return_inverse=True, return_counts=True)  # (Np,), (R',), (Np,)
    centre = (
        np.stack([np.bincount(slot, points[:, d]) for d in range(3)], axis=1) / counts[:, None]
    )  # (Np, 3)
    offset = points - centre[slot]  # (R', 3)
    angle = np.arctan2(np.einsum("rd,rd->r", offset, v), np.einsum("rd,rd->r", offset, u))  # (R',)
    order = np.lexsort((angle, slot))  # (R',) polygon by polygon, counter-clockwise
    points, slot = points[order], slot[order]  # (R', 3), (R',)
    # Drop a corner that repeats its predecessor (cyclically) when rounding split a merged pair.
    starts = np.cumsum(counts) - counts  # (Np,)
    previous = np.arange(len(points)) - 1  # (R',)
    previous[starts] = starts + counts - 1
    distinct = np.linalg.norm(points - points[previous], axis=1) > 10 * eps  # (R',)
    distinct[starts[counts == 1]] = True
    points, slot = points[distinct], slot[distinct]  # (R'', 3), (R'',)
    counts = np.bincount(slot, minlength=len(keys))  # (Np,)
    fan_tris = _fan(counts, 0)  # (T, 3)
    tri_owner = np.repeat(np.arange(len(keys)), np.maximum(counts - 2, 0))  # (T,)
    a, b, c = (points[fan_tris[:, j]] for j in range(3))  # (T, 3) each
    vector_area = np.cross(b - a, c - a)  # (T, 3)
    summed = np.stack(
        [np.bincount(tri_owner, vector_area[:, d], len(keys)) for d in range(3)], axis=1
    )  # (Np, 3)
    keep = (counts >= 3) & (0.5 * np.linalg.norm(summed, axis=1) > MIN_POLYGON_AREA)  # (Np,)
    return BrushFaces(
        vertices=points[np.repeat(keep, counts)], counts=counts[keep].astype(np.int64), side=keys[keep]
    )


def _fan(counts: np.ndarray, base: int) -> np.ndarray:
    """Fan triangles of polygons stored one after another: (T, 3) int64 vertex indices offset by base."""
    counts = np.asarray(counts, dtype=np.int64)  # (Np,)
    starts = base + np.cumsum(counts) - counts  # (Np,)
    tri_counts = np.maximum(counts - 2, 0)  # (Np,)
    first = np.repeat(starts, tri_counts)  # (T,)
    k = np.arange(int(tri_counts.sum())) - np.repeat(np.cumsum(tri_counts) - tri_counts, tri_counts)  # (T,)
    return np.stack([first, first + k + 1, first + k + 2], axis=1)  # (T, 3) int64


def _inside_brushes(points: np.ndarray, data: BspData, brush_ids: np.ndarray, margin: float) -> np.ndarray:
    """Whether each point lies inside any of the brushes, deeper than `margin` map units: (S,) bool."""
    inside = np.zeros(len(points), dtype=bool)  # (S,)
    if len(points) == 0 or len(brush_ids) == 0:
        return inside
    brushes = data.brushes[brush_ids]  # (Bk,)
    sizes = brushes["n_sides"].astype(np.int64)  # (Bk,)
    keep = sizes > 0
    brushes, sizes = brushes[keep], sizes[keep]
    side_index = np.repeat(brushes["side"].astype(np.int64), sizes) + (
        np.arange(int(sizes.sum())) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    )  # (Bs_k,)
    plane = data.planes[data.brushsides["plane"][side_index]]  # (Bs_k,)
    signed = points @ plane["normal"].astype(np.float64).T - plane["dist"].astype(np.float64)  # (S, Bs_k)
    worst = np.maximum.reduceat(signed, np.cumsum(sizes) - sizes, axis=1)  # (S, Bk)
    inside |= (worst < -margin).any(axis=1)
    return inside


def _surface_triangles(data: BspData, level: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Triangles of polygon, mesh and patch faces, wound to face their vertex normals.

    Returns (vertices (V, 3) map units, triangles (T, 3) int64, face id (T,) int64, is patch (T,) bool).
    """
    positions = data.vertices["position"].astype(np.float64)  # (Vq, 3) map units
    normals = data.vertices["normal"].astype(np.float64)  # (Vq, 3)
    types = data.faces["type"]  # (Fq,)
    flat_tris, flat_face = face_triangles(
        data, np.flatnonzero((types == FACE_POLYGON) | (types == FACE_MESH))
    )
    patch_ids = np.flatnonzero(types == FACE_PATCH)  # (Kp,)
    control, control_normals, patch_face = patch_control_grids(data.faces, positions, normals, patch_ids)
    patch_vertices, patch_normals, patch_tris, patch_owner = tessellate_patches(
        control, control_normals, level
    )  # (Vp, 3), (Vp, 3), (Tp, 3), (Tp,)
    vertices = np.concatenate([positions, patch_vertices])  # (Vq + Vp, 3)
    all_normals = np.concatenate([normals, patch_normals])  # (Vq + Vp, 3)
    tris = _orient(vertices, all_normals, np.concatenate([flat_tris, patch_tris + len(positions)]))  # (T, 3)
    face = np.concatenate([flat_face, patch_face[patch_owner]])  # (T,)
    is_patch = np.concatenate([np.zeros(len(flat_tris), bool), np.ones(len(patch_tris), bool)])  # (T,)
    return vertices, tris, face, is_patch


def _spawn_seeds(data: BspData, solid_brushes: np.ndarray, options: BspOptions) -> np.ndarray:
    """Spawn origins lifted by spawn_lift, unlifted if that lands in a solid, dropped if still in one: (S, 3) m."""
    spawns = spawn_origins(parse_entities(data.entities))  # (S, 3) map units
    lifted = spawns + np.array([0.0, 0.0, options.spawn_lift / options.scale])  # (S, 3)
    lifted_bad = _inside_brushes(lifted, data, solid_brushes, 0.0)  # (S,)
    lifted[lifted_bad] = spawns[lifted_bad]
    keep = ~_inside_brushes(lifted, data, solid_brushes, 0.0)  # (S,)
    return lifted[keep] * options.scale  # (S', 3) meters


def bsp_to_scene(
    data: BspData, name: str, options: BspOptions, extra_seeds: np.ndarray | None = None
) -> Scene:
    """Turn parsed lumps into a Scene in meters (see docs/SCENES.md for the rules)."""
    if options.scale <= 0 or not np.isfinite(options.scale):
        raise IngestError(f"scale must be a positive number of meters per map unit, got {options.scale}")
    rules = shader_rules(data.shaders)
    vertices, tris, face, is_patch = _surface_triangles(
        data, options.patch_level
    )  # (V, 3), (T, 3), (T,), (T,)
    tri_shader = data.faces["shader"][face]  # (T,)
    drawn = rules.drawn[tri_shader]  # (T,) bool
    barrier = rules.barrier[tri_shader]  # (T,) bool
    classes = classify_by_normal(vertices, tris)  # (T,) uint8
    classes[is_patch] = CLASS_PATCH

    world = data.models[0]
    world_brushes = np.arange(int(world["brush"]), int(world["brush"] + world["n_brushes"]))  # (Bw,)
    solid_brushes = world_brushes[rules.blocking[data.brushes["shader"][world_brushes]]]  # (Bs,)
    extent = 2.0 * float(np.abs(np.concatenate([world["mins"], world["maxs"]])).max()) + 1024.0
    walls = brush_faces(data.planes, data.brushes[solid_brushes], data.brushsides, extent)
    brush_tris = _fan(walls.counts, len(vertices))  # (Tb, 3)
    vertices = np.concatenate([vertices, walls.vertices])  # (V + Vb, 3) map units

    drawn_tris = tris[drawn]  # (F, 3)
    barrier_tris = np.concatenate([tris[barrier], brush_tris])  # (Fb, 3)
    if len(drawn_tris) == 0:
        raise IngestError(f"map {name!r} has no drawn surfaces after the sky/nodraw/trigger rules")
    seeds = _spawn_seeds(data, solid_brushes, options)  # (S, 3) meters
    if extra_seeds is not None and len(extra_seeds):
        seeds = np.concatenate([seeds, np.asarray(extra_seeds, np.float64).reshape(-1, 3)])

    used = np.unique(np.concatenate([drawn_tris.ravel(), barrier_tris.ravel()]))  # (U,)
    remap = np.full(len(vertices), -1, dtype=np.int64)  # (V + Vb,)
    remap[used] = np.arange(len(used))
    try:
        return Scene(
            name=name,
            vertices=vertices[used] * options.scale,  # (U, 3) meters
            faces=remap[drawn_tris],
            face_class=classes[drawn],
            class_names=CLASS_NAMES,
            barrier_faces=remap[barrier_tris],
            seeds=np.ascontiguousarray(seeds, dtype=np.float64),
        )
    except ValueError as err:
        raise IngestError(f"map {name!r}: {err}") from err
