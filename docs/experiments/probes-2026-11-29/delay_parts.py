import sys, numpy as np
from exolan.diagnose import physics, ident, parallel_filter
from exolan.diagnose.procedure import load_trials
from exolan.diagnose.flat import prepare, exo_own, exo_copy
from exolan.diagnose.candidates import FITTED

root, jn = sys.argv[1], sys.argv[2]
flat = prepare(load_trials(root), max_delay=0.1, seed=0)
j = flat.joints.index(jn)
res = physics.setup(flat, FITTED, [0, 1])
prob = res._probs[j]
sig = prob.sig
own = parallel_filter.signals(exo_own(flat, j)).tau_e[:, j]
te = sig.tau_e[:, j]
cp = te - own
grid = ident._delay_grid(sig, j, prob.ctx)
ident.TERMS["copy_rate"] = ident.Term("copy_rate", lambda s, jj, nu, ctx: np.zeros(len(s.tau[:, jj])))
def col(x, d):
    return np.nan_to_num(sig.lp(x - ident._delayed(x, sig, d)))
print("rate variance share of own:", np.var(np.diff(own[~np.isnan(own)])) / np.var(np.diff(te[~np.isnan(te)])))
for label in ("whole", "own+copyfree", "own only"):
    best = None
    for d in grid:
        if label == "whole":
            prob._cols[("actuation_delay", float(d))] = col(te, d); terms = ["actuation_delay"]
        else:
            prob._cols[("actuation_delay", float(d))] = col(own, d)
            prob._cols[("copy_rate", None)] = col(cp, d)
            terms = ["actuation_delay", "copy_rate"] if label == "own+copyfree" else ["actuation_delay"]
        s = prob.sse(terms, {"actuation_delay": d})
        if best is None or s < best[0]:
            best = (s, d)
    base = prob.sse([], {})
    print(label, "delay", round(best[1] * 1e3, 2), "ms; sse ratio", best[0] / base)
    for k in [k for k in prob._cols if k[0] in ("actuation_delay", "copy_rate")]:
        del prob._cols[k]
