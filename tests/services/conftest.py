"""Makes services_testlib importable and provides the `services` fixture."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

from services_testlib import Services, services_fixture


@pytest.fixture
def services(tmp_path: Path) -> Iterator[Services]:
    yield from services_fixture(tmp_path)
