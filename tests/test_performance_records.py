"""Every figure in docs/PERFORMANCE.md's targets table stands on a raw record: the record file it names
exists, is of the row's date and GPU, holds the commits the row names, and carries the row's figure among
its measured numbers. Every record line has the keys benchmarks/results/README.md promises."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks/results"
PERFORMANCE = ROOT / "docs/PERFORMANCE.md"
COLUMNS = ("target", "current figure", "met", "date", "GPU", "command", "anchor, same run", "record")
FIRST_NUMBER = re.compile(r"-?\d[\d,]*(\.\d+)?")


def target_rows(text: str) -> list[dict[str, str]]:
    """The targets table's rows, as column name -> cell (the header checked against COLUMNS)."""
    section = text.split("\n## Targets\n", 1)[1].split("\n## ", 1)[0]
    lines = [line for line in section.splitlines() if line.startswith("|")]
    cells = [[cell.strip() for cell in line.strip().strip("|").split("|")] for line in lines]
    assert tuple(cells[0]) == COLUMNS, f"the targets table's header changed: {cells[0]}"
    return [dict(zip(COLUMNS, row, strict=True)) for row in cells[2:]]


def numbers(value: Any) -> list[float]:
    """The numeric fields of a record, at any depth (booleans and strings are not measurements)."""
    if isinstance(value, bool):
        return []
    if isinstance(value, (int, float)):
        return [float(value)]
    if isinstance(value, dict):
        return [x for v in value.values() for x in numbers(v)]
    if isinstance(value, list):
        return [x for v in value for x in numbers(v)]
    return []


def shown_as(value: float, figure: str) -> bool:
    """Whether a measured value prints as the figure: at the figure's decimals, its magnitude as is or a
    fraction shown in percent (a slowdown of 25.0% may be recorded as 25.0 or -0.25)."""
    match = FIRST_NUMBER.search(figure.replace("\u2212", "-"))
    assert match is not None, f"no number in the figure {figure!r}"
    decimals = len(match.group(1) or ".") - 1
    shown = abs(float(match.group().replace(",", "")))
    return any(round(abs(value) * scale, decimals) == shown for scale in (1, 100))


def records(name: str) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (RESULTS / name).read_text().splitlines() if line.strip()]


def readme_benches(text: str) -> set[str]:
    """The bench names the results README lists in its `bench` item."""
    item = text.split("- `bench`:", 1)[1].split("\n- ", 1)[0]
    return set(re.findall(r"`([a-z-]+)`", item)) - {"navi", "evaluation.json"}


BENCHES = readme_benches((RESULTS / "README.md").read_text())
ROWS = target_rows(PERFORMANCE.read_text())


def test_the_helpers_read_a_figure_as_printed() -> None:
    assert shown_as(441438.0, "441,438 SPS (the lower of 2 runs)")
    assert shown_as(0.964, "96.4%") and shown_as(-0.25, "\u221225.0% (oa_dm3)")
    assert shown_as(12.903, "12.90 G rays/s") and not shown_as(12.91, "12.90 G rays/s")
    assert not shown_as(441437.0, "441,438 SPS")
    assert numbers({"a": [1, {"b": 2.5}], "ok": True, "c": "3"}) == [1.0, 2.5]


def test_the_table_has_rows_and_each_says_met_or_not() -> None:
    assert len(ROWS) >= 10
    assert {row["met"] for row in ROWS} <= {"yes", "no"}


@pytest.mark.parametrize(
    "row", ROWS, ids=[f"{i}-{row['target'].split('**')[1]}" for i, row in enumerate(ROWS)]
)
def test_each_target_figure_has_its_record(row: dict[str, str]) -> None:
    named = re.findall(r"`([^`/]+\.jsonl)`", row["record"])
    assert len(named) == 1, f"the row must name one record file: {row['record']!r}"
    name = named[0]
    assert (RESULTS / name).is_file(), f"{name} is not in benchmarks/results"
    date, gpu = name.removesuffix(".jsonl").rsplit("-", 1)
    assert date == row["date"], f"{name} is not of the row's date {row['date']}"
    row_gpu = "CPU" if row["GPU"].startswith("none") else row["GPU"]
    assert gpu in row_gpu, f"{name} is not of the row's GPU {row['GPU']!r}"
    lines = records(name)
    commits = re.findall(r"\b[0-9a-f]{7,40}\b", row["record"])
    if commits:  # the row points at the lines of these commits
        lines = [rec for rec in lines if str(rec.get("commit", "")).startswith(tuple(commits))]
        assert lines, f"{name} has no line of commit {commits}"
    measured = [value for rec in lines for value in numbers(rec)]
    assert any(shown_as(value, row["current figure"]) for value in measured), (
        f"no measured value in {name} prints as the figure {row['current figure']!r}"
    )


@pytest.mark.parametrize("path", sorted(RESULTS.glob("*.jsonl")), ids=lambda p: p.name)
def test_every_record_line_has_the_promised_keys(path: Path) -> None:
    date, gpu = path.name.removesuffix(".jsonl").rsplit("-", 1)
    for number, rec in enumerate(records(path.name), 1):
        missing = {"date", "gpu", "bench", "command"} - rec.keys()
        assert not missing, f"{path.name}:{number} lacks {sorted(missing)}"
        assert (rec["date"], rec["gpu"]) == (date, gpu), f"{path.name}:{number} is of another date or GPU"
        assert rec["bench"] in BENCHES, (
            f"{path.name}:{number}: bench {rec['bench']!r} is not in the README's list"
        )


def test_the_readme_lists_every_navi_bench_command() -> None:
    from navi.commands.bench import app

    commands = {str(command.name) for command in app.registered_commands}
    assert commands and commands <= BENCHES, f"not in the results README: {sorted(commands - BENCHES)}"
