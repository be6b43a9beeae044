"""The learner's `navi` commands end to end on the toy env (train -> registry -> evaluate), and their
one-line errors (exit code 2)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from navi.cli import build_app
from navi_learner.serving.checkpoint import read_meta

runner = CliRunner()


@pytest.fixture(autouse=True)
def in_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, single_thread: None) -> None:
    monkeypatch.chdir(tmp_path)


def invoke(*args: str) -> tuple[int, str, str]:
    result = runner.invoke(build_app(), list(args))
    return result.exit_code, result.stdout, result.stderr


def test_train_promote_list_evaluate_compare(tmp_path: Path) -> None:
    code, out, err = invoke(
        "train",
        "--env",
        "toy",
        "--actors",
        "4",
        "--rollout-length",
        "32",
        "--total-steps",
        "256",
        "--device",
        "cpu",
        "--temporal-core",
        "gru",
    )
    assert code == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["steps"] == 256 and summary["promoted"] == "v001"
    assert Path(summary["checkpoint"]).is_file() and Path(summary["report"]).is_file()
    code, out, err = invoke("models", "list", "--json")
    assert code == 0, err
    listing = json.loads(out)
    assert [v["version"] for v in listing["versions"]] == ["v001"] and listing["aliases"]["latest"] == "v001"
    # a second run resumes from artifacts/models/latest.pt
    code, out, err = invoke(
        "train",
        "--env",
        "toy",
        "--actors",
        "4",
        "--rollout-length",
        "32",
        "--total-steps",
        "512",
        "--device",
        "cpu",
        "--temporal-core",
        "gru",
    )
    assert code == 0, err
    assert "resuming from artifacts/models/latest.pt" in err
    assert json.loads(out.strip().splitlines()[-1])["steps"] == 512
    code, out, err = invoke("evaluate", "v001", "--env", "toy", "--steps", "50", "--device", "cpu", "--json")
    assert code == 0, err
    (row,) = json.loads(out)["results"]
    assert row["steps"] == 50 and row["actors"] == 4 and row["per_actor"]["steps"] == [50.0] * 4
    assert row["policy"].endswith("v001.pt") and -1.0 <= row["reward_per_step"] <= 1.0
    assert len(row["mean_outside"]) == 4 and all(0.0 <= x <= 1.0 for x in row["mean_outside"])
    code, out, err = invoke("evaluate", "v001", "--env", "toy", "--steps", "50", "--device", "cpu")
    assert code == 0, err
    shares = " / ".join(f"{x:.1%}" for x in row["mean_outside"])  # the same flight, seeded
    assert (
        f"Action means outside [-1, 1], forward / vertical / lateral / yaw rate ({row['policy']}): {shares}"
        in out
    )
    code, out, err = invoke(
        "compare", "random", "reactive", "--env", "toy", "--steps", "50", "--device", "cpu", "--json"
    )
    assert code == 0, err
    rand, reactive = json.loads(out)["results"]
    assert reactive["reward_per_step"] > rand["reward_per_step"]
    code, out, _ = invoke(
        "models",
        "promote",
        summary["checkpoint"],
        "--alias",
        "champion",
        "--notes",
        "hand-picked",
        "--tags",
        "rl,gru",
    )
    promoted = json.loads(out)
    assert code == 0 and promoted["tags"] == ["rl", "gru"] and promoted["notes"] == "hand-picked"
    code, out, _ = invoke("models", "list", "--json")
    assert code == 0 and json.loads(out)["aliases"]["champion"] == promoted["version"]


def test_engine_option_shapes_a_fresh_engine_and_is_ignored_on_resume() -> None:
    args = ("train", "--env", "toy", "--actors", "4", "--rollout-length", "32", "--device", "cpu")
    code, out, err = invoke(
        *args, "--total-steps", "128", "--engine", "head_hidden=16", "--engine", "rnd_dim=8",
        "--engine", "attention=explicit",
    )  # fmt: skip
    assert code == 0, err
    engine = read_meta(Path(json.loads(out.strip().splitlines()[-1])["checkpoint"])).config["engine"]
    assert engine["head_hidden"] == 16 and engine["rnd_dim"] == 8 and engine["attention"] == "explicit"
    code, out, err = invoke(*args, "--total-steps", "256", "--engine", "head_hidden=64")
    assert code == 0, err
    assert "--engine is ignored" in err
    engine = read_meta(Path(json.loads(out.strip().splitlines()[-1])["checkpoint"])).config["engine"]
    assert engine["head_hidden"] == 16


def test_bench_learn_help_names_every_ppo_setting_and_run_size_an_arm_takes() -> None:
    from navi_bench.learn import ARM_PPO_FIELDS, ARM_SIZE_FIELDS

    shown = CliRunner().invoke(build_app(), ["bench", "learn", "--help"], env={"COLUMNS": "400"})
    assert shown.exit_code == 0, shown.output
    arm_help = " ".join(shown.output.split("--arm", 1)[1].split("--budget-s", 1)[0].split())
    assert "PPO settings (" + ", ".join(ARM_PPO_FIELDS) + ")" in arm_help
    assert "run sizes (" + ", ".join(ARM_SIZE_FIELDS) + ")" in arm_help


def test_errors_are_one_line_with_exit_code_2(tmp_path: Path) -> None:
    code, _, err = invoke("evaluate", "--env", "toy")
    assert code == 2 and "give exactly one of CHECKPOINT or --policy" in " ".join(
        err.replace("│", " ").split()
    )
    code, _, err = invoke("evaluate", "nope.pt", "--env", "toy", "--device", "cpu")
    assert code == 2 and "neither" in err
    code, _, err = invoke(
        "train", "--corpus", str(tmp_path / "missing"), "--device", "cpu", "--total-steps", "1"
    )
    assert code == 2 and "does not exist" in err
    code, _, err = invoke("models", "rollback")
    assert code == 2 and "no previous version" in err
    code, _, err = invoke("train", "--env", "toy", "--obs-storage", "compact", "--device", "cpu", "--fresh")
    assert code == 2 and "DistanceMatrix v2" in err  # the toy env's observations are not
    code, _, err = invoke("bench", "train", "--env", "toy", "--obs-storage", "bfloat16", "--device", "cpu")
    assert code == 2 and "--obs-storage" in err
    for command in (("train", "--fresh"), ("bench", "train")):
        code, _, err = invoke(*command, "--env", "toy", "--rank-scenes", "half", "--device", "cpu")
        assert code == 2 and "--rank-scenes" in err and "share, all" in err
    code, _, err = invoke("bench", "learn", "--reward", "no_such_weight=1", "--device", "cpu")
    assert code == 2 and "unknown reward weight" in err and "exploration_weight" in err
    code, _, err = invoke("bench", "learn", "--reward", "exploration_weight", "--device", "cpu")
    assert code == 2 and "KEY=NUMBER" in err
    code, _, err = invoke("bench", "learn", "--engine", "no_such_field=1", "--device", "cpu")
    assert code == 2 and "unknown engine field" in err and "patch_el" in err
    code, _, err = invoke("bench", "learn", "--arm", "mamba2/lr=0", "--device", "cpu")
    assert code == 2 and "lr expects a positive learning rate" in err
    code, _, err = invoke("bench", "learn", "--arm", "mamba2/actors=many", "--device", "cpu")
    assert code == 2 and "actors expects a positive whole number" in err
    code, _, err = invoke("train", "--env", "toy", "--engine", "patch_el=wide", "--device", "cpu")
    assert code == 2 and "patch_el expects int" in err
    code, _, err = invoke("train", "--env", "toy", "--engine", "attention=flash", "--device", "cpu")
    assert code == 2 and "attention expects one of auto, sdpa, explicit, fused" in err
    code, _, err = invoke(
        "bench", "train", "--env", "toy", "--engine", "temporal_core=gru", "--device", "cpu"
    )
    assert code == 2 and "unknown engine field 'temporal_core'" in err
    (tmp_path / "junk.pt").write_bytes(b"junk")
    code, _, err = invoke("export", "junk.pt", "--onnx", "out.onnx")
    assert code == 2 and err.startswith("error:")
    code, _, err = invoke("train", "--env", "toy", "--init-from", "absent.pt", "--device", "cpu")
    assert code == 2 and "init_from: checkpoint absent.pt does not exist" in err
    code, _, err = invoke("train", "--env", "toy", "--init-from", "explore", "--checkpoint", "junk.pt")
    assert code == 2 and "--checkpoint resumes one" in err


def test_export_without_onnx_says_what_to_install(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """onnx is installed for the export tests, so its absence is made here: a None in sys.modules makes
    `import onnx` raise ImportError, as on a machine without it."""
    code, out, err = invoke(
        "train",
        "--env",
        "toy",
        "--actors",
        "4",
        "--rollout-length",
        "32",
        "--total-steps",
        "128",
        "--device",
        "cpu",
        "--fresh",
    )
    assert code == 0, err
    ckpt = json.loads(out.strip().splitlines()[-1])["checkpoint"]
    for name in [
        m for m in sys.modules if m == "onnx" or m.startswith(("onnx.", "onnxscript", "onnxruntime"))
    ]:
        monkeypatch.delitem(sys.modules, name)
    for name in ("onnx", "onnxscript", "onnxruntime"):
        monkeypatch.setitem(sys.modules, name, None)
    code, _, err = invoke("export", ckpt, "--onnx", "out.onnx")
    assert code == 2 and "pip install onnx" in err


@pytest.mark.skipif(
    importlib.util.find_spec("onnxruntime") is None, reason="onnx/onnxruntime are not installed"
)
def test_onnx_export_matches_pytorch_step(tmp_path: Path) -> None:
    import numpy as np
    import onnxruntime as ort

    from navi_learner.config import EngineConfig
    from navi_learner.engine.policy import CognitiveMambaPolicy
    from navi_learner.serving.checkpoint import load_checkpoint

    code, out, err = invoke(
        "train",
        "--env",
        "toy",
        "--actors",
        "4",
        "--rollout-length",
        "32",
        "--total-steps",
        "128",
        "--device",
        "cpu",
        "--fresh",
        "--engine",
        "attention=fused",  # a Triton kernel on CUDA: the export writes SDPA, the same function
    )
    assert code == 0, err
    ckpt = json.loads(out.strip().splitlines()[-1])["checkpoint"]
    code, out, err = invoke("export", ckpt, "--onnx", "policy.onnx")
    assert code == 0 and out.splitlines()[-1] == "policy.onnx", err  # torch.onnx logs its stages before
    loaded = load_checkpoint(Path(ckpt))
    policy = CognitiveMambaPolicy((3, 16, 8), EngineConfig.from_dict(loaded.meta.config["engine"]))
    policy.load_state_dict(loaded.model)
    policy.eval()
    obs = torch.rand(3, 3, 16, 8)
    resets = torch.tensor([True, False, True])
    state = tuple(torch.randn_like(s) for s in policy.initial_state(3, torch.device("cpu")))
    with torch.no_grad():
        want = policy.act(obs, resets, state, deterministic=True)
    sess = ort.InferenceSession("policy.onnx")
    feeds = {
        "obs": obs.numpy(),
        "resets": resets.numpy(),
        **{f"state_{i}": s.numpy() for i, s in enumerate(state)},
    }
    action, value, *new_state = sess.run(None, feeds)
    assert np.allclose(action, want.action.clamp(-1, 1).numpy(), atol=1e-4)
    assert np.allclose(value, want.value.numpy(), atol=1e-4)
    for got, ref in zip(new_state, want.state, strict=True):
        assert np.allclose(got, ref.numpy(), atol=1e-4)


def test_train_records_the_update_options_and_keeps_tf32_to_cuda() -> None:
    """The update options reach the run's config (its manifest): the compiled objective by default,
    --no-compile-update and --tf32 on request. On the CPU neither changes how it runs: the objective
    stays eager and float32 matrix products keep full precision."""
    for flags, want in (((), True), (("--no-compile-update",), False)):
        code, out, err = invoke(
            "train", "--env", "toy", "--actors", "4", "--rollout-length", "32", "--total-steps", "128",
            "--device", "cpu", "--tf32", *flags,
        )  # fmt: skip
        assert code == 0, err
        run_dir = Path(json.loads(out.strip().splitlines()[-1])["checkpoint"]).parents[1]
        config = json.loads((run_dir / "manifests" / "run.json").read_text())["config"]
        assert config["compile_update"] is want and config["tf32"] is True
        assert torch.backends.cuda.matmul.allow_tf32 is False
