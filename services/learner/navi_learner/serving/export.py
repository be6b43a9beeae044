"""ONNX export of the step-mode policy: (obs, resets, recurrent state) in -> (action, value, new state) out.

Needs the `onnx` and `onnxscript` packages (imported lazily); without them, ExportUnavailable says so.
"""

from __future__ import annotations

import importlib.util
from dataclasses import replace
from pathlib import Path

import torch
from torch import nn

from navi_learner.config import EngineConfig
from navi_learner.engine.policy import CognitiveMambaPolicy
from navi_learner.serving.checkpoint import load_checkpoint


class ExportUnavailable(RuntimeError):
    """The ONNX toolchain is not installed."""


class StepPolicy(nn.Module):
    """Deterministic one-step policy with the recurrent state as explicit inputs and outputs."""

    def __init__(self, policy: CognitiveMambaPolicy) -> None:
        super().__init__()
        self.policy = policy

    def forward(
        self, obs: torch.Tensor, resets: torch.Tensor, state: tuple[torch.Tensor, ...]
    ) -> tuple[torch.Tensor, ...]:
        out = self.policy.act(obs, resets, state, deterministic=True)
        return (out.action.clamp(-1.0, 1.0), out.value, *out.state)


def export_onnx(checkpoint: Path, out: Path, n_actors: int = 2) -> Path:
    """Write the step-mode policy of a checkpoint as ONNX with a dynamic batch dimension N (traced with
    n_actors ≥ 2 example actors, so N is not specialised to 1); returns out."""
    missing = [m for m in ("onnx", "onnxscript") if importlib.util.find_spec(m) is None]
    if missing:
        raise ExportUnavailable(f"ONNX export needs {' and '.join(missing)}: pip install onnx onnxscript")
    ckpt = load_checkpoint(checkpoint)
    shape = tuple(int(v) for v in ckpt.meta.obs_shape)
    obs_shape = (shape[0], shape[1], shape[2])
    engine = EngineConfig.from_dict(ckpt.meta.config["engine"])
    # SDPA exports as ONNX operators; the fused attention is a Triton kernel (the same function, same weights)
    policy = CognitiveMambaPolicy(obs_shape, replace(engine, attention="sdpa"))
    policy.load_state_dict(ckpt.model)
    policy.eval()
    model = StepPolicy(policy)
    obs = torch.rand(n_actors, *obs_shape)  # (N, 3, Az, El)
    resets = torch.zeros(n_actors, dtype=torch.bool)  # (N,)
    state = policy.initial_state(n_actors, torch.device("cpu"))
    names = [f"state_{i}" for i in range(len(state))]
    out.parent.mkdir(parents=True, exist_ok=True)
    batch = torch.export.Dim("N", min=1, max=1 << 20)
    torch.onnx.export(
        model,
        (obs, resets, tuple(state)),
        str(out),
        dynamo=True,
        dynamic_shapes=({0: batch}, {0: batch}, tuple({0: batch} for _ in state)),
        input_names=["obs", "resets", *names],
        output_names=["action", "value", *[f"new_{n}" for n in names]],
    )
    return out
