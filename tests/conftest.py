"""Shared fixtures: a tiny simulated world that many test files reuse (session scope); torch's thread count."""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest


def threads_per_worker() -> int:
    """CPU threads per test process: the cores shared among pytest-xdist's workers (`-n`), at most 2.

    Two processes that each run torch on every core oversubscribe them, and OpenMP's spinning threads then
    slow both down several-fold; one thread each keeps the cores busy without contention.
    """
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    return max(1, min(2, (os.cpu_count() or 1) // max(workers, 1)))


_OWN_CACHE = "_EXOLAN_TEST_CACHE_OWNER"  # set by the process that made the session's cache folder


def pytest_configure(config):
    # the reader's cache in a folder of this test session, never the user's ~/.cache/exolan; pytest-xdist's
    # workers and the CLI tests' subprocesses inherit it from the process that made it
    if not os.environ.get(_OWN_CACHE):
        os.environ["EXOLAN_CACHE_DIR"] = tempfile.mkdtemp(prefix="exolan-test-cache-")
        os.environ[_OWN_CACHE] = str(os.getpid())
    # before any test module imports torch's users; subprocesses (the CLI tests) inherit OMP_NUM_THREADS
    n = threads_per_worker()
    os.environ["OMP_NUM_THREADS"] = str(n)
    os.environ["EXOLAN_FIT_WORKERS"] = str(n)     # the diagnosis' fits side by side: the same share of the cores
    import torch

    torch.set_num_threads(n)


def pytest_unconfigure(config):
    if os.environ.get(_OWN_CACHE) == str(os.getpid()):
        shutil.rmtree(os.environ["EXOLAN_CACHE_DIR"], ignore_errors=True)


def pytest_collection_modifyitems(config, items):
    """The heavy tests first, each followed by one light test, the rest in their order.

    With `--dist load --maxschedchunk 1` (scripts/test.sh) pytest-xdist hands every worker two tests to start
    with and then one test at a time to whichever worker is free: the heavy tests start on different workers
    at the beginning instead of one of them starting last while the other workers idle.
    """
    heavy = [item for item in items if item.get_closest_marker("heavy") is not None]
    light = [item for item in items if item.get_closest_marker("heavy") is None]
    order = []
    for item in heavy:
        order += [item] + light[:1]
        light = light[1:]
    items[:] = order + light


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


@pytest.fixture(scope="module")
def arm():
    """A simulated two-link arm, two trials of 6 s, prepared for the diagnosis (its building-block tests)."""
    from exolan.diagnose.flat import prepare
    from exolan.diagnose.synthetic import two_link

    trials, _ = two_link(n_trials=2, seconds=6.0, seed=3)
    return prepare(trials)
