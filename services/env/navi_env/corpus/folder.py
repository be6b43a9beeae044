"""Training corpora: a folder of .gmdag scenes with a manifest, built transactionally.

Layout of a corpus folder:
  manifest.json    {"format": "navi-corpus", "version": 1, "created_at", "resolution", "fit_rules",
                    "scenes": [...], "rejected": [...]}; fit_rules: how the compiler fitted the scenes'
                    cubes (navi_compiler.compile.FIT_RULES; 1 where absent); each scene: name, file, source, resolution, voxel_size, bytes,
                    qualification (navi_env.space.qualify.Qualification as JSON, with the viable spawns
                    and the trace cost),
                    obstacles (moving obstacles it declares, from a mesh's sidecar or edited in; may be
                    absent)
  <name>.gmdag     one file per scene that passed qualification

`build_corpus` compiles (navi_compiler), checks (reads every written file back through the validating
reader) and qualifies every source into a temporary folder beside the target, and swaps it in only
when every source compiled and at least one scene qualified. Compiling runs on the CPU, one source per
core at a time where the lattice is large enough to pay for the worker processes (compile_workers);
qualifying runs in the calling process, on its device, in source order. Anything else leaves the old corpus as
it was. A scene that fails qualification is left out and listed under "rejected" with the reason.
"""

from __future__ import annotations

import contextlib
import json
import logging
import multiprocessing
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch

from navi_compiler.compile import FIT_RULES
from navi_env.space.qualify import Qualification, QualifyConfig, qualify_scene
from navi_env.tracer.scene import SceneCorpus, load_corpus

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
FORMAT = "navi-corpus"
VERSION = 1
DEFAULT_CORPUS = Path("artifacts/corpus/default")
"""Where `navi corpus build --default` and the trainer look by default."""
MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".ply", ".stl")
MAP_SUFFIXES = (".bsp", ".pk3")

Progress = Callable[[str], None]


class CorpusError(RuntimeError):
    """A corpus could not be built or read; the message says which source or file and why."""


@dataclass(frozen=True)
class SceneEntry:
    """One qualified scene of a corpus."""

    name: str  # unique within the corpus
    file: str  # file name inside the corpus folder
    source: str  # where it came from (path, or archive.pk3:maps/x.bsp)
    resolution: int  # cells per cube edge
    voxel_size: float  # meters
    bytes: int  # size of the .gmdag file
    qualification: dict[str, object]  # Qualification.to_json()
    obstacles: dict[str, float] = field(default_factory=dict)  # declared moving obstacles (SCENE_KEYS)

    def spawns(self) -> torch.Tensor:
        """Viable spawn positions (K, 3) float32 meters, best first."""
        points = self.qualification.get("spawns", [])
        return torch.tensor(points, dtype=torch.float32).reshape(-1, 3)  # (K, 3)

    def trace_cost(self) -> float:
        """Mean sphere-tracing steps per ray from the scene's spawns (qualify.trace_cost); 0.0 where the
        manifest predates the measurement."""
        cost = self.qualification.get("trace_cost", 0.0)
        return float(cost) if isinstance(cost, (int, float)) else 0.0


@dataclass(frozen=True)
class CorpusManifest:
    """The manifest of a corpus folder."""

    created_at: str
    resolution: int
    scenes: tuple[SceneEntry, ...]
    rejected: tuple[dict[str, str], ...] = field(default_factory=tuple)  # {"source", "reason"}
    fit_rules: int = FIT_RULES  # how the compiler fitted the scenes' cubes (navi_compiler.compile.FIT_RULES)

    def to_json(self) -> dict[str, object]:
        return {
            "format": FORMAT,
            "version": VERSION,
            "created_at": self.created_at,
            "resolution": self.resolution,
            "fit_rules": self.fit_rules,
            "scenes": [asdict(s) for s in self.scenes],
            "rejected": list(self.rejected),
        }

    def spawn_tensors(self) -> list[torch.Tensor]:
        """Per scene (K_s, 3) spawns, in scene order: the `spawns` argument of SdfDagEnv."""
        return [s.spawns() for s in self.scenes]

    def obstacle_settings(self) -> list[dict[str, float]]:
        """Per scene, the moving obstacles it declares (empty: none): SdfDagEnv's `scene_obstacles`."""
        return [dict(s.obstacles) for s in self.scenes]

    def summary(self) -> dict[str, object]:
        """Small JSON summary (for checkpoints and logs)."""
        return {
            "scenes": len(self.scenes),
            "rejected": len(self.rejected),
            "resolution": self.resolution,
            "bytes": sum(s.bytes for s in self.scenes),
            "names": [s.name for s in self.scenes],
        }


