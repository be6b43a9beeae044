"""Corpus build (transactional), manifest, listing and loading; the env's CLI commands."""

from __future__ import annotations

import json
import logging
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import typer
from typer.testing import CliRunner

from navi.commands import bench as cli_bench
from navi.commands import env as cli_env
from navi.commands.common import cpu_model
from navi_compiler.dag.build import build_gmdag
from navi_compiler.gmdag import Gmdag, write_gmdag
from navi_env.config import EnvConfig
from navi_env.corpus.folder import (
    DEFAULT_RANK_SCENES,
    CorpusError,
    SceneEntry,
    build_corpus,
    find_sources,
    load_corpus_folder,
    rank_share,
    read_manifest,
)
from navi_env.sim.env import SdfDagEnv
from navi_learner.config import TrainConfig

RES, VOXEL = 32, 0.5


def points() -> np.ndarray:
    i = np.arange(RES + 1, dtype=np.float64) * VOXEL
    return np.stack(np.meshgrid(i, i, i, indexing="ij"), axis=-1)


def room(height: float = 3.0) -> Gmdag:
    q = np.abs(points() - np.array([8.0, 8.0, 1.0 + height])) - np.array([7.0, 7.0, height])
    box = np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)
    return build_gmdag(
        (-box / VOXEL).astype(np.float32),
        origin=(0.0, 0.0, 0.0),
        voxel_size=VOXEL,
        bounds=((1.0, 1.0, 1.0), (15.0, 15.0, 1.0 + 2 * height)),
    )


def ball() -> Gmdag:
    d = np.linalg.norm(points() - 8.0, axis=-1) - 1.0
    return build_gmdag(
        (d / VOXEL).astype(np.float32),
        origin=(0.0, 0.0, 0.0),
        voxel_size=VOXEL,
        bounds=((0.5, 0.5, 0.5), (15.5, 15.5, 15.5)),
    )


@pytest.fixture
def sources(tmp_path: Path) -> Path:
    src = tmp_path / "src"
    src.mkdir()
    write_gmdag(room(), src / "room_a.gmdag")
    write_gmdag(room(2.5), src / "room_b.gmdag")
    write_gmdag(ball(), src / "void.gmdag")
    (src / "notes.txt").write_text("not a scene")
    return src


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_build_list_and_load(sources: Path, tmp_path: Path) -> None:
    found = find_sources(sources)
    assert [Path(s).name for s in found] == ["room_a.gmdag", "room_b.gmdag", "void.gmdag"]
    out = tmp_path / "corpus"
    manifest = build_corpus(found, out, resolution=32)
    assert [s.name for s in manifest.scenes] == ["room_a", "room_b"]
    assert len(manifest.rejected) == 1 and "void.gmdag" in manifest.rejected[0]["source"]
    assert sorted(p.name for p in out.iterdir()) == ["manifest.json", "room_a.gmdag", "room_b.gmdag"]
    entry = manifest.scenes[0]
    assert (
        entry.resolution == 32
        and entry.voxel_size == VOXEL
        and entry.bytes == (out / entry.file).stat().st_size
    )
    assert entry.qualification["verdict"] == "pass" and entry.qualification["viable_spawns"] > 0
    assert read_manifest(out) == manifest
    scenes, loaded = load_corpus_folder(out, "cpu")
    assert len(scenes) == 2 and loaded == manifest
    spawns = loaded.spawn_tensors()
    assert [s.shape[1] for s in spawns] == [3, 3] and all(s.shape[0] > 0 for s in spawns)
    env = SdfDagEnv(scenes, 4, "cpu", EnvConfig(azimuth_bins=16, elevation_bins=4), spawns=spawns)
    env.reset(seed=0)
    assert env.scene.tolist() == [0, 1, 0, 1]
    assert not list(tmp_path.glob(".corpus.*"))  # no temporary folder left behind


