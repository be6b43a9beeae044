"""The OpenArena maps (Debian's openarena-081-maps, `pak1-maps.pk3`) as the real-map test set.

`tests/data/fetch_openarena.sh` puts the package at DEFAULT_PK3; `$NAVI_OPENARENA_PK3` points elsewhere.
Every fifth map by sorted name, from the first, is held out of every training split that uses real maps
(`navi bench learn`'s, `navi bench transfer`'s): no drone Navi trains has seen those ten, so they judge
flights on real maps never seen (`navi run` reports that verdict where the package is present).
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

PK3_ENV = "NAVI_OPENARENA_PK3"
"""Environment variable naming the package when it is not at DEFAULT_PK3."""
DEFAULT_PK3 = Path("artifacts/data/openarena/pak1-maps.pk3")
"""Where tests/data/fetch_openarena.sh puts the package (relative to the repository root)."""
HELD_OUT_EVERY = 5
"""Every fifth map (sorted by name, from the first) is held out of training."""


def default_pk3() -> Path:
    """$NAVI_OPENARENA_PK3, or DEFAULT_PK3 (which may not exist)."""
    return Path(os.environ.get(PK3_ENV, DEFAULT_PK3))


def openarena_maps(pk3: Path) -> list[str]:
    """Members maps/*.bsp of the package, sorted."""
    with zipfile.ZipFile(pk3) as z:
        return sorted(n for n in z.namelist() if n.lower().endswith(".bsp"))


def split_openarena(maps: list[str]) -> tuple[list[str], list[str]]:
    """(train, held out): every HELD_OUT_EVERY-th map from the first is held out."""
    held = maps[::HELD_OUT_EVERY]
    return [m for m in maps if m not in held], held
