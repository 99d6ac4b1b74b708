"""Probe: the physics-first extended model's held-out gain, three ways of fitting its networks."""
import sys, time, copy, numpy as np, torch
from dataclasses import replace
from exolan.diagnose.procedure import load_trials, fit_base
from exolan.diagnose.settings import Settings
from exolan.diagnose.flat import prepare
from exolan.diagnose.export import extend
from exolan.diagnose.refits import refit, refit_terms_frozen
from exolan.diagnose.fit import sq_errors, train
from exolan.diagnose.rules import paired_gain
from exolan.diagnose import compensate
from exolan.diagnose.physics_path import learned_residual
torch.set_num_threads(1)
root, jn, size = sys.argv[1], sys.argv[2], float(sys.argv[3])
flat = prepare(load_trials(root), max_delay=0.1, seed=0)
j = flat.joints.index(jn)
s = Settings(steps_base=1500, steps_refit=400, hidden=64, verbose=False)
held = flat.index("held")
t = time.time(); base, start, _ = fit_base(flat, s, None); print("base", time.time() - t, flush=True)
ref = copy.deepcopy(base); refit(ref, flat, s)
e_ref = sq_errors(ref, flat, held).sum(1)
terms = [("viscous_damping", j)]; init = {"viscous_damping": {j: size}}
def report(label, m):
    g = paired_gain(e_ref, sq_errors(m, flat, held).sum(1), s)
    print(f"{label}: gain {g['gain']:.3g} [{g['ci'][0]:.3g}, {g['ci'][1]:.3g}] rel {100*g['rel']:+.1f} %", flush=True)
for steps in (400, 1200):
    t = time.time()
    ext = extend(base, flat, terms, init=init, max_delay=0.1)
    refit_terms_frozen(ext, flat, replace(s, steps_refit=steps), 1)
    report(f"A warm frozen refit {steps}", ext); print(" t", time.time() - t)
t = time.time()
fc = compensate.data(flat, terms, init, 0.1)
bc = copy.deepcopy(start); train(bc, fc, s.steps_base, lr=s.lr_base, batch=s.batch, seed=s.seed, w_acc=s.w_acc)
refit(bc, fc, s)
report("C from scratch on compensated data (same seed, +refit)", compensate.on_raw(bc, flat, terms, init, 0.1))
print(" t", time.time() - t)
# the noise between optima: the raw base fitted at seed+1 with the same recipe
b2 = copy.deepcopy(start); train(b2, flat, s.steps_base, lr=s.lr_base, batch=s.batch, seed=s.seed + 1, w_acc=s.w_acc)
refit(b2, flat, s); report("D term-free from scratch at seed+1 (noise)", b2)
fc2 = copy.deepcopy(start); train(fc2, fc, s.steps_base, lr=s.lr_base, batch=s.batch, seed=s.seed + 1, w_acc=s.w_acc)
refit(fc2, fc, s); report("C2 compensated from scratch seed+1", compensate.on_raw(fc2, flat, terms, init, 0.1))
