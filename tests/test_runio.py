"""Run-directory I/O: atomic writes leave complete files with the permissions open() would give."""
from __future__ import annotations

import json
import os
import stat

from exolan.runio import atomic_write, write_json


def test_atomic_write_gives_umask_permissions_and_no_temporary_files(tmp_path):
    mask = os.umask(0)
    os.umask(mask)
    atomic_write(tmp_path / "a.txt", "hello")
    write_json(tmp_path / "b.json", {"x": float("nan"), "y": float("inf")})
    for name in ("a.txt", "b.json"):
        mode = stat.S_IMODE((tmp_path / name).stat().st_mode)
        assert mode == 0o666 & ~mask, oct(mode)   # as open() would make it, not mkstemp's 0600
    assert (tmp_path / "a.txt").read_text() == "hello"
    assert json.loads((tmp_path / "b.json").read_text()) == {"x": None, "y": "inf"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.json"]