def corpus_is_current(corpus_dir: str | os.PathLike[str]) -> bool:
    """`corpus_dir` holds a readable corpus whose cubes were fitted under the compiler's current rules
    (FIT_RULES): what the commands that reuse a corpus folder of real maps check before reusing it."""
    try:
        return read_manifest(corpus_dir).fit_rules == FIT_RULES
    except CorpusError:
        return False


def read_manifest(corpus_dir: str | os.PathLike[str]) -> CorpusManifest:
    """Read and check `corpus_dir/manifest.json`."""
    path = Path(corpus_dir) / MANIFEST
    if not path.is_file():
        raise CorpusError(f"{corpus_dir} is not a corpus: {MANIFEST} is missing")
    try:
        raw = json.loads(path.read_text())
        if raw.get("format") != FORMAT or raw.get("version") != VERSION:
            raise CorpusError(f"{path}: not a {FORMAT} manifest of version {VERSION}")
        scenes = tuple(SceneEntry(**s) for s in raw["scenes"])
        return CorpusManifest(
            created_at=str(raw["created_at"]),
            resolution=int(raw["resolution"]),
            scenes=scenes,
            rejected=tuple(raw.get("rejected", [])),
            fit_rules=int(raw.get("fit_rules", 1)),
        )
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise CorpusError(f"{path}: malformed manifest ({exc})") from exc


def costs_recorded(scenes: Sequence[SceneEntry]) -> bool:
    """Whether every scene records its trace cost (manifests from before the measurement do not)."""
    return all(s.trace_cost() > 0.0 for s in scenes)


RANK_SCENES = ("share", "all")
"""How data-parallel ranks take a corpus's scenes: `share` (rank_share: disjoint shares, dealt by trace
cost) or `all` (every rank loads every scene)."""
DEFAULT_RANK_SCENES = "all"
"""Every rank flies every scene: each rank's actors spread over the whole corpus, so every rank's step
costs what one process's does, whatever the scenes (shares dealt by the trace cost measured at
qualification leave one rank's scenes slower in flight)."""


def rank_share(scenes: Sequence[SceneEntry], rank: int, world: int) -> tuple[SceneEntry, ...]:
    """Rank `rank`'s share of `scenes` among `world` data-parallel ranks, in manifest order.

    Every rank flies its own scenes with the same number of actors, spread evenly over them, so a
    step of the slowest rank's scenes sets the pace of all (the ranks meet at every step's
    collectives). Where every scene records its trace cost, the scenes are dealt out costliest first,
    to ranks 0, 1, ..., W - 1 and then back W - 1, ..., 0, and so on: the shares differ in size by at
    most one and their costs are close. Otherwise (a manifest from before the measurement) rank r
    takes scenes[r::W]. Either way the shares are disjoint and cover the corpus."""
    if not costs_recorded(scenes):
        return tuple(scenes[rank::world])
    order = sorted(range(len(scenes)), key=lambda i: (-scenes[i].trace_cost(), i))  # costliest first
    mine = []
    for k, i in enumerate(order):
        turn, seat = divmod(k, world)
        if (seat if turn % 2 == 0 else world - 1 - seat) == rank:
            mine.append(i)
    return tuple(scenes[i] for i in sorted(mine))


