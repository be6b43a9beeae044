"""The layout keeps its promises: imports point down the layers and the sub-layers inside a package, the
architecture page names real paths, every sub-package says what it owns, and the command layer stays
light and flat."""

from __future__ import annotations

import ast
import itertools
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = (
    "navi_contracts",
    "navi_mesh",
    "navi_compiler",
    "navi_env",
    "navi_learner",
    "navi_auditor",
    "navi_bench",
    "navi",
)
"""Bottom to top: a module may import its own package and the ones before it, never one after it."""
PACKAGES = {
    "navi_contracts": ROOT / "shared/contracts/navi_contracts",
    "navi_mesh": ROOT / "shared/mesh/navi_mesh",
    "navi_compiler": ROOT / "services/compiler/navi_compiler",
    "navi_env": ROOT / "services/env/navi_env",
    "navi_learner": ROOT / "services/learner/navi_learner",
    "navi_auditor": ROOT / "services/auditor/navi_auditor",
    "navi_bench": ROOT / "benchmarks/navi_bench",
    "navi": ROOT / "navi",
}


def imported_packages(source: str) -> list[tuple[int, str]]:
    """(line, module) of every absolute import in `source`, at module level or inside functions and
    TYPE_CHECKING blocks, that names one of Navi's packages."""
    found = []
    for node in ast.walk(ast.parse(source)):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        else:
            continue
        found += [(node.lineno, name) for name in names if name.split(".")[0] in LAYERS]
    return found


def upward_imports(package: str, source: str) -> list[str]:
    """The imports of a module of `package` that point up a layer."""
    rank = LAYERS.index(package)
    return [
        f"line {line}: {name}"
        for line, name in imported_packages(source)
        if LAYERS.index(name.split(".")[0]) > rank
    ]


def test_the_checker_sees_imports_at_every_depth() -> None:
    source = (
        "import navi_contracts\n"
        "from navi_learner.ppo import train\n"
        "def f():\n    import navi_auditor.server as s\n"
        "if True:\n    from navi import cli\n"
    )
    assert upward_imports("navi_env", source) == [
        "line 2: navi_learner.ppo",
        "line 4: navi_auditor.server",
        "line 6: navi",
    ]
    assert upward_imports("navi", source) == []


@pytest.mark.parametrize("package", LAYERS)
def test_imports_point_down_the_layers(package: str) -> None:
    modules = sorted(PACKAGES[package].rglob("*.py"))
    assert modules, f"{package} has no modules at {PACKAGES[package]}"
    bad = {
        str(path.relative_to(ROOT)): up
        for path in modules
        if (up := upward_imports(package, path.read_text(encoding="utf-8")))
    }
    assert not bad, f"imports that point up a layer (order {' <- '.join(LAYERS)}): {bad}"


SUB_LAYERS = {
    "navi_env": ("config", "rays", "tracer", "space", "sim", "corpus", "ecosystem", "service"),
    "navi_learner": ("config", "engine", "envs", "serving", "ppo", "evaluation", "service"),
}
"""Bottom to top inside a package: the sub-packages and top-level modules (by stem). A module may import
its own sub-package's modules and those before it, never one after it. The package's __init__.py sits
above them all."""


def sub_layer(package: str, parts: tuple[str, ...]) -> str | None:
    """The sub-layer of `package` that a module path (its parts below the package) belongs to; None for
    the package itself."""
    if not parts or parts[0] == "__init__":
        return None
    return parts[0]


def upward_sub_imports(package: str, module: tuple[str, ...], source: str) -> list[str]:
    """The imports of `module` (its path parts below `package`, no suffix) that point up a sub-layer."""
    order = SUB_LAYERS[package]
    own = sub_layer(package, module)
    rank = len(order) if own is None else order.index(own)
    bad = []
    for line, name in imported_packages(source):
        parts = tuple(name.split("."))
        if parts[0] != package or (target := sub_layer(package, parts[1:])) is None:
            continue
        if target not in order:
            bad.append(f"line {line}: {name} (no sub-layer {target!r})")
        elif order.index(target) > rank:
            bad.append(f"line {line}: {name}")
    return bad


def test_the_sub_layer_checker_sees_upward_imports() -> None:
    source = (
        "from navi_env.config import EnvConfig\nfrom navi_env.sim.env import SdfDagEnv\nimport navi_env\n"
    )
    assert upward_sub_imports("navi_env", ("tracer", "trace"), source) == ["line 2: navi_env.sim.env"]
    assert upward_sub_imports("navi_env", ("sim", "goals"), source) == []
    assert upward_sub_imports("navi_env", ("__init__",), source) == []


