"""Probe: a torque gain tested on the whole recorded exo torque (warm refit, as step 2 does) against the same
term on the controller's own variation alone (rule 3's own-variation null), per joint.
Usage: python own_gain.py WORLD JOINT_INDEX"""
import sys, time
import numpy as np, torch
from exolan.diagnose.settings import Settings
from exolan.diagnose.procedure import load_trials, new_base, reference
from exolan.diagnose.flat import prepare
from exolan.diagnose.session import Tools
from exolan.diagnose.workers import Workers, running
from exolan.diagnose.nulls import on_own_variation
from exolan.diagnose.export import extend
from exolan.diagnose.refits import refit, held_errors
from exolan.diagnose.rules import paired_gain

root, j = sys.argv[1], int(sys.argv[2])
s = Settings()
torch.manual_seed(s.seed)
flat = prepare(load_trials(root), max_delay=s.max_delay, seed=s.seed)
t0 = time.time()
w = Workers(2)
with running(w):
    ss, _ = reference(flat, s, None, Tools(), w, [0, 1], new_base(flat, s))
    ss.first_twin.cancel()
print(f"base + reference {time.time() - t0:.0f} s")
for k0 in (1.5, 0.7):
    init = {"torque_gain": k0}
    t0 = time.time()
    g_own, k_own = on_own_variation(ss.base, flat, j, init, ss.e_ref, ss.held, ss.w_held, s)
    m = extend(ss.base, flat, [("torque_gain", j)], init=init, max_delay=s.max_delay)
    refit(m, flat, s)
    g_all = paired_gain(ss.e_ref, held_errors(m, flat, ss.held, ss.w_held)[1], s)
    print(f"start {k0}: whole torque k {m.estimate('torque_gain', j):.4f} gain {g_all['gain']:.3g} "
          f"[{g_all['ci'][0]:.3g}, {g_all['ci'][1]:.3g}]; own variation k {k_own:.4f} gain {g_own['gain']:.3g} "
          f"[{g_own['ci'][0]:.3g}, {g_own['ci'][1]:.3g}] ({time.time() - t0:.0f} s)", flush=True)
