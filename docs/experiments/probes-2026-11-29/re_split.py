"""Probe: the subject form judged against the spread between recordings (random effects) instead of HAC alone."""
import sys, numpy as np
from pathlib import Path
from exolan.world import simulate
from exolan.diagnose import physics, physics_subjects, consistency
from exolan.diagnose.subjects import cochran_q
from exolan.diagnose.procedure import load_trials
from exolan.diagnose.flat import prepare
from exolan.diagnose.candidates import FITTED
TASKS = "walk,squat,calisthenics,turn"
def world(out, seed, sizes):
    if not (out / "world").exists():
        simulate(out / "world", users=2, tasks=TASKS, seconds=16, seed=seed, progress=False,
                 effects=[f"viscous_damping:knee:{v}:{u}" for u, v in sizes.items()])
    return out / "world"
def probe(root, label):
    flat = prepare(load_trials(root), max_delay=0.1, seed=0)
    res = physics.setup(flat, FITTED, [0, 1])
    physics.select(res, flat, n_boot=200, joints=[1])
    users, row_user = flat.user_index()
    prob = res._probs[1]; prob.split = {}
    terms = res._fits[1].terms
    shared = prob.fit(terms, intervals=False)
    for e in terms:
        if e != "viscous_damping":
            continue
        masks = [(row_user == k).astype(float) for k in range(len(users))]
        th, se, split = prob.fit_split(shared, e, masks)
        Q, p = cochran_q(th, se)
        tt, ts, trials = prob.by_trial(shared, e)
        subj = np.array([flat.trial_meta[k]["subject"] for k in trials])
        pools = [consistency.pooled(tt[subj == u], ts[subj == u], "greater") for u in users]
        m = np.array([q["mean"] for q in pools]); s = np.array([q["se"] for q in pools])
        Qr, pr = cochran_q(m, s)
        # Welch on the raw per-trial estimates (equal weights)
        from scipy import stats
        w = stats.ttest_ind(tt[subj == users[0]], tt[subj == users[1]], equal_var=False)
        g = physics._held_gain(prob.held_sq(shared), prob.held_sq(split), 400)
        print(f"{label}: terms {terms}; HAC split {np.round(th,3)} ± {np.round(se,3)} Q p {p:.2g}; RE means {np.round(m,3)} ± {np.round(s,3)} "
              f"tau {[round(q['tau'],3) for q in pools]} Q p {pr:.2g}; Welch p {w.pvalue:.2g}; held-out adv {g['gain']:.2g} [{g['ci'][0]:.2g}, {g['ci'][1]:.2g}]", flush=True)
out = Path(sys.argv[1])
for spec in sys.argv[2:]:
    seed, a, b = spec.split(":"); seed = int(seed)
    sizes = {"S01": float(a), "S02": float(b)}
    probe(world(out / f"w{seed}_{a}_{b}", seed, sizes), f"seed {seed} {sizes}")
