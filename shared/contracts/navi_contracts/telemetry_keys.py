"""Names of the `TelemetryEvent.key`s the services publish and the dashboard reads.

Keys are dotted: `<source>.<name>`. The learner turns every training log row into
`actor.training.<column>` (sps, reward_ema, episode_return, collisions_per_1k, coverage_per_1k,
entropy, value_loss, ...) and inference into `actor.inference.<name>`; the dashboard's mode is the
prefix of the newest fresh `actor.*` key.
"""

from __future__ import annotations

TRAINING = "actor.training."
"""Prefix of training telemetry (one event per column of each PPO log row, plus the heartbeat)."""
INFERENCE = "actor.inference."
"""Prefix of inference telemetry."""
ACTORS = "actors"
"""Last component of the actor-count heartbeat (`actor.training.actors`, once a second while running)."""

CORPUS = "corpus."
"""Prefix of the corpus build's progress, published by the learner while it builds or loads its corpus."""
CORPUS_SCENES_READY = "corpus.scenes_ready"
"""Scenes compiled and qualified so far."""
CORPUS_SCENES_PLANNED = "corpus.scenes_planned"
"""Scenes the build makes."""
CORPUS_SCENES_REJECTED = "corpus.scenes_rejected"
"""Scenes rejected by spawn qualification."""
CORPUS_READY = "corpus.ready"
"""1 once the corpus is ready, 0 while it is built."""