def test_data_parallel_ranks_load_disjoint_shares_of_the_scenes(
    sources: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Each scene records its trace cost (the env's mean steps per probe ray from its spawns), and two
    ranks take one scene each, the costlier to rank 0 (without the costs, every 2nd scene from the rank,
    with a warning); `scene` loads one scene alone."""
    out = tmp_path / "corpus"
    full = build_corpus(find_sources(sources), out, resolution=32)
    costs = [s.trace_cost() for s in full.scenes]
    assert all(1.0 <= c <= EnvConfig().trace_max_steps for c in costs) and costs[0] != costs[1]
    shares = [load_corpus_folder(out, "cpu", rank, 2, rank_scenes="share") for rank in (0, 1)]
    assert [len(scenes) for scenes, _ in shares] == [1, 1]
    first = max(range(2), key=lambda i: costs[i])
    assert [m.scenes[0] for _, m in shares] == [full.scenes[first], full.scenes[1 - first]]
    scenes, alone = load_corpus_folder(out, "cpu", scene=1)
    assert len(scenes) == 1 and alone.scenes == (full.scenes[1],)
    with pytest.raises(CorpusError, match="cannot be shared by 3 ranks"):
        load_corpus_folder(out, "cpu", 0, 3, rank_scenes="share")
    raw = json.loads((out / "manifest.json").read_text())
    del raw["scenes"][1]["qualification"]["trace_cost"]  # a manifest from before the measurement
    (out / "manifest.json").write_text(json.dumps(raw))
    with caplog.at_level(logging.WARNING, logger="navi_env.corpus.folder"):
        shares = [load_corpus_folder(out, "cpu", rank, 2, rank_scenes="share") for rank in (0, 1)]
    assert [m.scenes[0].name for _, m in shares] == ["room_a", "room_b"]  # every 2nd scene from the rank
    assert "no trace cost" in caplog.text and "navi corpus build" in caplog.text
    with pytest.raises(CorpusError, match="scene 2 alone"):
        load_corpus_folder(out, "cpu", scene=2)


def test_with_rank_scenes_all_every_rank_loads_every_scene(sources: Path, tmp_path: Path) -> None:
    """rank_scenes "all" (the default): each of 3 ranks loads both scenes of a 2-scene corpus, in
    manifest order (more ranks than scenes is no error then), and an env on it spreads its actors over
    both; an unknown value is refused by name."""
    out = tmp_path / "corpus"
    full = build_corpus(find_sources(sources), out, resolution=32)
    for rank in range(3):
        scenes, manifest = load_corpus_folder(out, "cpu", rank, 3, rank_scenes="all")
        assert manifest.scenes == full.scenes and len(scenes.infos) == 2
        assert load_corpus_folder(out, "cpu", rank, 3)[1].scenes == full.scenes  # the default
    assert TrainConfig().rank_scenes == DEFAULT_RANK_SCENES == "all"  # training's default is the loader's
    cfg = EnvConfig(azimuth_bins=16, elevation_bins=4)
    env = SdfDagEnv(scenes, 4, "cpu", cfg, spawns=manifest.spawn_tensors())
    env.reset(seed=1)
    assert sorted(set(env.scene.tolist())) == [0, 1]
    with pytest.raises(CorpusError, match="rank_scenes must be one of share, all"):
        load_corpus_folder(out, "cpu", 0, 2, rank_scenes="half")


def _entry(name: str, cost: float) -> SceneEntry:
    return SceneEntry(name, f"{name}.gmdag", name, 32, VOXEL, 1, {"verdict": "pass", "trace_cost": cost})


def test_ranks_share_the_scenes_out_by_trace_cost() -> None:
    """Dealt costliest first, there and back: the shares are disjoint, cover the corpus, differ in size
    by at most one, keep manifest order, and their mean costs spread less than taking every W-th scene;
    a manifest without costs falls back to every W-th scene."""
    costs = [8.17, 8.31, 8.74, 9.39, 7.35, 8.23, 7.36, 10.16, 6.0, 12.5, 9.0]
    scenes = [_entry(f"s{i}", c) for i, c in enumerate(costs)]

    def spread(shares: list[tuple[SceneEntry, ...]]) -> float:
        means = [sum(s.trace_cost() for s in share) / len(share) for share in shares]
        return max(means) - min(means)

    for n, world in ((8, 4), (11, 4), (5, 2), (3, 3)):
        shares = [rank_share(scenes[:n], r, world) for r in range(world)]
        names = [s.name for share in shares for s in share]
        assert sorted(names) == sorted(s.name for s in scenes[:n]) and len(set(names)) == n
        assert max(map(len, shares)) - min(map(len, shares)) <= 1
        assert all(list(share) == sorted(share, key=scenes.index) for share in shares)
        assert spread(shares) <= spread([tuple(scenes[:n][r::world]) for r in range(world)]) + 1e-9
    shares = [rank_share(scenes[:8], r, 4) for r in range(4)]
    assert [s.name for s in shares[0]] == ["s4", "s7"]  # the costliest with the cheapest
    unmeasured = [*scenes[:4], _entry("old", 0.0)]
    assert [rank_share(unmeasured, r, 2) for r in (0, 1)] == [
        tuple(unmeasured[0::2]),
        tuple(unmeasured[1::2]),
    ]


def test_a_failing_source_leaves_the_old_corpus_intact(sources: Path, tmp_path: Path) -> None:
    out = tmp_path / "corpus"
    build_corpus([sources / "room_a.gmdag"], out, resolution=32)
    before = snapshot(out)
    broken = sources / "broken.gmdag"
    data = bytearray((sources / "room_b.gmdag").read_bytes())
    data[200] ^= 0xFF  # checksum mismatch
    broken.write_bytes(bytes(data))
    with pytest.raises(CorpusError, match=r"broken\.gmdag"):
        build_corpus([sources / "room_b.gmdag", broken], out, resolution=32)
    assert snapshot(out) == before
    with pytest.raises(CorpusError, match="no scene qualified"):
        build_corpus([sources / "void.gmdag"], out, resolution=32)
    assert snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["corpus", "src"]
    build_corpus([sources / "room_b.gmdag"], out, resolution=32)  # a good build does replace it
    assert sorted(snapshot(out)) == ["manifest.json", "room_b.gmdag"]


def test_an_exception_from_progress_stops_the_build_as_it_is(sources: Path, tmp_path: Path) -> None:
    """A caller stops a build between scenes by raising from `progress` (the learner service does on a
    signal): its exception comes out unchanged, not as the scene's CorpusError, and the old corpus stays."""
    out = tmp_path / "corpus"
    build_corpus([sources / "room_a.gmdag"], out, resolution=32)
    before = snapshot(out)
    lines: list[str] = []

    def stop_after_the_first_scene(line: str) -> None:
        lines.append(line)
        if len(lines) > 2:  # "[1/2] ...: compiling", "[1/2] ...: pass", then the second scene's first line
            raise InterruptedError("stopped")

    with pytest.raises(InterruptedError, match="stopped"):
        build_corpus([sources / "room_a.gmdag", sources / "room_b.gmdag"], out, resolution=32, workers=1,
                     progress=stop_after_the_first_scene)  # fmt: skip
    assert [line.split(":")[0] for line in lines] == ["[1/2] room_a", "[1/2] room_a", "[2/2] room_b"]
    assert lines[-1].endswith("compiling " + str(sources / "room_b.gmdag"))
    assert snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["corpus", "src"]  # no work folder left


def test_mesh_sources_compile_into_a_corpus(tmp_path: Path) -> None:
    from navi_compiler.ingest.procedural import generate_corpus

    meshes = generate_corpus(tmp_path / "meshes", 2, seed=1, families=["rooms", "corridors"])
    manifest = build_corpus(meshes, tmp_path / "corpus", resolution=32)
    assert len(manifest.scenes) + len(manifest.rejected) == 2 and manifest.scenes
    assert all(s.resolution == 32 for s in manifest.scenes)


def test_sources_compiled_in_worker_processes_build_the_same_corpus(sources: Path, tmp_path: Path) -> None:
    """Two worker processes compile the same files and manifest as one process, in source order; a source
    that fails in a worker names itself and leaves the old corpus as it was."""
    from navi_compiler.ingest.procedural import generate_corpus

    meshes = generate_corpus(tmp_path / "meshes", 3, seed=2, families=["rooms", "corridors", "hall"])
    here = build_corpus(meshes, tmp_path / "here", resolution=32, workers=1)
    lines: list[str] = []
    pooled = build_corpus(meshes, tmp_path / "pooled", resolution=32, workers=2, progress=lines.append)
    assert replace(pooled, created_at="") == replace(here, created_at="")
    assert snapshot(tmp_path / "pooled").keys() == snapshot(tmp_path / "here").keys()
    for name, data in snapshot(tmp_path / "here").items():
        if name != "manifest.json":
            assert snapshot(tmp_path / "pooled")[name] == data, name
    assert lines[0] == "compiling 3 sources, 2 at a time"
    assert [line.split(":")[0] for line in lines[1:]] == [
        "[1/3] rooms_0000",
        "[2/3] corridors_0001",
        "[3/3] hall_0002",
    ]

    before = snapshot(tmp_path / "pooled")
    broken = sources / "broken.gmdag"
    data = bytearray((sources / "room_b.gmdag").read_bytes())
    data[200] ^= 0xFF  # checksum mismatch
    broken.write_bytes(bytes(data))
    with pytest.raises(CorpusError, match=r"broken\.gmdag"):
        build_corpus(
            [sources / "room_a.gmdag", broken, sources / "room_b.gmdag"], tmp_path / "pooled", 32, workers=2
        )
    assert snapshot(tmp_path / "pooled") == before
    assert not list(tmp_path.glob(".pooled.*"))


def test_a_script_without_a_main_guard_builds_with_worker_processes(sources: Path, tmp_path: Path) -> None:
    """The compile processes do not run the caller's script again: a plain script, no `__main__` guard,
    builds with workers and prints its scenes once."""
    import subprocess
    import sys

    script = tmp_path / "build.py"
    script.write_text(
        "from navi_env.corpus.folder import build_corpus\n"
        f"m = build_corpus([{str(sources / 'room_a.gmdag')!r}, {str(sources / 'room_b.gmdag')!r}], "
        f"{str(tmp_path / 'corpus')!r}, 32, workers=2)\n"
        "print('scenes', [s.name for s in m.scenes])\n"
    )
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["scenes ['room_a', 'room_b']"]


def test_compile_workers_follow_cores_memory_and_lattice(monkeypatch: pytest.MonkeyPatch) -> None:
    from navi_env.corpus import folder

    monkeypatch.setattr(folder, "_cores", lambda: 16)
    monkeypatch.setattr(folder, "_memory_bytes", lambda: int(128e9))
    assert folder.compile_workers(512, 50) == 16  # one per core: 16 x 3.5 GB fit in 128 GB
    assert folder.compile_workers(512, 50, share=4) == 4  # four builds side by side split the cores
    assert folder.compile_workers(512, 3) == 3  # never more than there are sources
    assert folder.compile_workers(128, 50) == 1  # small lattices compile here, in order
    assert folder.compile_workers(512, 1) == 1
    monkeypatch.setattr(folder, "_memory_bytes", lambda: int(10e9))
    assert folder.compile_workers(512, 50) == 2  # 10 GB holds two 512^3 compiles
    assert folder.compile_workers(256, 50) == 16  # and eight times as many at 256^3, capped by cores
    assert folder._cores() >= 1 and folder._memory_bytes() > 0  # this machine's figures can be read


def test_available_memory_honours_a_container_limit(tmp_path: Path) -> None:
    from navi_env.corpus.folder import _memory_bytes

    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal:       24683656 kB\nMemAvailable:   20000000 kB\n")
    cgroup = tmp_path / "cgroup"
    cgroup.mkdir()
    assert _memory_bytes(str(meminfo), str(cgroup)) == 20000000 * 1024  # no cgroup files: MemAvailable
    (cgroup / "memory.max").write_text("max\n")
    (cgroup / "memory.current").write_text("1000\n")
    assert _memory_bytes(str(meminfo), str(cgroup)) == 20000000 * 1024  # no limit set
    (cgroup / "memory.max").write_text(f"{8 * 2**30}\n")
    (cgroup / "memory.current").write_text(f"{2**30}\n")
    assert _memory_bytes(str(meminfo), str(cgroup)) == 7 * 2**30  # the limit less what is in use


@pytest.mark.parametrize("semantics", ["object", "surface"])
def test_slab_families_compile_qualify_and_repeat_per_seed(tmp_path: Path, semantics: str) -> None:
    """The slab families and the field at 128^3: every scene compiles and qualifies with spawns, the same
    seed builds the same files, and a surface-classed scene names only Quake 3's classes."""
    from navi_compiler.ingest.bsp import CLASS_NAMES as SURFACE_CLASS_NAMES
    from navi_env.corpus.folder import build_default_corpus

    families = ["arena", "platforms", "floating", "field"]
    a = build_default_corpus(tmp_path / "a", 128, 4, 7, families=families, semantics=semantics)
    b = build_default_corpus(tmp_path / "b", 128, 4, 7, families=families, semantics=semantics)
    names = ["arena_0000", "platforms_0001", "floating_0002", "field_0003"]
    assert [s.name for s in a.scenes] == names and not a.rejected
    for sa, sb in zip(a.scenes, b.scenes, strict=True):
        assert len(sa.spawns()) >= 4
        assert (tmp_path / "a" / sa.file).read_bytes() == (tmp_path / "b" / sb.file).read_bytes()
    corpus, _ = load_corpus_folder(tmp_path / "a", torch.device("cpu"))
    for info in corpus.infos:
        assert (info.class_names == SURFACE_CLASS_NAMES) == (semantics == "surface")


def test_a_corpus_built_in_pieces_merges_the_same_however_it_was_dealt(tmp_path: Path) -> None:
    from navi_env.corpus.folder import build_default_corpus, merge_corpora

    for name, families in (("p", ["maze", "rooms"]), ("q", ["caves"])):
        build_default_corpus(tmp_path / name, 32, 2, 3, families=families)
    kept = merge_corpora([tmp_path / "p", tmp_path / "q"], tmp_path / "kept")
    a = merge_corpora([tmp_path / "q", tmp_path / "p"], tmp_path / "a", by_name=True)
    b = merge_corpora([tmp_path / "p", tmp_path / "q"], tmp_path / "b", by_name=True)
    assert [s.name for s in kept.scenes] == ["maze_0000", "rooms_0001", "caves_0000", "caves_0001"]
    assert [s.name for s in a.scenes] == [s.name for s in b.scenes] == sorted(s.name for s in kept.scenes)
    assert [s.name for s in a.scenes] != [s.name for s in kept.scenes]
    for sa, sb in zip(a.scenes, b.scenes, strict=True):
        assert (tmp_path / "a" / sa.file).read_bytes() == (tmp_path / "b" / sb.file).read_bytes()


def test_a_corpus_records_how_its_cubes_were_fitted_and_older_ones_read_as_stale(
    sources: Path, tmp_path: Path
) -> None:
    """A new manifest carries the compiler's FIT_RULES and reads as current; a manifest written before
    the field existed reads as rules 1, stale, and so does every merge that holds it; a missing or
    broken corpus is not current either."""
    from navi_compiler.compile import FIT_RULES
    from navi_env.corpus.folder import corpus_is_current, merge_corpora, subset_corpus

    new = tmp_path / "new"
    built = build_corpus(find_sources(sources), new, resolution=32)
    assert built.fit_rules == FIT_RULES >= 2
    assert json.loads((new / "manifest.json").read_text())["fit_rules"] == FIT_RULES
    assert corpus_is_current(new)
    old = tmp_path / "old"
    build_corpus(find_sources(sources), old, resolution=32)
    raw = json.loads((old / "manifest.json").read_text())
    del raw["fit_rules"]
    (old / "manifest.json").write_text(json.dumps(raw))
    assert read_manifest(old).fit_rules == 1 and not corpus_is_current(old)
    assert merge_corpora([new, old], tmp_path / "both").fit_rules == 1
    assert not corpus_is_current(tmp_path / "both")
    assert subset_corpus(old, ["room_a"], tmp_path / "sub").fit_rules == 1
    assert merge_corpora([new, new], tmp_path / "twice").fit_rules == FIT_RULES
    assert not corpus_is_current(tmp_path / "missing")
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "manifest.json").write_text("{")
    assert not corpus_is_current(tmp_path / "broken")


def test_scenes_declare_moving_obstacles_through_sidecar_and_manifest(tmp_path: Path) -> None:
    """A mesh's sidecar "obstacles" reaches the manifest and the env: that scene gets its declared count
    and speeds, a scene that declares nothing keeps the env's default (none)."""
    import dataclasses

    from navi_compiler.ingest.procedural import generate_corpus
    from navi_compiler.ingest.sidecar import read_sidecar, sidecar_path, write_sidecar
    from navi_env.tracer import primitives as ob
    from navi_learner.envs.factory import make_env

    meshes = generate_corpus(tmp_path / "meshes", 2, seed=1, families=["hall", "hall"])
    side = sidecar_path(meshes[0])
    declared = {"count": 4.0, "speed_min": 1.0, "speed_max": 1.5}
    write_sidecar(meshes[0], dataclasses.replace(read_sidecar(side), obstacles=declared))
    manifest = build_corpus(meshes, tmp_path / "corpus", resolution=64)
    assert [s.obstacles for s in manifest.scenes] == [declared, {}]
    assert read_manifest(tmp_path / "corpus").obstacle_settings() == [declared, {}]
    env = make_env(tmp_path / "corpus", 8, "cpu", 0)
    env.reset(seed=0)
    st = env.obstacles  # type: ignore[attr-defined]
    assert st is not None and st.count == 4
    active = st.prims[..., ob.KIND] != ob.NONE  # (N, K)
    first = env.scene == 0  # type: ignore[attr-defined]
    assert bool(active[first].any()) and not bool(active[~first].any())
    speeds = st.speed.abs()[active]
    assert bool(((speeds >= 1.0 - 1e-6) & (speeds <= 1.5 + 1e-6)).all())
    bad = dataclasses.replace(manifest.scenes[0], obstacles={"speed_min": 3.0, "speed_max": 1.0})
    scenes, _ = load_corpus_folder(tmp_path / "corpus")
    with pytest.raises(ValueError, match="hall"):
        SdfDagEnv(
            scenes, 2, "cpu", EnvConfig(), manifest.spawn_tensors(), scene_obstacles=[bad.obstacles, {}]
        )
    with pytest.raises(ValueError, match="unknown obstacle settings"):
        SdfDagEnv(
            scenes, 2, "cpu", EnvConfig(), manifest.spawn_tensors(), scene_obstacles=[{"mass": 1.0}, {}]
        )


def app() -> typer.Typer:
    root = typer.Typer(pretty_exceptions_enable=False)
    root.add_typer(cli_env.app)
    root.add_typer(cli_bench.app, name="bench")
    return root


def test_cli_qualify_corpus_and_bench(sources: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    good = runner.invoke(app(), ["qualify", str(sources / "room_a.gmdag"), "--json"])
    assert good.exit_code == 0, good.output
    verdict = json.loads(good.stdout)
    assert verdict["verdict"] == "pass" and verdict["viable_spawns"] > 0 and verdict["best_starvation"] == 0.0
    assert verdict["trace_cost"] > 1.0
    text = runner.invoke(app(), ["qualify", str(sources / "room_a.gmdag")])
    assert f"trace cost {verdict['trace_cost']:.2f} steps per ray" in text.stdout
    bad = runner.invoke(app(), ["qualify", str(sources / "void.gmdag"), "--json"])
    assert bad.exit_code == 1 and json.loads(bad.stdout)["verdict"] == "fail"
    missing = runner.invoke(app(), ["qualify", str(tmp_path / "nope.gmdag")])
    assert missing.exit_code == 2 and "not found" in missing.output
    out = tmp_path / "corpus"
    built = runner.invoke(
        app(), ["corpus", "build", str(sources), "--out", str(out), "--resolution", "32", "--json"]
    )
    assert built.exit_code == 0, built.output
    assert json.loads(built.stdout)["scenes"] == 2
    listed = runner.invoke(app(), ["corpus", "list", str(out)])
    assert listed.exit_code == 0 and "room_a" in listed.stdout and "rejected" in listed.stdout
    assert listed.stdout.count("trace cost") == 2
    both = runner.invoke(app(), ["corpus", "build", str(sources), "--default", "--out", str(out)])
    assert both.exit_code == 2
    res = runner.invoke(
        app(),
        [
            "bench",
            "env",
            "--corpus",
            str(out),
            "--actors",
            "2",
            "--steps",
            "2",
            "--azimuth",
            "16",
            "--elevation",
            "4",
            "--json",
            "--record",
            str(tmp_path / "results"),
        ],
    )
    assert res.exit_code == 0, res.output
    report = json.loads(res.stdout)
    (record_file,) = (tmp_path / "results").glob("*.jsonl")  # DATE-CPU.jsonl
    (row,) = [json.loads(line) for line in record_file.read_text().splitlines()]
    assert (
        row["bench"] == "env"
        and row["command"].startswith("navi ")
        and record_file.stem.startswith(row["date"])
    )
    assert row["cpu"] == cpu_model() and row["cpu_count"] == os.cpu_count()  # the host that fed the device
    assert {k: row[k] for k in report} == report  # the printed result, whole, plus how to reproduce it
    assert report["obs_shape"] == [2, 3, 16, 4] and report["steps_per_s"] > 0
    assert set(report["ms_per_stage"]) == {"physics", "reward", "episode", "trace", "observation"}
    assert torch.tensor(list(report["ms_per_stage"].values())).ge(0).all()
