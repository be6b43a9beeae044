"""The control plane under bad input: 1,000 requests with bad bodies and odd version strings, then
schemathesis over the OpenAPI schema (bounded). No request may get a 500, and nothing may be
written outside the registry folder."""

from __future__ import annotations

import collections
import json
import os
import random
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import quote

import pytest
import torch
from fastapi.testclient import TestClient

from navi_learner.config import TrainConfig
from navi_learner.serving.checkpoint import CheckpointMeta, save_checkpoint
from navi_learner.serving.control_plane import MAX_BODY_BYTES, ControlPlaneConfig, create_app

TOKEN = "fuzz-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
REQUESTS = 1000
ALLOWED = {200, 400, 401, 403, 404, 405, 413, 422}
REGISTRY_FILES = {"registry.json", "audit.jsonl", "latest.pt", ".registry.lock"}

ODD = [
    "../",
    "../../etc/passwd",
    "..%2F..%2Fetc%2Fpasswd",
    "v001/../../x",
    "/etc/passwd",
    "/dev/zero",
    "/dev/stdin",
    "/proc/self/environ",
    "/",
    ".",
    "",
    " ",
    "a" * 300,
    "a" * 5000,
    "b/" * 3000,
    "模型",
    "v\u0000001",
    "\u0000",
    "\ud800",
    "\u202ev100",
    "🚁",
    "latest",
    "champion",
    "v001",
    "v999",
    "registry.json",
    "audit.jsonl",
    "%00",
    "\\..\\..\\windows",
    "file:///etc/passwd",
    "http://127.0.0.1:1/x",
    "con",
    "nul",
    "~/.ssh/id_rsa",
    "$(touch /tmp/pwned)",
    "`id`",
    "*",
    "?",
    "\n",
    "\t\r",
]


def snapshot(root: Path, skip: Path) -> dict[str, tuple[int, int]]:
    """Every file under root except those under `skip`: path -> (size, mtime_ns)."""
    out = {}
    for folder, dirs, files in os.walk(root):
        if Path(folder).resolve() == skip.resolve():
            dirs[:] = []
            continue
        for name in files:
            p = Path(folder) / name
            st = p.lstat()
            out[str(p)] = (st.st_size, st.st_mtime_ns)
    return out


def checkpoint(folder: Path, step: int) -> Path:
    meta = CheckpointMeta(step, 0, 0.1 * step, 0.0, "gru", "fuzz", TrainConfig().to_dict(), [3, 16, 8])
    return save_checkpoint(folder / f"ckpt_{step}.pt", {"w": torch.ones(2)}, None, meta)


@pytest.fixture
def plane(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[TestClient, Path, Path]]:
    work = tmp_path / "cwd"
    work.mkdir()
    monkeypatch.chdir(work)  # relative paths in requests resolve here: it must stay untouched too
    registry = tmp_path / "models"
    (tmp_path / "ckpts").mkdir()
    with TestClient(create_app(ControlPlaneConfig(registry, TOKEN))) as client:
        yield client, registry, tmp_path


def as_json(body: Any, auth: dict[str, str]) -> dict[str, Any]:
    """A JSON body as bytes (ASCII escapes, so unpaired surrogates reach the server as JSON allows)."""
    return {"content": json.dumps(body).encode(), "headers": {**auth, "Content-Type": "application/json"}}


def bad_requests(rng: random.Random, good: list[str]) -> Iterator[tuple[str, str, dict[str, Any]]]:
    """(method, path, httpx keyword arguments) for REQUESTS requests, deterministic for a seed."""
    junk_bodies: list[Any] = [
        b"",
        b"{",
        b"null",
        b"[]",
        b"\xff\xfe\x00",
        b'{"checkpoint": }',
        b"[" * 5000 + b"]" * 5000,
        b'{"checkpoint": "' + b"x" * (MAX_BODY_BYTES + 10) + b'"}',
        json.dumps({"checkpoint": 1}).encode(),
        json.dumps({"checkpoint": None}).encode(),
        json.dumps({"checkpoint": ["a"]}).encode(),
        json.dumps({"alias": {"x": 1}}).encode(),
        json.dumps({"checkpoint": "v001", "tags": ["t"] * 100}).encode(),
        json.dumps({"checkpoint": "v001", "tags": ["x" * 500]}).encode(),
        json.dumps({"checkpoint": "v001", "notes": "n" * 3000}).encode(),
        json.dumps({"checkpoint": "v001", "extra": True, "alias": "ok"}).encode(),
    ]
    for i in range(REQUESTS):
        kind = i % 8
        odd = rng.choice(ODD)
        auth = AUTH if rng.random() < 0.85 else rng.choice([{}, {"Authorization": "Bearer nope"}])
        if kind == 0:
            yield "GET", "/models/" + quote(odd, safe="", errors="surrogatepass"), {}
        elif kind == 1:
            yield "GET", "/models/" + quote(odd, safe="/%", errors="surrogatepass"), {}
        elif kind == 2:
            body = {"checkpoint": odd or "x", "alias": rng.choice(["champion", "stable", "latest"])}
            yield "POST", "/models/promote", as_json(body, auth)
        elif kind == 3:
            body = {"checkpoint": rng.choice([*good, "v001", "latest"]), "alias": odd}
            yield "POST", "/models/promote", as_json(body, auth)
        elif kind == 4:
            yield "POST", "/models/rollback", as_json({"alias": odd}, auth)
        elif kind == 5:
            headers = {**auth, "Content-Type": rng.choice(["application/json", "text/plain", "x/y"])}
            yield (
                "POST",
                rng.choice(["/models/promote", "/models/rollback"]),
                {
                    "content": rng.choice(junk_bodies),
                    "headers": headers,
                },
            )
        elif kind == 6:
            body = {"checkpoint": rng.choice(good), "notes": odd, "tags": [odd or "t"]}
            yield "POST", "/models/promote", as_json(body, auth)
        else:
            method = rng.choice(["PUT", "DELETE", "PATCH", "GET", "POST"])
            odd_path = "/" + quote(odd, safe="/", errors="surrogatepass")
            yield method, rng.choice(["/models", "/healthz", "/metrics", "/models/promote", odd_path]), {}