def load_corpus_folder(
    corpus_dir: str | os.PathLike[str],
    device: torch.device | str = "cpu",
    rank: int = 0,
    world: int = 1,
    scene: int | None = None,
    rank_scenes: str = DEFAULT_RANK_SCENES,
) -> tuple[SceneCorpus, CorpusManifest]:
    """Load the scenes of a corpus onto `device`, in manifest order, with its manifest.

    With world > 1 (data-parallel training) every rank loads every scene (rank_scenes "all", the default),
    or with "share" only this rank's share (rank_share), and the returned manifest lists just those.
    `scene` loads that one scene (its index in the manifest) alone. Use `manifest.spawn_tensors()` as
    SdfDagEnv's `spawns`.
    """
    root = Path(corpus_dir)
    if rank_scenes not in RANK_SCENES:
        raise CorpusError(f"rank_scenes must be one of {', '.join(RANK_SCENES)}, got {rank_scenes!r}")
    manifest = read_manifest(root)
    if not manifest.scenes:
        raise CorpusError(f"{root}: the corpus holds no scene")
    if scene is not None:
        if world > 1 or not 0 <= scene < len(manifest.scenes):
            raise CorpusError(
                f"{root}: scene {scene} alone needs one rank and 0 <= scene < {len(manifest.scenes)}"
            )
        manifest = replace(manifest, scenes=manifest.scenes[scene : scene + 1])
    elif world > 1 and rank_scenes == "share":
        if len(manifest.scenes) < world:
            raise CorpusError(
                f"{root}: {len(manifest.scenes)} scenes cannot be shared by {world} ranks (one scene each at least)"
            )
        if rank == 0 and not costs_recorded(manifest.scenes):
            log.warning(
                "%s records no trace cost for some scenes: rank r takes scenes r, r + %d, ...; "
                "`navi corpus build %s --out NEW` rebuilds it with the costs, which balance the ranks",
                root,
                world,
                root,
            )
        manifest = replace(manifest, scenes=rank_share(manifest.scenes, rank, world))
    files = []
    for s in manifest.scenes:
        path = root / s.file
        if not path.is_file() or path.stat().st_size != s.bytes:
            raise CorpusError(f"{path}: missing or not the size the manifest records ({s.bytes} bytes)")
        files.append(path)
    return load_corpus(files, device), manifest


def find_sources(src_dir: str | os.PathLike[str]) -> list[str]:
    """Scene sources under src_dir (recursive, sorted): meshes, .bsp, each map of a .pk3, and .gmdag."""
    from navi_compiler.ingest.pk3 import list_pk3_maps

    root = Path(src_dir)
    if not root.is_dir():
        raise CorpusError(f"source folder not found: {root}")
    out: list[str] = []
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        suffix = path.suffix.lower()
        if suffix == ".pk3":
            out += [f"{path}:{member}" for member in list_pk3_maps(path)]
        elif suffix in MESH_SUFFIXES or suffix in (".bsp", ".gmdag"):
            out.append(str(path))
    return out


def _scene_name(source: str, taken: set[str]) -> str:
    base = Path(source.split(":")[-1]).stem if ":" in source else Path(source).stem
    name, k = base, 2
    while name in taken:
        name, k = f"{base}_{k}", k + 1
    taken.add(name)
    return name


def _compile_one(source: str, out_path: Path, resolution: int) -> None:
    """Compile (or copy) one source to out_path, then read it back through the validating reader."""
    from navi_compiler.compile import compile_scene
    from navi_compiler.gmdag import read_gmdag, write_gmdag
    from navi_compiler.ingest import load_scene

    if source.lower().endswith(".gmdag"):
        write_gmdag(read_gmdag(source), out_path)
    else:
        gmdag, _ = compile_scene(load_scene(source), resolution=resolution)
        write_gmdag(gmdag, out_path)
    read_gmdag(out_path)


PARALLEL_MIN_RESOLUTION = 256
"""Below this lattice a source compiles in about a second, less than starting a worker process costs."""
COMPILE_BYTES_512 = 3.5e9
"""Peak resident memory of compiling one source at 512³ (3.0 GB measured on the largest OpenArena maps)."""


def _cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _memory_bytes(meminfo: str = "/proc/meminfo", cgroup: str = "/sys/fs/cgroup") -> int:
    """Memory available for new work: MemAvailable where /proc/meminfo has it (else physical memory),
    and no more than a cgroup v2 limit leaves (a container's `memory.max` less its `memory.current`)."""
    free = int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    with contextlib.suppress(OSError, ValueError), open(meminfo) as f:
        for line in f:
            if line.startswith("MemAvailable:"):
                free = int(line.split()[1]) * 1024
    with contextlib.suppress(OSError, ValueError):
        limit = Path(cgroup, "memory.max").read_text().strip()
        if limit != "max":
            free = min(free, int(limit) - int(Path(cgroup, "memory.current").read_text()))
    return max(free, 0)


