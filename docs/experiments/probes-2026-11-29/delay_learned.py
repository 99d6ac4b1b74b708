import sys, numpy as np, torch
from exolan.diagnose import physics, ident, parallel_filter
from exolan.diagnose.procedure import load_trials, fit_base
from exolan.diagnose.settings import Settings
from exolan.diagnose.flat import prepare, exo_own
from exolan.diagnose.physics_path import learned_residual
from exolan.diagnose.candidates import FITTED
torch.set_num_threads(1)
root, jn = sys.argv[1], sys.argv[2]
flat = prepare(load_trials(root), max_delay=0.1, seed=0)
j = flat.joints.index(jn)
s = Settings(steps_base=1500, hidden=64, verbose=False)
base, _, _ = fit_base(flat, s, None)
r = learned_residual(base, flat)
res = physics.setup(flat, FITTED, [0, 1])
prob = res._probs[j]
sig = prob.sig
own = parallel_filter.signals(exo_own(flat, j)).tau_e[:, j]
te = sig.tau_e[:, j]
rl = sig.lp(r[:, j]) if hasattr(sig, "lp") else r[:, j]
tr = prob.train
grid = ident._delay_grid(sig, j, prob.ctx)
def col(x, d):
    return np.nan_to_num(sig.lp(x - ident._delayed(x, sig, d)))
for label, x in (("whole", te), ("own", own)):
    out = []
    for d in grid:
        c = col(x, d)
        X = np.stack([np.ones(tr.sum())], 1)
        z = np.nan_to_num(rl[tr]) - c[tr]
        z = z - z.mean()
        out.append((float(z @ z), d))
    # also the linear (first-order) LS coefficient on the rate column
    print(label, "learned residual: delay", round(min(out)[1] * 1e3, 2), "ms")
