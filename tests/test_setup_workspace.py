"""Set-up keeps the torch that is installed: deploy/setup_workspace.py pins it by the version pip knows
it by (the distribution's metadata), which pip then accepts as satisfied, while a pin written from the
run-time `torch.__version__` (which may carry a `+cu130` label the metadata lacks) matches nothing.

The installed torch here is a stand-in distribution on PYTHONPATH (a METADATA file and a module), so the
check needs no index and no GPU; pip itself is asked, in a dry run, whether the pin is satisfied."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "deploy" / "setup_workspace.py"


def fake_torch(site: Path, metadata_version: str, runtime_version: str) -> None:
    """A torch distribution whose metadata says `metadata_version` and whose module says `runtime_version`."""
    info = site / f"torch-{metadata_version}.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: torch\nVersion: {metadata_version}\n")
    (info / "INSTALLER").write_text("pip\n")
    (info / "RECORD").write_text("")
    (site / "torch").mkdir()
    (site / "torch" / "__init__.py").write_text(f"__version__ = {runtime_version!r}\n")


def isolated_env(site: Path) -> dict[str, str]:
    """No pip configuration of this machine (index, find-links, constraints): only the stand-in counts."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PIP_")}
    env.update(PYTHONPATH=str(site), PIP_CONFIG_FILE=os.devnull, PIP_NO_INDEX="1")
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    return env


def run_python(code: str, env: dict[str, str]) -> str:
    return subprocess.run(
        [sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True
    ).stdout.strip()


def pip_accepts(pin: str, tmp_path: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """pip's dry run of `torch>=2.5` under the pin as a constraint: satisfied by the installed torch, or not."""
    constraint = tmp_path / "pin.txt"
    constraint.write_text(pin + "\n")
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--dry-run",
            "--no-deps",
            "-c",
            str(constraint),
            "torch>=2.5",
        ],
        env=env,
        capture_output=True,
        text=True,
    )


PIN_CODE = f"import sys; sys.path.insert(0, {str(SCRIPT.parent)!r}); import setup_workspace; print(setup_workspace.pin_line())"


@pytest.mark.parametrize(
    ("metadata_version", "runtime_version"),
    [
        ("2.9.0", "2.9.0+cu130"),  # PyPI's CUDA builds: the label only at run time
        ("2.9.0+cu130", "2.9.0+cu130"),  # a wheel from a PyTorch index: the label in the metadata too
        ("2.9.0", "2.9.0"),  # a plain build
    ],
)
def test_the_pin_is_the_version_pip_knows(
    metadata_version: str, runtime_version: str, tmp_path: Path
) -> None:
    site = tmp_path / "site"
    fake_torch(site, metadata_version, runtime_version)
    env = isolated_env(site)
    assert run_python("import torch; print(torch.__version__)", env) == runtime_version
    pin = run_python(PIN_CODE, env)
    assert pin == f"torch=={metadata_version}"
    kept = pip_accepts(pin, tmp_path, env)
    assert kept.returncode == 0, kept.stderr
    assert "Requirement already satisfied: torch" in kept.stdout
    assert "Would install" not in kept.stdout


def test_a_pin_from_the_runtime_version_fails_where_the_labels_differ(tmp_path: Path) -> None:
    """The fault the metadata pin avoids: `torch==2.9.0+cu130` asks pip for a torch it does not have."""
    site = tmp_path / "site"
    fake_torch(site, "2.9.0", "2.9.0+cu130")
    env = isolated_env(site)
    broken = "torch==" + run_python("import torch; print(torch.__version__)", env)
    refused = pip_accepts(broken, tmp_path, env)
    assert refused.returncode != 0
    assert "torch" in refused.stderr


def test_without_torch_the_pin_says_so(tmp_path: Path) -> None:
    env = isolated_env(tmp_path)  # an empty PYTHONPATH entry: the interpreter's own torch may be there
    code = (
        f"import sys; sys.path.insert(0, {str(SCRIPT.parent)!r}); import setup_workspace;"
        "print(setup_workspace.pin_line('navi-no-such-distribution'))"
    )
    failed = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert failed.returncode != 0
    assert "navi-no-such-distribution is not installed" in failed.stderr


def test_every_optional_extra_is_declared_by_its_package() -> None:
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        import setup_workspace
    finally:
        sys.path.remove(str(SCRIPT.parent))
    for package, extra in setup_workspace.OPTIONAL:
        requirements = setup_workspace.extra_requirements(package, extra)
        assert requirements, f"{package}[{extra}] adds no requirement"
        assert not any(r.startswith("torch") and not r.startswith("torchrl") for r in requirements)
    with pytest.raises(KeyError, match="no extra"):
        setup_workspace.extra_requirements("services/env", "no-such-extra")


def test_a_failing_extra_is_reported_in_one_line() -> None:
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        import setup_workspace
    finally:
        sys.path.remove(str(SCRIPT.parent))
    output = (
        "Collecting x\nERROR: Cannot install torchrl because these package versions have conflicting "
        "dependencies.\n    torchrl 0.14.1 depends on torch>=2.1.0\n"
    )
    assert setup_workspace.first_error(output).startswith("ERROR: Cannot install torchrl")


def test_a_failed_install_on_a_full_disk_says_how_much_is_free_and_needed() -> None:
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        import setup_workspace
    finally:
        sys.path.remove(str(SCRIPT.parent))
    hint = setup_workspace.disk_hint(Path("/venv"), 300 * 10**6)
    assert "/venv has 0.30 GB free" in hint and "about 7 GB" in hint
    assert setup_workspace.disk_hint(Path("/venv"), 50 * 10**9) == ""


def test_an_extra_that_cannot_resolve_is_skipped_in_one_line_and_set_up_goes_on(tmp_path: Path) -> None:
    """Real pip, no index: an extra naming a package nobody has is skipped with one line; the next extra,
    whose requirement is already installed, still goes in."""
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "pyproject.toml").write_text(
        '[project]\nname = "x"\nversion = "0"\n[project.optional-dependencies]\n'
        'broken = ["nosuchpackage-anywhere-navi>=99"]\nfine = ["pytest>=1"]\n'
    )
    pin = tmp_path / "pin.txt"
    pin.write_text("torch==2.9.0\n")
    code = (
        f"import sys; sys.path.insert(0, {str(SCRIPT.parent)!r}); import setup_workspace as s; from pathlib import Path;"
        f"print(s.install_optional(Path({str(pin)!r}), [('pkg', 'broken'), ('pkg', 'fine')], Path({str(tmp_path)!r})))"
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith("PIP_")}
    env.update(PIP_CONFIG_FILE=os.devnull, PIP_NO_INDEX="1")
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.strip().splitlines()
    skipped = [line for line in lines if "skipped the optional extra" in line]
    assert len(skipped) == 1 and skipped[0].startswith("[navi] skipped the optional extra pkg[broken]")
    assert "cannot resolve against torch==2.9.0" in skipped[0] and "nosuchpackage-anywhere-navi" in skipped[0]
    assert any(line.startswith("[navi] installed the optional extra pkg[fine]") for line in lines)
    assert lines[-1] == "['pkg[broken]']"
