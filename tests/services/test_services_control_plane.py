"""The learner's FastAPI control plane over a real on-disk registry (no network: TestClient)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from navi_contracts.models import ModelPromoted
from navi_learner.config import TrainConfig
from navi_learner.serving.checkpoint import CheckpointMeta, save_checkpoint
from navi_learner.serving.control_plane import ControlPlaneConfig, ControlPlaneError, create_app

TOKEN = "s3cret-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def checkpoint(folder: Path, step: int, reward_ema: float) -> Path:
    meta = CheckpointMeta(
        step_id=step,
        episode_count=step // 100,
        reward_ema=reward_ema,
        wall_time_hours=0.01,
        temporal_core="gru",
        run_id="run-test",
        config=TrainConfig().to_dict(),
        obs_shape=[3, 16, 8],
    )
    return save_checkpoint(folder / f"ckpt_{step}.pt", {"w": torch.ones(2)}, None, meta)


@pytest.fixture
def plane(tmp_path: Path) -> tuple[TestClient, list[ModelPromoted], Path]:
    announced: list[ModelPromoted] = []
    app = create_app(ControlPlaneConfig(tmp_path / "models", TOKEN), announced.append)
    return TestClient(app), announced, tmp_path


def test_mutations_need_the_bearer_token(plane: tuple[TestClient, list[ModelPromoted], Path]) -> None:
    client, announced, tmp = plane
    ckpt = checkpoint(tmp, 1000, 0.5)
    body = {"checkpoint": str(ckpt), "alias": "champion", "notes": "first", "tags": ["rl"]}
    missing = client.post("/models/promote", json=body)
    assert missing.status_code == 401 and missing.headers["www-authenticate"] == "Bearer"
    wrong = client.post("/models/promote", json=body, headers={"Authorization": "Bearer nope"})
    assert wrong.status_code == 403
    assert client.post("/models/rollback", json={"alias": "champion"}).status_code == 401
    assert announced == [] and client.get("/models").json()["count"] == 0

    ok = client.post("/models/promote", json=body, headers=AUTH)
    assert ok.status_code == 200, ok.text
    move = ok.json()
    assert move["alias"] == "champion" and move["version"] == "v001" and move["previous_version"] is None
    assert move["model"]["step_id"] == 1000 and move["model"]["aliases"] == ["champion"]
    assert len(announced) == 1
    msg = announced[0]
    assert (msg.alias, msg.version, msg.previous_version, msg.notes, msg.tags) == (
        "champion",
        "v001",
        None,
        "first",
        ("rl",),
    )
    assert Path(msg.checkpoint).is_file() and Path(msg.checkpoint).name == "v001.pt"


def test_every_refused_request_is_counted_under_its_status(
    plane: tuple[TestClient, list[ModelPromoted], Path],
) -> None:
    """navi_refused_requests_total{status}: each 4xx answer once, the body limit's 413 among them; an
    accepted request counts nothing."""
    from navi_learner.serving.control_plane import MAX_BODY_BYTES
    from navi_mesh import metrics

    client, _, tmp = plane

    def counts() -> dict[str, float]:
        return {
            s.labels["status"]: s.value
            for f in metrics.REFUSED_REQUESTS.collect()
            for s in f.samples
            if s.name.endswith("_total")
        }

    before = counts()
    body = {"checkpoint": str(checkpoint(tmp, 100, 0.5))}
    answers = [
        client.post("/models/promote", json=body).status_code,  # no token
        client.post("/models/promote", json=body, headers={"Authorization": "Bearer nope"}).status_code,
        client.post("/models/promote", content=b"{not json", headers=AUTH).status_code,
        client.post("/models/promote", json={"checkpoint": "/nowhere/x.pt"}, headers=AUTH).status_code,
        client.get("/models/v999").status_code,
        client.post("/models/promote", content=b"x" * (MAX_BODY_BYTES + 1), headers=AUTH).status_code,
        client.post("/models/promote", json=body, headers=AUTH).status_code,  # accepted
    ]
    assert answers == [401, 403, 422, 422, 404, 413, 200]
    after = counts()
    added = {k: after.get(k, 0.0) - before.get(k, 0.0) for k in after}
    assert {k: v for k, v in added.items() if v} == {
        "401": 1.0,
        "403": 1.0,
        "422": 2.0,
        "404": 1.0,
        "413": 1.0,
    }


def test_promote_rollback_and_audit_log(plane: tuple[TestClient, list[ModelPromoted], Path]) -> None:
    client, announced, tmp = plane
    for step, ema in ((1000, 0.1), (2000, 0.3)):
        r = client.post("/models/promote", json={"checkpoint": str(checkpoint(tmp, step, ema))}, headers=AUTH)
        assert r.status_code == 200, r.text
    listing = client.get("/models").json()
    assert [m["version"] for m in listing["data"]] == ["v001", "v002"]
    assert listing["aliases"]["champion"] == "v002"
    assert client.get("/models/champion").json()["version"] == "v002"
    assert client.get("/models/v001").json()["step_id"] == 1000
    assert client.get("/models/v999").status_code == 404

    # A version can be promoted by name, without a new file.
    again = client.post("/models/promote", json={"checkpoint": "v001", "alias": "stable"}, headers=AUTH)
    assert again.status_code == 200 and again.json()["version"] == "v001"
    assert len(client.get("/models").json()["data"]) == 2

    back = client.post("/models/rollback", json={"alias": "champion"}, headers=AUTH)
    assert back.status_code == 200, back.text
    assert back.json()["version"] == "v001" and back.json()["previous_version"] == "v002"
    assert announced[-1].version == "v001" and announced[-1].previous_version == "v002"
    assert client.post("/models/rollback", json={"alias": "champion"}, headers=AUTH).status_code == 422
    missing = client.post("/models/promote", json={"checkpoint": str(tmp / "nope.pt")}, headers=AUTH)
    assert missing.status_code == 422

    audit = [json.loads(line) for line in (tmp / "models" / "audit.jsonl").read_text().splitlines()]
    moves = [(a["action"], a["alias"], a["from_version"], a["to_version"]) for a in audit]
    assert moves == [
        ("promote", "champion", None, "v001"),
        ("promote", "champion", "v001", "v002"),
        ("promote", "stable", None, "v001"),
        ("rollback", "champion", "v002", "v001"),
    ]
    assert all(a["when"] for a in audit)


def test_no_token_refuses_to_start_unless_read_only(tmp_path: Path) -> None:
    with pytest.raises(ControlPlaneError, match=r"NAVI_API_TOKEN is empty.*--read-only"):
        create_app(ControlPlaneConfig(tmp_path / "models", ""))
    client = TestClient(create_app(ControlPlaneConfig(tmp_path / "models", "", read_only=True)))
    r = client.post("/models/promote", json={"checkpoint": "v001"}, headers={"Authorization": "Bearer "})
    assert r.status_code == 503
    assert client.post("/models/promote", json={"checkpoint": "v001"}, headers=AUTH).status_code == 503
    health = client.get("/healthz").json()
    assert health["status"] == "ok" and health["mutations_enabled"] is False
    assert client.get("/models").json()["count"] == 0  # reads still work
    # A token does not reopen a read-only control plane.
    locked = TestClient(create_app(ControlPlaneConfig(tmp_path / "models", TOKEN, read_only=True)))
    assert locked.post("/models/rollback", json={"alias": "champion"}, headers=AUTH).status_code == 503


def test_navi_serve_learner_refuses_to_start_without_a_token(tmp_path: Path) -> None:
    """The command exits 2 with one line before it builds anything; --read-only starts it."""
    env = {**os.environ, "NAVI_API_TOKEN": "", "NAVI_ARTIFACTS_DIR": str(tmp_path / "artifacts")}
    env["NAVI_ZENOH_CONNECT"] = "tcp/127.0.0.1:1"  # never reached: it stops before the mesh
    out = subprocess.run(
        [sys.executable, "-m", "navi", "serve", "learner", "--env", "toy", "--port", "8999"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "refusing to start the control plane" in out.stderr and "--read-only" in out.stderr
    assert not (tmp_path / "artifacts").exists()


def test_metrics_health_and_docs(plane: tuple[TestClient, list[ModelPromoted], Path]) -> None:
    client, _, tmp = plane
    client.post("/models/promote", json={"checkpoint": str(checkpoint(tmp, 10, 0.0))}, headers=AUTH)
    r = client.get("/metrics", follow_redirects=False)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    families = {f.name: f for f in text_string_to_metric_families(r.text)}
    assert "navi_promotions" in families and "navi_decode_errors" in families
    promote = [s.value for s in families["navi_promotions"].samples if s.labels.get("action") == "promote"]
    assert promote and promote[0] >= 1
    assert all(name.startswith(("navi_", "process_", "python_")) for name in families)
    assert client.get("/metrics/", follow_redirects=False).status_code == 404  # no redirect games
    assert client.get("/healthz").json()["mutations_enabled"] is True
    assert client.get("/docs").status_code == 200
    paths = client.get("/openapi.json").json()["paths"]
    assert {
        "/models",
        "/models/{version}",
        "/models/promote",
        "/models/rollback",
        "/healthz",
        "/metrics",
    } <= set(paths)


def test_a_real_server_refuses_a_streamed_body_over_the_limit(tmp_path: Path) -> None:
    """Through uvicorn on a port the OS picked (read back from the bound socket): a chunked body with no
    Content-Length, which TestClient never sends, is counted as it streams and refused with 413 past
    MAX_BODY_BYTES; a streamed body under the limit reaches the endpoint, which promotes its checkpoint."""
    import threading

    import httpx
    import uvicorn

    from navi_learner.serving.control_plane import MAX_BODY_BYTES

    app = create_app(ControlPlaneConfig(tmp_path / "models", TOKEN), lambda _: None)
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=0, log_level="warning", lifespan="on"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        for _ in range(600):  # bounds a hang only: the server starts in well under a second
            if server.started:
                break
            thread.join(0.05)
        assert server.started, "uvicorn did not start"
        port = server.servers[0].sockets[0].getsockname()[1]

        def chunks(payload: bytes, size: int = 8192):  # a generator body: chunked, no Content-Length
            for i in range(0, len(payload), size):
                yield payload[i : i + size]

        url = f"http://127.0.0.1:{port}/models/promote"
        big = b'{"checkpoint": "' + b"x" * (MAX_BODY_BYTES + 1) + b'"}'
        with httpx.Client(timeout=30.0) as client:
            refused = client.post(
                url, content=chunks(big), headers=AUTH | {"content-type": "application/json"}
            )
            assert refused.status_code == 413, refused.text
            assert refused.json()["detail"] == f"request body over {MAX_BODY_BYTES} bytes"
            ckpt = checkpoint(tmp_path, 100, 0.5)
            small = json.dumps({"checkpoint": str(ckpt)}).encode()
            taken = client.post(
                url, content=chunks(small, 16), headers=AUTH | {"content-type": "application/json"}
            )
            assert taken.status_code == 200, taken.text
            assert taken.json()["version"] == "v001"
    finally:
        server.should_exit = True
        thread.join(30.0)
    assert not thread.is_alive()
