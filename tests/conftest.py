"""Shared fixtures: a tiny simulated world that many test files reuse (session scope)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

SMALL_WORLD = dict(users=6, tasks=["walk", "stand", "jump_in_place", "squat", "run", "cut"], seconds=4.0, seed=7)


@pytest.fixture(scope="session")
def small_world(tmp_path_factory) -> Path:
    """A tiny layout-1 world: 6 users (S01..S06) x 6 tasks (walk, stand, jump_in_place, squat, run,
    cut) x 4 s, with sensor noise, no injected effect. Returns its root directory."""
    from exolan.world import simulate

    root = tmp_path_factory.mktemp("small_world")
    simulate(root, progress=False, **SMALL_WORLD)
    return root


@pytest.fixture(scope="session")
def real_data() -> Path:
    """The real recordings (layout 1): $EXOLAN_REAL_DATA or <repo>/../shared/real; skips if absent."""
    env = os.environ.get("EXOLAN_REAL_DATA")
    p = Path(env) if env else Path(__file__).resolve().parents[1].parent / "shared" / "real"
    if not (p / "subjects.csv").exists():
        pytest.skip(f"real recordings not found at {p} (set EXOLAN_REAL_DATA)")
    return p
