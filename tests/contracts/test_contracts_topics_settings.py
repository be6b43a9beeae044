"""Topic table and settings defaults."""

from __future__ import annotations

from pathlib import Path

import pytest

from navi_contracts import NaviSettings, topics
from navi_contracts.models import MESSAGE_TYPES


def test_every_topic_is_under_navi_and_unique() -> None:
    keys = [t.key for t in topics.ALL_TOPICS]
    assert len(set(keys)) == len(keys)
    assert all(k.startswith("navi/") and "*" not in k for k in keys)
    for t in topics.ALL_TOPICS:
        assert t.payload in MESSAGE_TYPES and t.direction
        assert (t.reply is not None) == (t in (topics.STEP, topics.COMPILE_JOBS))


def test_qos_matches_the_contract() -> None:
    assert topics.TELEMETRY.reliability == "best_effort" and topics.TELEMETRY.congestion == "drop"
    for t in (topics.COMPILE_JOBS, topics.STEP):
        assert t.reliability == "reliable" and t.congestion == "block"


def test_alive_key() -> None:
    assert topics.alive_key("learner", "abc") == "navi/alive/learner/abc"
    with pytest.raises(ValueError):
        topics.alive_key("learner", "a/b")


def test_settings_defaults_match_the_original_system(
    monkeypatch: pytest.MonkeyPatch, tmp_path: object
) -> None:
    monkeypatch.chdir(tmp_path)  # no .env here
    s = NaviSettings()
    assert (s.azimuth_bins, s.elevation_bins, s.max_distance) == (256, 48, 100.0)
    assert (s.gmdag_resolution, s.max_steps_per_episode, s.scene_episodes_per_scene) == (512, 2000, 16)
    assert s.connect_endpoints == ["tcp/127.0.0.1:7447"]


def test_settings_read_environment_and_dotenv(monkeypatch: pytest.MonkeyPatch, tmp_path: object) -> None:
    monkeypatch.chdir(tmp_path)
    with open(".env", "w") as f:
        f.write("NAVI_ELEVATION_BINS=72\nNAVI_API_TOKEN=secret\n")
    monkeypatch.setenv("NAVI_AZIMUTH_BINS", "384")
    monkeypatch.setenv("NAVI_ZENOH_CONNECT", "tcp/10.0.0.1:7447, tcp/10.0.0.2:7447")
    s = NaviSettings()
    assert (s.azimuth_bins, s.elevation_bins) == (384, 72)
    assert s.api_token.get_secret_value() == "secret"
    assert s.connect_endpoints == ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"]
    monkeypatch.setenv("NAVI_AZIMUTH_BINS", "-1")
    with pytest.raises(ValueError):
        NaviSettings()


def test_env_example_holds_the_defaults(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    example = Path(__file__).resolve().parents[2] / ".env.example"
    (tmp_path / ".env").write_text(example.read_text())
    monkeypatch.chdir(tmp_path)
    from_file = NaviSettings()
    (tmp_path / ".env").unlink()
    assert from_file == NaviSettings()