def test_a_thousand_bad_requests_get_no_500_and_write_nothing_outside_the_registry(
    plane: tuple[TestClient, Path, Path],
) -> None:
    client, registry, tmp = plane
    good = [str(checkpoint(tmp / "ckpts", step)) for step in (1, 2)]
    assert client.post("/models/promote", json={"checkpoint": good[0]}, headers=AUTH).status_code == 200
    before = snapshot(tmp, registry)
    statuses: collections.Counter[int] = collections.Counter()
    failures = []
    requests = list(bad_requests(random.Random(15), good))
    assert len(requests) == REQUESTS
    for method, path, kwargs in requests:
        response = client.request(method, path, **kwargs)
        statuses[response.status_code] += 1
        if response.status_code not in ALLOWED:
            failures.append((method, path[:80], response.status_code, response.text[:200]))
    print(f"statuses of {REQUESTS} bad requests: {dict(sorted(statuses.items()))}")
    assert failures == [], failures[:5]
    assert sum(statuses.values()) == REQUESTS and statuses[500] == 0
    assert {413, 422, 404, 401, 403} <= set(statuses)  # every guard was exercised
    # Nothing outside the registry changed (the source checkpoints, the working folder, tmp itself).
    assert snapshot(tmp, registry) == before
    # The registry holds only its own files, and its index is consistent.
    names = {p.name for p in registry.iterdir()}
    versions = {n for n in names if n.startswith("v") and n.endswith(".pt")}
    assert names - versions <= REGISTRY_FILES, names
    index = json.loads((registry / "registry.json").read_text())
    assert {v["file"] for v in index["versions"]} == versions
    assert set(index["aliases"].values()) <= {v["version"] for v in index["versions"]}
    for line in (registry / "audit.jsonl").read_text().splitlines():
        json.loads(line)


def test_schemathesis_over_the_openapi_schema(plane: tuple[TestClient, Path, Path]) -> None:
    """Schema-driven inputs for every operation (bounded: 60 examples each, no shrinking): no 500."""
    schemathesis = pytest.importorskip("schemathesis", reason="schemathesis is not installed")
    from hypothesis import HealthCheck, Phase, given, settings

    client, registry, tmp = plane
    good = checkpoint(tmp / "ckpts", 3)
    assert client.post("/models/promote", json={"checkpoint": str(good)}, headers=AUTH).status_code == 200
    before = snapshot(tmp, registry)
    schema = schemathesis.openapi.from_asgi("/openapi.json", client.app)
    statuses: collections.Counter[int] = collections.Counter()
    operations = 0
    for result in schema.get_all_operations():
        operation = result.ok()
        operations += 1

        @given(case=operation.as_strategy())
        @settings(
            max_examples=60,
            deadline=None,
            derandomize=True,
            database=None,
            phases=[Phase.explicit, Phase.generate],
            suppress_health_check=list(HealthCheck),
        )
        def run(case: Any) -> None:
            response = case.call(headers=AUTH)
            statuses[response.status_code] += 1
            assert response.status_code < 500, (case.method, case.path, response.text[:200])

        run()
    print(f"schemathesis: {operations} operations, statuses {dict(sorted(statuses.items()))}")
    assert operations >= 6 and sum(statuses.values()) >= 6 * 10 and statuses[500] == 0
    assert snapshot(tmp, registry) == before
