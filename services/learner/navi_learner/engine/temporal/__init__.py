"""Temporal cores: Mamba-2 SSD (chunked scan + recurrent step), a plain Mamba reference, and a GRU."""

from __future__ import annotations

from navi_learner.config import EngineConfig
from navi_learner.engine.temporal.gru import GRUCore
from navi_learner.engine.temporal.mamba2 import CoreState, Mamba2Core
from navi_learner.engine.temporal.mambapy import MambaPyCore

TemporalCore = Mamba2Core | GRUCore
"""Every core offers initial_state(n, device), forward(x, resets, state) and step(x, resets, state)."""


def make_core(cfg: EngineConfig) -> TemporalCore:
    """The core named by cfg.temporal_core."""
    if cfg.temporal_core == "mamba2":
        return Mamba2Core(cfg)
    if cfg.temporal_core == "mambapy":
        return MambaPyCore(cfg)
    if cfg.temporal_core == "gru":
        return GRUCore(cfg)
    raise ValueError(f"unknown temporal core {cfg.temporal_core!r}; choose mamba2, gru or mambapy")


__all__ = ["CoreState", "GRUCore", "Mamba2Core", "MambaPyCore", "TemporalCore", "make_core"]
