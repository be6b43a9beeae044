"""Installs the Navi workspace into the running interpreter's environment (`make setup` calls it).

Standard library only: it runs before anything of Navi's is installed.

1. Build tools (setuptools, pybind11, wheel).
2. torch: the one already installed is kept; only when none is installed is `--torch-spec` installed.
3. The pin: `torch==VERSION`, VERSION read from the installed distribution's metadata (what pip
   compares against), never `torch.__version__` (a run-time string that may carry a local label such
   as `+cu130` that the installed distribution does not). Every later pip call takes the pin as a
   constraint, so nothing can replace or upgrade that torch: pip fails instead.
4. The core: every workspace package in editable mode (builds the C++ extensions) and the dev tools.
   A failure here fails set-up.
5. The optional extras (Gymnasium, TorchRL, skrl, rsl_rl adapters; plots; TensorBoard), each group on its own:
   one that cannot resolve against the pinned torch is named in one line and skipped.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CORE = ["shared/contracts", "shared/mesh", "services/compiler", "services/env", "services/learner",
        "services/auditor", "benchmarks", "."]  # fmt: skip
# (package folder, extra) pairs installed after the core, each in its own pip call.
OPTIONAL = [("services/env", "gym"), ("services/env", "torchrl"), ("services/env", "skrl"),
            ("services/env", "rsl_rl"), ("services/learner", "plots"), ("services/learner", "tensorboard")]  # fmt: skip


def log(message: str) -> None:
    print(f"[navi] {message}", flush=True)


def installed_version(name: str) -> str | None:
    """The version pip knows a distribution by (its metadata), or None when it is not installed."""
    importlib.invalidate_caches()
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def pin_line(name: str = "torch") -> str:
    """`name==VERSION` from the installed distribution's metadata; raises when it is not installed."""
    version = installed_version(name)
    if version is None:
        raise RuntimeError(f"{name} is not installed in {sys.prefix}")
    return f"{name}=={version}"


def extra_requirements(package: str, extra: str, root: Path = ROOT) -> list[str]:
    """The requirements an extra of a workspace package adds, read from its pyproject.toml."""
    with open(root / package / "pyproject.toml", "rb") as f:
        project = tomllib.load(f)["project"]
    extras = project.get("optional-dependencies", {})
    if extra not in extras:
        raise KeyError(f"{package}/pyproject.toml declares no extra {extra!r}")
    # An extra naming a workspace package (navi-mesh) is part of the core already.
    return [r for r in extras[extra] if not r.startswith("navi-")]


def pip(*args: str, quiet_failure: bool = False) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q", "install", *args]
    if quiet_failure:
        return subprocess.run(command, cwd=ROOT, text=True, capture_output=True)
    done = subprocess.run(command, cwd=ROOT, text=True)
    if done.returncode != 0:
        raise SystemExit(
            f"[navi] set-up failed: `pip install {' '.join(args)}` exited {done.returncode} (pip's error above)"
            + disk_hint(Path(sys.prefix), shutil.disk_usage(sys.prefix).free)
        )
    return done


ENV_BYTES = 7 * 10**9
"""About what a new environment takes on disk, torch's CUDA build being most of it (6.7 GB measured)."""


def disk_hint(prefix: Path, free: int) -> str:
    """A second line for a failed pip call when the disk of `prefix` is nearly full, else ""."""
    if free >= 2 * 10**9:
        return ""
    return (
        f"\n[navi] the disk holding {prefix} has {free / 1e9:.2f} GB free; a new environment takes about "
        f"{ENV_BYTES / 1e9:.0f} GB (torch's CUDA build is most of it): free some space and run it again"
    )


def first_error(output: str) -> str:
    """The first line of pip's output that says what went wrong."""
    lines = [line.strip() for line in output.splitlines() if line.strip()]
    for line in lines:
        if line.startswith("ERROR:"):
            return line
    return lines[-1] if lines else "pip failed"


def install_optional(pin: Path, optional: list[tuple[str, str]], root: Path = ROOT) -> list[str]:
    """Each extra in its own pip call under the pin; one that cannot be installed is named in one line
    and skipped. Returns the names of the skipped extras."""
    skipped = []
    for package, extra in optional:
        requirements = extra_requirements(package, extra, root)
        done = pip("-c", str(pin), *requirements, quiet_failure=True)
        name = f"{Path(package).name}[{extra}]"
        if done.returncode == 0:
            log(f"installed the optional extra {name}: {' '.join(requirements)}")
        else:
            log(f"skipped the optional extra {name} (cannot resolve against {pin.read_text().strip()}): "
                f"{first_error(done.stdout + done.stderr)}")  # fmt: skip
            skipped.append(name)
    return skipped


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--torch-spec", default="torch>=2.5", help="installed only when no torch is")
    parser.add_argument("--pin", type=Path, required=True, help="where the torch pin is written")
    parser.add_argument("--no-optional", action="store_true", help="skip the optional extras")
    args = parser.parse_args(argv)

    log("installing build tools")
    pip("setuptools>=68", "pybind11>=2.12", "wheel")
    if installed_version("torch") is None:
        log(f"installing {args.torch_spec} (no torch is installed in {sys.prefix})")
        pip(args.torch_spec)
    pin = pin_line("torch")
    args.pin.parent.mkdir(parents=True, exist_ok=True)
    args.pin.write_text(pin + "\n")
    log(f"installing the workspace packages (builds the C++ extensions), keeping {pin}")
    editable = [a for p in CORE for a in ("-e", p)]
    pip("--no-build-isolation", "-c", str(args.pin), *editable, "-r", "requirements-dev.txt")
    if not args.no_optional:
        install_optional(args.pin, OPTIONAL)
    return 0


if __name__ == "__main__":
    sys.exit(main())
