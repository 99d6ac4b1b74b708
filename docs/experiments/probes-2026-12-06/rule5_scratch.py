"""Probe: rule 5 (task invariance) of a candidate judged on its warm refit (as step 2 does) and on its fit from
scratch against the reference (the term-free base with the same recipe), and the unweighted held-out MSE of the
reference, the warm refit and the fit from scratch per joint and task. Usage: python rule5_scratch.py W EFFECT J INIT"""
import sys, time
import numpy as np, torch
from exolan.diagnose.settings import Settings
from exolan.diagnose.procedure import load_trials, new_base, reference
from exolan.diagnose.flat import prepare, sample_groups
from exolan.diagnose.session import Tools
from exolan.diagnose.workers import Workers, running
from exolan.diagnose.export import extend
from exolan.diagnose.refits import refit, fresh_fit
from exolan.diagnose.procedure import refit_noise
from exolan.diagnose.candidates import LIBRARY
from exolan.diagnose.fit import sq_errors

root, effect, j, v0 = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
s = Settings()
torch.manual_seed(s.seed)
flat = prepare(load_trials(root), max_delay=s.max_delay, seed=s.seed)
w = Workers(2)
with running(w):
    start = new_base(flat, s)
    ss, _ = reference(flat, s, None, Tools(), w, [0, 1], start)
    noise = refit_noise(ss.base, ss.flat, s, ss.e_ref, ss.errors, 1, ss.scale, w, first=ss.first_twin)
    ss.sigma_r, ss.twin_d = noise["sigma"], noise.pop("twin_d")
    ss.groups, ss.group_kind = sample_groups(flat, ss.held)

    init = {effect: v0}
    t0 = time.time()
    warm = extend(ss.base, flat, [(effect, j)], init=init, max_delay=s.max_delay)
    refit(warm, flat, s)
    fresh = fresh_fit(flat, s, [(effect, j)], init, start)
    print(f"fits {time.time() - t0:.0f} s; warm {warm.estimate(effect, j):.4g}, from scratch {fresh.estimate(effect, j):.4g}")
    for name, m in (("warm", warm), ("from scratch", fresh)):
        e = ss.errors(m)[1]
        g = ss.gain(ss.e_ref, e)
        inv = ss.invariance(ss.e_ref - e, m, effect, j)
        print(f"{name}: gain {g['gain']:.3g} [{g['ci'][0]:.3g}, {g['ci'][1]:.3g}]; by task " +
              ", ".join(f"{k} {v:.3g}" for k, v in inv["groups"].items()) +
              f"; rest {inv['gain_rest']:.3g} [{inv['ci_rest'][0]:.3g}, {inv['ci_rest'][1]:.3g}]; passes {inv['passes']}"
              f"; θ by task " + ", ".join(f"{k} {v['estimate']:.3g}" for k, v in inv.get('theta_by_group', {}).items()),
              flush=True)
    # per joint and task: the unweighted held-out squared error of the reference, warm and from-scratch fits
    E = {nm: sq_errors(m, flat, ss.held) for nm, m in (("ref", ss.ref), ("warm", warm), ("scratch", fresh))}
    for task in np.unique(ss.groups):
        k = ss.groups == task
        print(f"{task:14s} " + "; ".join(f"{flat.joints[jj]}: ref {E['ref'][k, jj].mean():.3g}, warm "
              f"{E['warm'][k, jj].mean():.3g}, scratch {E['scratch'][k, jj].mean():.3g}" for jj in range(flat.n)))
