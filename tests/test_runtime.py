"""Process settings made on import (exolan/runtime.py): they apply, and they leave a user's own alone."""
import os
import sys

import pytest

from exolan import runtime


def _clean(monkeypatch):
    for k in list(os.environ):
        if k.startswith("MALLOC_") or k in ("GLIBC_TUNABLES", "EXOLAN_MALLOPT"):
            monkeypatch.delenv(k)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt only")
def test_glibc_accepts_the_allocator_thresholds(monkeypatch):
    _clean(monkeypatch)
    assert runtime.keep_freed_memory() is True          # mallopt returned 1 for both


@pytest.mark.parametrize("var, value", [("MALLOC_ARENA_MAX", "2"), ("MALLOC_TRIM_THRESHOLD_", "0"),
                                        ("GLIBC_TUNABLES", "glibc.malloc.trim_threshold=0"), ("EXOLAN_MALLOPT", "0")])
def test_a_users_allocator_settings_are_left_alone(monkeypatch, var, value):
    _clean(monkeypatch)
    monkeypatch.setenv(var, value)
    assert runtime.keep_freed_memory() is False


def test_a_users_wait_policy_is_left_alone(monkeypatch):
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    assert runtime.apply()["omp_wait_policy"] == "ACTIVE"
