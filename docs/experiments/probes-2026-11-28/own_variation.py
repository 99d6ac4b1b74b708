import sys, numpy as np
from exolan.diagnose import physics, parallel_filter
from exolan.diagnose.procedure import load_trials
from exolan.diagnose.flat import prepare, exo_own
from exolan.diagnose.candidates import FITTED

root = sys.argv[1]
flat = prepare(load_trials(root), max_delay=0.1, seed=0)
J = [0, 1]
res = physics.setup(flat, FITTED, J)
physics.select(res, flat, n_boot=200, log=None, joints=J)
print(res.summary(flat.joints))
for j in J:
    prob = res._probs[j]
    terms = list(res._fits[j].terms)
    cands = terms if "torque_gain" in terms else terms + ["torque_gain"]
    sig_own = parallel_filter.signals(exo_own(flat, j))
    own_col = np.nan_to_num(prob.sig.lp(sig_own.tau_e)[:, j])
    for label, col in (("whole", None), ("own", own_col)):
        saved = dict(prob._cols)
        if col is not None:
            prob._cols[("torque_gain", None)] = col
        f = prob.fit(cands)
        te = physics.term_estimate(prob, f, "torque_gain", flat.joints[j])
        print(flat.joints[j], label, cands, "gain", round(te.estimate, 4), [round(v, 3) for v in te.ci], "p", te.p,
              "| others", {e: round(physics.term_estimate(prob, f, e, flat.joints[j]).estimate, 4) for e in cands if e != "torque_gain"})
        prob._cols = saved
