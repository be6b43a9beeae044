"""What every command group shares: one-line errors, device and choice checks, the options several groups
take, and the benchmark records (`--record DIR`). Module-level imports: typer and the standard
library only, so `navi --help` stays fast."""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Annotated, Any

import typer

MODELS_DIR = Path("artifacts/models")
DEFAULT_CORPUS = Path("artifacts/corpus/default")
UNSEEN_CORPUS = Path("artifacts/corpus/unseen")

EnvOpt = Annotated[str, typer.Option("--env", help="Environment: sdfdag (the drone env) or toy (tests).")]
TaskOpt = Annotated[
    str,
    typer.Option(
        "--task",
        help="What episodes ask of the drone: explore, or pointgoal (reach a goal; docs/TASKS.md).",
    ),
]
CorpusOpt = Annotated[Path | None, typer.Option("--corpus", help="Corpus folder of .gmdag scenes.")]
DeviceOpt = Annotated[str, typer.Option("--device", help="Torch device: auto, cpu, cuda, cuda:N.")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Seed for torch and the environment.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print one JSON object.")]
ResumeOpt = Annotated[
    Path | None, typer.Option("--checkpoint", help="Training: resume from this checkpoint.")
]
RecordOpt = Annotated[
    Path | None,
    typer.Option(
        "--record",
        help="Also append the result as one JSON line to DIR/DATE-GPU.jsonl (with the date, the device, "
        "the git commit and the command line), e.g. --record benchmarks/results.",
    ),
]


def fail(message: str) -> typer.Exit:
    """Print a one-line error to stderr; the caller raises the returned Exit(2)."""
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(2)


def pick_device(device: str) -> str:
    """'auto' -> cuda when available, else cpu; anything else is checked."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise fail(f"device {device} requested but CUDA is not available")
    if not (device == "cpu" or device.startswith("cuda")):
        raise fail(f"unknown device {device!r}; use auto, cpu, cuda or cuda:N")
    return device


def check_choice(value: str, choices: tuple[str, ...], what: str) -> str:
    """Validate an enumerated option."""
    if value not in choices:
        raise typer.BadParameter(f"{what} must be one of {', '.join(choices)}, got {value!r}")
    return value


def device_name(device: str) -> str:
    """A short name for the machine a benchmark ran on: the GPU's model (H100, H200, ...) for a CUDA device,
    else CPU."""
    if device.startswith("cuda"):
        import torch

        name = torch.cuda.get_device_name(torch.device(device))
        for word in name.replace("-", " ").split():
            if any(c.isdigit() for c in word) and word[0].isalpha():
                return word
        return name.replace(" ", "_")
    return "CPU"


def cpu_model(cpuinfo: str | None = None) -> str:
    """The host's processor as /proc/cpuinfo names it (its first "model name"), else platform.processor(),
    else "unknown". The same GPU can be fed by slower or faster host CPUs: a record names both."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace")
        except OSError:
            cpuinfo = ""
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "model name" and value.strip():
            return value.strip()
    return platform.processor() or "unknown"


def record_result(result: dict[str, Any], bench: str, device: str, folder: Path) -> Path:
    """Append `result` to folder/DATE-GPU.jsonl as one line, with the date, the machine, the command line
    and the commit that reproduce it (docs/PERFORMANCE.md reads these records)."""
    from navi import __version__, git_commit

    day = time.strftime("%Y-%m-%d")
    machine = device_name(device)
    row = {
        "date": day,
        "gpu": machine,
        "bench": bench,
        "command": "navi " + " ".join(sys.argv[1:]),
        "commit": git_commit(),
        "navi": __version__,
        "python": platform.python_version(),
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        **result,
    }
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{day}-{machine}.jsonl"
    with path.open("a", encoding="utf-8") as out:
        out.write(json.dumps(row, default=str) + "\n")
    typer.echo(f"recorded in {path}", err=True)
    return path
