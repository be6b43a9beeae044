"""A training run's folder, logs, metrics, manifest, progress line and final report.

artifacts/runs/<run_id>/{logs,metrics,manifests,checkpoints,reports}: rotating text logs, metrics as
JSONL (always) and TensorBoard scalars (when tensorboard is installed), a manifest JSON, checkpoints,
and a markdown report with a PNG plot of reward and SPS (when matplotlib is installed).
"""

from __future__ import annotations

import json
import logging
import secrets
import sys
from collections.abc import Callable
from datetime import UTC, datetime
from logging.handlers import RotatingFileHandler
from pathlib import Path
from typing import Any

from navi_learner.serving.checkpoint import atomic_write, code_version, utc_now

SUBDIRS = ("logs", "metrics", "manifests", "checkpoints", "reports")


def new_run_id() -> str:
    """UTC timestamp plus 6 random hex digits, e.g. 20261122-201530-3fa2c1."""
    return f"{datetime.now(UTC):%Y%m%d-%H%M%S}-{secrets.token_hex(3)}"


class RunFiles:
    """Owns the files of one run; `log_metrics` fans a row out to JSONL, TensorBoard and a callback.

    With write=False (the ranks other than 0 of a data-parallel run) nothing is written: no folder, log
    file, metrics, TensorBoard, manifest or report; rows still reach the callback."""

    def __init__(
        self,
        root: Path,
        run_id: str,
        on_log: Callable[[str, dict[str, float]], None] | None = None,
        write: bool = True,
    ) -> None:
        self.root, self.run_id, self.on_log, self.write = Path(root), run_id, on_log, write
        if write:
            for sub in SUBDIRS:
                (self.root / sub).mkdir(parents=True, exist_ok=True)
        self.metrics_path = self.root / "metrics" / "metrics.jsonl"
        self.checkpoints = self.root / "checkpoints"
        self.rows: list[dict[str, float]] = []
        self.logger = logging.getLogger(f"navi_learner.run.{run_id}")
        self.logger.setLevel(logging.INFO)
        self.logger.propagate = False
        self.tb: Any = None
        if not write:
            self.logger.addHandler(logging.NullHandler())
            return
        handler = RotatingFileHandler(self.root / "logs" / "train.log", maxBytes=10 * 2**20, backupCount=5)
        handler.setFormatter(logging.Formatter(f"%(asctime)s %(levelname)s run={run_id} %(message)s"))
        self.logger.addHandler(handler)
        self.tb = self._tensorboard()

    def _tensorboard(self) -> Any:
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            self.logger.info("tensorboard is not installed: metrics go to JSONL only")
            return None
        return SummaryWriter(str(self.root / "logs" / "tensorboard"))

    def write_manifest(self, name: str, data: dict[str, Any]) -> Path:
        """manifests/<name>.json with run_id, code version and time stamped in."""
        path = self.root / "manifests" / f"{name}.json"
        if not self.write:
            return path
        body = {"run_id": self.run_id, "code_version": code_version(), "written_at": utc_now(), **data}
        text = json.dumps(body, indent=2, sort_keys=True, default=str).encode()
        atomic_write(path, lambda f: f.write(text))
        return path

    def log_metrics(self, row: dict[str, float]) -> None:
        """Append a metrics row (must hold 'step')."""
        self.rows.append(row)
        if self.write:
            with self.metrics_path.open("a") as f:
                f.write(json.dumps({"run_id": self.run_id, **row}) + "\n")
        if self.tb is not None:
            for key, value in row.items():
                if key != "step":
                    self.tb.add_scalar(key, value, int(row["step"]))
        self.logger.info(" ".join(f"{k}={v:.4g}" for k, v in row.items()))
        if self.on_log is not None:
            self.on_log(self.run_id, row)

    def close(self) -> None:
        """Flush and close TensorBoard and the log handlers."""
        if self.tb is not None:
            self.tb.close()
        for handler in list(self.logger.handlers):
            handler.close()
            self.logger.removeHandler(handler)


class Progress:
    """A one-line progress bar on stderr (steps, SPS, ETA, extra text), shown only on a terminal unless
    `enabled` says otherwise. With a time limit the bar and the ETA follow whichever budget ends first."""

    def __init__(self, total: int, enabled: bool | None = None, time_limit_s: float = 0.0) -> None:
        self.total = total
        self.time_limit_s = time_limit_s
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self.start_step: int | None = None

    def eta_s(self, step: int, sps: float, elapsed_s: float) -> float:
        """Seconds left: the step budget at the current SPS, or the time limit, whichever ends first."""
        left = (self.total - step) / sps if sps > 0 else float("inf")
        if self.time_limit_s > 0:
            left = min(left, self.time_limit_s - elapsed_s)
        return max(left, 0.0)

    def update(self, step: int, sps: float, elapsed_s: float = 0.0, extra: str = "") -> None:
        if not self.enabled:
            return
        frac = min(1.0, step / max(self.total, 1))
        if self.time_limit_s > 0:
            frac = max(frac, min(1.0, elapsed_s / self.time_limit_s))
        bar = "#" * int(30 * frac) + "-" * (30 - int(30 * frac))
        eta = self.eta_s(step, sps, elapsed_s)
        clock = f"{int(eta) // 60}:{int(eta) % 60:02d}" if eta < 1e7 else "--"
        sys.stderr.write(f"\r[{bar}] {step:,} steps  {sps:,.0f} SPS  ETA {clock}  {extra}   ")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")
            sys.stderr.flush()


def plot_png(rows: list[dict[str, float]], path: Path) -> str | None:
    """Reward and SPS over steps as a PNG; returns None when written, else why not."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return "matplotlib is not installed, so no plot was drawn (pip install matplotlib)"
    steps = [r["step"] for r in rows]
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    ax1.plot(steps, [r.get("reward_ema", 0.0) for r in rows], label="reward_ema")
    ax1.plot(steps, [r.get("reward_per_step", 0.0) for r in rows], alpha=0.5, label="reward per step")
    ax1.set_ylabel("reward")
    ax1.legend()
    ax2.plot(steps, [r.get("sps", 0.0) for r in rows])
    ax2.set_ylabel("SPS")
    ax2.set_xlabel("env steps")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return None


def write_report(run: RunFiles, summary: dict[str, Any]) -> Path:
    """reports/report.md (and report.png) summarising the run (not written when run.write is False)."""
    reports = run.root / "reports"
    if not run.write:
        return reports / "report.md"
    why_not = plot_png(run.rows, reports / "report.png") if run.rows else "no metrics rows were logged"
    lines = [f"# Training run {run.run_id}", "", "| key | value |", "| --- | --- |"]
    lines += [f"| {k} | {v} |" for k, v in summary.items()]
    if run.rows:
        last = run.rows[-1]
        lines += ["", "## Last metrics", "", "| metric | value |", "| --- | --- |"]
        lines += [f"| {k} | {v:.6g} |" for k, v in last.items()]
    lines += ["", "## Plot", ""]
    lines.append(f"Not drawn: {why_not}." if why_not else "![reward and SPS](report.png)")
    path = reports / "report.md"
    text = ("\n".join(lines) + "\n").encode()
    atomic_write(path, lambda f: f.write(text))
    return path