@pytest.mark.parametrize("package", sorted(SUB_LAYERS))
def test_imports_point_down_the_sub_layers(package: str) -> None:
    root = PACKAGES[package]
    order = SUB_LAYERS[package]
    unplaced = sorted(
        str(path.relative_to(ROOT))
        for path in root.rglob("*.py")
        if (layer := sub_layer(package, path.relative_to(root).with_suffix("").parts)) is not None
        and layer not in order
    )
    assert not unplaced, f"modules outside the sub-layers {order}: {unplaced}"
    bad = {
        str(path.relative_to(ROOT)): up
        for path in sorted(root.rglob("*.py"))
        if (
            up := upward_sub_imports(
                package, path.relative_to(root).with_suffix("").parts, path.read_text(encoding="utf-8")
            )
        )
    }
    assert not bad, f"imports that point up a sub-layer (order {' <- '.join(order)}): {bad}"


def test_only_the_bench_command_imports_the_benchmarks() -> None:
    """Benchmark and anchor code lives in navi_bench; of the command layer only `navi bench` reaches it."""
    importers = sorted(
        str(path.relative_to(ROOT))
        for path in (ROOT / "navi").rglob("*.py")
        if any(
            name.split(".")[0] == "navi_bench"
            for _, name in imported_packages(path.read_text(encoding="utf-8"))
        )
    )
    assert importers == ["navi/commands/bench.py"]


@pytest.mark.parametrize("package", LAYERS)
def test_every_package_and_sub_package_says_what_it_owns(package: str) -> None:
    for init in sorted(PACKAGES[package].rglob("__init__.py")):
        doc = ast.get_docstring(ast.parse(init.read_text(encoding="utf-8"))) or ""
        assert len(doc.split()) >= 8, f"{init.relative_to(ROOT)} needs a docstring saying what it owns"


def expand_braces(path: str) -> list[str]:
    """`a/{b,c}.py` -> [`a/b.py`, `a/c.py`]."""
    parts = re.split(r"\{([^}]*)\}", path)
    choices = [[p] if i % 2 == 0 else p.split(",") for i, p in enumerate(parts)]
    return ["".join(combo) for combo in itertools.product(*choices)]


def named_paths(markdown: str) -> list[str]:
    """The file and folder paths a page names in backticks (anything with a slash and no spaces, URLs
    and key expressions aside)."""
    spans = re.findall(r"`([^`\s]+)`", markdown)
    return [s for s in spans if "/" in s and not s.startswith(("navi/actor", "http", "/")) and ":" not in s]


def resolves(path: str) -> bool:
    roots = [ROOT, *(p.parent for p in PACKAGES.values())]
    return any((root / path).exists() for root in roots)


def test_the_architecture_page_names_paths_that_exist() -> None:
    page = (ROOT / "docs/ARCHITECTURE.md").read_text(encoding="utf-8")
    paths = [p for span in named_paths(page) for p in expand_braces(span)]
    assert len(paths) > 60, "the page should name the data path's modules"
    missing = sorted({p for p in paths if not resolves(p)})
    assert not missing, f"docs/ARCHITECTURE.md names paths that do not exist: {missing}"


def test_the_command_layer_imports_no_heavy_packages() -> None:
    program = "import sys, navi.cli; print(sorted(m for m in ('torch', 'numpy', 'zenoh', 'fastapi') if m in sys.modules))"
    out = subprocess.run(
        [sys.executable, "-c", program], capture_output=True, text=True, timeout=120, cwd=ROOT
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]", f"`navi --help` would import {out.stdout.strip()}"


def test_commands_are_top_level_functions() -> None:
    """No function defines commands inside itself: every command group is a module-level app."""
    nested = []
    for path in sorted((ROOT / "navi").rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for outer in ast.walk(tree):
            if not isinstance(outer, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            for inner in ast.walk(outer):
                if inner is outer or not isinstance(inner, ast.FunctionDef | ast.AsyncFunctionDef):
                    continue
                for deco in inner.decorator_list:
                    call = deco.func if isinstance(deco, ast.Call) else deco
                    if isinstance(call, ast.Attribute) and call.attr in ("command", "callback"):
                        nested.append(f"{path.relative_to(ROOT)}:{inner.lineno} {inner.name} in {outer.name}")
    assert not nested, f"commands defined inside functions: {nested}"
