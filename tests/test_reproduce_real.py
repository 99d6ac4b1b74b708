"""`exolan reproduce` with exolan's own world, reader, models and training (not a stand-in), at a test-only
scale: one seed, two architectures, one epoch. It proves that the sweep, the evaluation and the report
work against the real interfaces, including the real-recordings section. The full small-scale study is
`test_small_scale_study` (slow)."""
from __future__ import annotations

import json

import pytest

pytest.importorskip("exolan.train", reason="training module not available")

from exolan import reproduce as R  # noqa: E402


@pytest.mark.parametrize("with_real", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_micro_sweep_with_the_real_models(tmp_path, with_real):
    real = R.default_real_dir() if with_real else None
    R.reproduce("micro", tmp_path, workers=1, real_dir=real, log=lambda *a: None)
    res = json.loads((tmp_path / "results.json").read_text())
    assert set(res["intention"]) == {"exolan", "mlp-tcn"}
    for m in res["intention"].values():
        assert float(m["seen"]["mse"][0]) > 0 and float(m["unseen"]["mse"][0]) > 0
    refs = {"reference: recorded", "reference: true inputs, recorded τ", "reference: true inputs"}
    assert set(res["forward_dynamics"]) == {"inverse", "w_fd", "w_fd+w_ms"} | refs
    fd = res["forward_dynamics"]
    # the world's own leg with every true input is the floor of the references
    assert float(fd["reference: true inputs"]["mean_std"]["qd20"][0]) < float(fd["reference: recorded"]["mean_std"]["qd20"][0])
    assert "q20" in res["forward_dynamics"]["w_fd"]["mean_std"]
    assert 0 <= float(res["task_identification"]["sample_split"]["exolan"]["accuracy"][0]) <= 1
    if real is not None:
        assert set(res["real"]) == {"exolan", "mlp-tcn"}
        assert float(res["real"]["exolan"]["unseen_user"]["mse"][0]) > 0
    for f in res["figures"].values():
        assert (tmp_path / f).stat().st_size > 10_000


@pytest.mark.slow
def test_small_scale_study(tmp_path):
    """The issue's check: `reproduce --scale small` fills every table with 16 methods, every figure is a
    real drawing, and a second run with the same seeds gives the same numbers."""
    R.reproduce("small", tmp_path / "a", workers=2)
    res = json.loads((tmp_path / "a" / "results.json").read_text())
    assert len(res["intention"]) == 16
    refs = {"reference: recorded", "reference: true inputs, recorded τ", "reference: true inputs"}
    assert set(res["forward_dynamics"]) == {"inverse", "w_fd", "w_fd+w_ms"} | refs
    fd = res["forward_dynamics"]
    # the world's own leg with every true input is the floor of the references
    assert float(fd["reference: true inputs"]["mean_std"]["qd20"][0]) < float(fd["reference: recorded"]["mean_std"]["qd20"][0])
    assert res["task_identification"]["sample_split"]["exolan"]
    for f in res["figures"].values():
        assert (tmp_path / "a" / f).stat().st_size > 10_000
    R.reproduce("small", tmp_path / "b", workers=2)
    res_b = json.loads((tmp_path / "b" / "results.json").read_text())
    for k in ("intention", "forward_dynamics", "task_identification", "real"):
        assert res_b[k] == res[k], k