def compile_workers(resolution: int, sources: int, share: int = 1) -> int:
    """How many sources to compile at once: one per core and as many as memory holds at `resolution`,
    never more than there are sources, and 1 below PARALLEL_MIN_RESOLUTION. `share` splits the machine
    between that many builds running side by side."""
    if resolution < PARALLEL_MIN_RESOLUTION or sources < 2:
        return 1
    share = max(1, share)
    per_worker = max(COMPILE_BYTES_512 * (resolution / 512) ** 3, 2.5e8)
    by_memory = int(_memory_bytes() / share // per_worker)
    return max(1, min(sources, _cores() // share, by_memory))


def _single_thread() -> None:
    """Worker start-up: one compile per process, so no process runs several threads of its own."""
    torch.set_num_threads(1)


def _compiler(workers: int) -> ProcessPoolExecutor | None:
    """The worker processes that compile the sources (None: compile in this process, one at a time).
    They are forked where the platform can (Linux): a fork starts at once and, unlike a spawned process,
    does not run the caller's main script again, so a script without a `__main__` guard builds too. The
    children compile on the CPU only, so a parent that holds a CUDA context is safe to fork."""
    if workers <= 1:
        return None
    method = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
    return ProcessPoolExecutor(workers, multiprocessing.get_context(method), initializer=_single_thread)


def _declared_obstacles(source: str) -> dict[str, float]:
    """The moving obstacles a mesh source's `.scene.json` sidecar declares (empty for other sources)."""
    path = Path(source)
    if path.suffix.lower() not in MESH_SUFFIXES:
        return {}
    from navi_compiler.ingest.sidecar import read_sidecar, sidecar_path

    side = sidecar_path(path)
    return dict(read_sidecar(side).obstacles) if side.is_file() else {}


def _build_into(
    work: Path,
    sources: Sequence[str],
    resolution: int,
    device: torch.device | str,
    qualify: QualifyConfig,
    say: Progress,
    workers: int,
) -> CorpusManifest:
    scenes: list[SceneEntry] = []
    rejected: list[dict[str, str]] = []
    taken: set[str] = set()
    names = [_scene_name(source, taken) for source in sources]
    n = len(sources)
    if workers > 1:
        say(f"compiling {n} sources, {workers} at a time")
    started = time.perf_counter()
    pool = _compiler(workers)
    compiling: list[Future[None]] = []
    try:
        if pool is not None:
            for source, name in zip(sources, names, strict=True):
                compiling.append(pool.submit(_compile_one, source, work / f"{name}.gmdag", resolution))
        for i, (source, name) in enumerate(zip(sources, names, strict=True), 1):
            path = work / f"{name}.gmdag"
            if pool is None:  # outside the try: what the progress callback raises is not the source's fault
                say(f"[{i}/{n}] {name}: compiling {source}")
            try:
                if pool is None:
                    _compile_one(source, path, resolution)
                else:
                    compiling[i - 1].result()
            except BrokenProcessPool as exc:
                raise CorpusError(
                    f"{source}: a compile process died ({exc}); where memory ran out, fewer workers"
                    " (`--workers`) need less of it"
                ) from exc
            except (OSError, ValueError, RuntimeError) as exc:
                raise CorpusError(f"{source}: {exc}") from exc
            corpus = load_corpus([path], device)
            verdict: Qualification = qualify_scene(corpus, 0, qualify)
            elapsed = "" if pool is None else f", {time.perf_counter() - started:.0f} s"
            say(f"[{i}/{n}] {name}: {verdict.verdict} ({verdict.reason}){elapsed}")
            if not verdict.passed:
                rejected.append({"source": source, "reason": verdict.reason})
                path.unlink()
                continue
            info = corpus.infos[0]
            scenes.append(
                SceneEntry(
                    name=name,
                    file=path.name,
                    source=source,
                    resolution=info.resolution,
                    voxel_size=info.voxel_size,
                    bytes=path.stat().st_size,
                    qualification=verdict.to_json(),
                    obstacles=_declared_obstacles(source),
                )
            )
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
    if not scenes:
        raise CorpusError(f"no scene qualified ({len(rejected)} rejected); the corpus would be empty")
    return CorpusManifest(
        created_at=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        resolution=resolution,
        scenes=tuple(scenes),
        rejected=tuple(rejected),
    )


def _write_manifest(work: Path, manifest: CorpusManifest) -> None:
    path = work / MANIFEST
    with open(path, "w") as f:
        json.dump(manifest.to_json(), f, indent=1)
        f.flush()
        os.fsync(f.fileno())


def replace_directory(new: Path, out: Path) -> None:
    """Put the complete folder `new` at `out`; the previous `out` is removed only after the swap."""
    old = out.with_name(f".{out.name}.old-{os.getpid()}-{time.monotonic_ns()}")
    if out.exists():
        os.replace(out, old)
    try:
        os.replace(new, out)
    except OSError:
        if old.exists():
            os.replace(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)


@contextmanager
def _transaction(out: str | os.PathLike[str], kind: str) -> Iterator[Path]:
    """A work folder beside `out`; when the block succeeds it replaces `out`, otherwise `out` is left
    untouched. The work folder is always removed."""
    target = Path(out)
    target.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{target.name}.{kind}-", dir=target.parent))
    try:
        yield work
        replace_directory(work, target)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def build_corpus(
    sources: Sequence[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    resolution: int = 512,
    device: torch.device | str = "cpu",
    qualify: QualifyConfig | None = None,
    progress: Progress | None = None,
    workers: int = 0,
) -> CorpusManifest:
    """Compile, check and qualify every source into the corpus folder `out`, transactionally; `workers`
    sources compile at once (0: compile_workers decides). An exception that `progress` raises ends the
    build as it is (a caller's way to stop it between scenes), with `out` left untouched."""
    if not sources:
        raise CorpusError("no scene sources given")
    if workers < 0:
        raise ValueError(f"workers must be >= 0 (0: one per core as memory allows), got {workers}")
    with _transaction(out, "build") as work:
        manifest = _build_into(
            work,
            [str(s) for s in sources],
            resolution,
            device,
            qualify or QualifyConfig(),
            progress or (lambda line: None),
            workers or compile_workers(resolution, len(sources)),
        )
        _write_manifest(work, manifest)
    return manifest


def merge_corpora(
    parts: Sequence[str | os.PathLike[str]], out: str | os.PathLike[str], by_name: bool = False
) -> CorpusManifest:
    """One corpus folder `out` holding every scene of the corpus folders `parts` (copied, in order, or
    ordered by name with `by_name`; a repeated name gets a suffix), transactionally like build_corpus. The
    resolution recorded is the first part's; scenes keep their own. Scene order decides which actors fly
    which scene, so a corpus built in pieces in parallel is merged `by_name` to be the same however it
    was dealt."""
    if not parts:
        raise CorpusError("no corpus to merge")
    with _transaction(out, "merge") as work:
        scenes: list[SceneEntry] = []
        rejected: list[dict[str, str]] = []
        taken: set[str] = set()
        resolution = 0
        fit_rules = FIT_RULES
        for part in parts:
            manifest = read_manifest(part)
            resolution = resolution or manifest.resolution
            fit_rules = min(fit_rules, manifest.fit_rules)
            rejected += manifest.rejected
            for scene in manifest.scenes:
                name = _scene_name(scene.name, taken)
                shutil.copyfile(Path(part) / scene.file, work / f"{name}.gmdag")
                scenes.append(replace(scene, name=name, file=f"{name}.gmdag"))
        if by_name:
            scenes.sort(key=lambda scene: scene.name)
        merged = CorpusManifest(
            created_at=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            resolution=resolution,
            scenes=tuple(scenes),
            rejected=tuple(rejected),
            fit_rules=fit_rules,
        )
        _write_manifest(work, merged)
    return merged


def subset_corpus(
    corpus: str | os.PathLike[str], names: Sequence[str], out: str | os.PathLike[str]
) -> CorpusManifest:
    """A corpus folder `out` holding the scenes of `corpus` named in `names` (copied, in the corpus's
    order), transactionally like build_corpus; CorpusError when a name is not in it."""
    manifest = read_manifest(corpus)
    missing = sorted(set(names) - {s.name for s in manifest.scenes})
    if missing:
        raise CorpusError(f"{corpus} has no scenes named {', '.join(missing)}")
    keep = tuple(s for s in manifest.scenes if s.name in set(names))
    with _transaction(out, "subset") as work:
        for scene in keep:
            shutil.copyfile(Path(corpus) / scene.file, work / scene.file)
        sub = replace(
            manifest, created_at=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), scenes=keep, rejected=()
        )
        _write_manifest(work, sub)
    return sub


def build_default_corpus(
    out: str | os.PathLike[str],
    resolution: int = 512,
    count: int = 16,
    seed: int = 0,
    device: torch.device | str = "cpu",
    progress: Progress | None = None,
    families: Sequence[str] | None = None,
    semantics: str = "object",
    workers: int = 0,
) -> CorpusManifest:
    """Generate `count` procedural scenes (navi_compiler.ingest.procedural: `families` cycled, the default
    families when None, face classes by `semantics`) and build them into the corpus `out` (`workers` as
    build_corpus takes it)."""
    from navi_compiler.ingest.procedural import generate_corpus

    target = Path(out)
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".{target.name}.sources-", dir=target.parent) as tmp:
        meshes = generate_corpus(tmp, count, seed, families=families, semantics=semantics)
        return build_corpus(meshes, target, resolution, device, progress=progress, workers=workers)
