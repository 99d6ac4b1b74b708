"""The world's own leg as a rollout reference (exolan.world.reference): with every true input it reproduces the
recorded motion up to the integrator, and each input the recordings lack costs it accuracy, in that order."""
import dataclasses

import numpy as np

from exolan.data import load
from exolan.reproduce import SCALES, reference_fd_rows
from exolan.world import simulate
from exolan.world.reference import MODES


def _qd_mse(rows, h):
    n = sum(r["horizons"][str(h)]["n"] for r in rows)
    return sum(sum(r["horizons"][str(h)]["sse_qd"]) for r in rows) / (2 * n)


def _errors(root, noise):
    simulate(root, users=2, tasks="walk,squat", seconds=3.0, seed=3, noise=noise, progress=False)
    scale = dataclasses.replace(SCALES["tiny"], users=2, seconds=3.0, world_seed=3, rollout_stride=20,
                                horizons=(4, 10, 20))
    items = [("seen", t, None) for t in load(root)]
    return {mode: _qd_mse(reference_fd_rows(items, scale, mode), 20) for mode in MODES}


def test_true_leg_with_true_inputs_follows_the_recording(tmp_path):
    clean = _errors(tmp_path / "clean", noise=False)
    # noise-free: with every true input only the semi-implicit Euler step (5 ms) separates rollout and data, and
    # the recorded torque is the true one; the unrecorded pelvis motion and horizontal ground force cost far more
    assert clean["true inputs"] < 0.02, clean
    assert abs(clean["true inputs, recorded τ"] - clean["true inputs"]) < 1e-9, clean
    assert clean["recorded"] > 100 * clean["true inputs"], clean
    # with sensors: the recorded torque (filtered moments, measured exo torque) costs accuracy too
    noisy = _errors(tmp_path / "noisy", noise=True)
    assert noisy["true inputs"] < noisy["true inputs, recorded τ"] < noisy["recorded"], noisy
    assert np.isfinite(list(noisy.values())).all()
