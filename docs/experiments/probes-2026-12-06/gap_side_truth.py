"""Probe (reads the simulator's truth; not a decision path): how well `gap_side` reads a backlash's side off the
recorded angle, per task. Re-simulates user 0's trials of a 4-user world with a hip backlash and compares
s = gap_side(q_meas) with the truth (q − q_meas)/(w/2). Usage: python gap_side_truth.py SEED WIDTH JOINT"""
import sys
import numpy as np
from exolan.world import simulate_trial, _rng
from exolan.world.anthropometry import make_users
from exolan.exo_signals import gap_side

seed, w, jn = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
j = ("hip", "knee").index(jn)
people = make_users(4, _rng(seed, 0))
for task in ("walk", "run", "squat", "jump_in_place", "sit_to_stand", "ball_toss"):
    rows = []
    for si in range(2):
        exo, mom, tr = simulate_trial(people[si], task, 20, seed, [f"backlash:{jn}:{w}"], True, subject_index=si)
        for side in ("l", "r"):
            s_idx = 0 if side == "l" else 1
            qm = np.deg2rad(exo[f"{jn}_angle_{side}"])
            s = gap_side(qm[:, None], 0.005)[:, 0]
            truth = (tr["q"][:, s_idx, j] - tr["q_meas"][:, s_idx, j]) / (w / 2)
            rows.append((np.mean(np.abs(s - truth) > 0.5), np.sqrt(np.mean((s - truth) ** 2)),
                         np.sum(np.abs(np.diff(np.sign(truth))) > 0)))
    r = np.array(rows)
    print(f"{task:14s} share |s - truth| > 0.5: {r[:, 0].mean():.3f}, rms {r[:, 1].mean():.3f}, side flips/trial {r[:, 2].mean():.0f}")
