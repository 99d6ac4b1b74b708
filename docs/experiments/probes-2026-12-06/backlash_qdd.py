"""Probe (reads the simulator's truth; never a decision path): with a backlash of the true width w, does the
term's shift of the recorded q̈ by (w/2) s̈ (the gap side's second derivative through the recorded filters, as
the diagnosis' Flat has it) bring q̈ closer to the limb's true q̈, per task? rms of q̈ − q̈_true without and with.
Usage: python backlash_qdd.py WORLD SEED WIDTH JOINT"""
import sys
import numpy as np
from exolan.diagnose.procedure import load_trials
from exolan.diagnose.flat import prepare
from exolan.world import simulate_trial, _rng
from exolan.world.anthropometry import make_users

root, seed, w, jn = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
j = ("hip", "knee").index(jn)
flat = prepare(load_trials(root), max_delay=0.08, seed=0)
people = {u.name: (i, u) for i, u in enumerate(make_users(4, _rng(seed, 0)))}
res = {}
start = 0
for i, (T, meta) in enumerate(zip(flat.lengths, flat.trial_meta)):
    sl = slice(start, start + T)
    start += T
    if meta["subject"] not in ("S01", "S02"):
        continue
    si, u = people[meta["subject"]]
    _, _, tr = simulate_trial(u, meta["task"], 20, seed, [f"backlash:{jn}:{w}"], True, subject_index=si)
    s_idx = 0 if meta["side"] == "l" else 1
    true = tr["qdd"][:, s_idx, j]
    rec = flat.qdd[sl, j].numpy().astype(np.float64)
    shift = 0.5 * w * flat.side_dd[sl, j].numpy().astype(np.float64)
    ok = flat.valid[sl].numpy() & np.isfinite(rec)
    n = min(len(true), ok.size)
    ok = ok[:n]
    a = (rec[:n] - true[:n])[ok]
    b = (rec[:n] + shift[:n] - true[:n])[ok]
    r = res.setdefault(meta["task"], [[], []])
    r[0].append(np.mean(a ** 2)); r[1].append(np.mean(b ** 2))
for task, (a, b) in sorted(res.items()):
    print(f"{task:14s} rms q̈ − q̈_true: recorded {np.sqrt(np.mean(a)):.3g}, shifted by the term {np.sqrt(np.mean(b)):.3g} rad/s²")
