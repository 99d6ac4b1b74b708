"""Backlash by variable projection on physics first's parametric base (the next step the backlash term needs).

    python backlash_profile.py WORLD JOINT_INDEX        (gap_side: in exolan.exo_signals since 2026-11-29)

For each width w of a grid the measured angles are corrected to the limb's, q + (w/2) s (s: `gap_side`, the side of
the gap read off the raw angle), physics first's signals and parametric base are made again on the corrected data
and the base alone is refitted; prints the joint equation's rms error on the training and the held-out rows.
Only the held-out rows are the same set at every w (the training rows leave out |q̇| < 3ε, which moves with w).
"""
import dataclasses
import sys

import numpy as np
import torch

from exolan.diagnose import physics
from exolan.diagnose.flat import prepare
from exolan.diagnose.procedure import load_trials
from exolan.exo_signals import gap_side

GRID = (0.0, 0.01, 0.02, 0.03, 0.035, 0.04, 0.045, 0.05, 0.06)


def main():
    root, j = sys.argv[1], int(sys.argv[2])
    trials = load_trials(root)
    flat = prepare(trials)
    side = torch.as_tensor(np.concatenate([gap_side(np.asarray(t.q, dtype=np.float64), float(t.dt)) for t in trials]),
                           dtype=flat.q.dtype)
    for w in GRID:
        res = physics.identify(dataclasses.replace(flat, q=flat.q + 0.5 * w * side), ("viscous_damping",), [j])
        prob = res._probs[j]
        r = prob.y - prob.fit([], intervals=False).pred
        print(f"w {w:.3f}  train rms {np.sqrt(np.mean(r[prob.train] ** 2)):.4f}  "
              f"held rms {np.sqrt(np.mean(r[prob.held] ** 2)):.4f}", flush=True)


if __name__ == "__main__":
    main()
