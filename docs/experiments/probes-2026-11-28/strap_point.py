"""Strap column's linearisation point, run against 175c170 (before the fixed point shipped): the base-only θ, then θ iterated to the fit with the strap (each: k, z, held-out MSE)."""
import sys, numpy as np, warnings, time
warnings.simplefilter("ignore")
from exolan.diagnose import physics, ident
from exolan.diagnose.procedure import load_trials
from exolan.diagnose.flat import prepare
from exolan.diagnose.settings import Settings
s = Settings()
flat = prepare(load_trials(sys.argv[1]), max_delay=s.max_delay, seed=s.seed)
for jn in ("hip", "knee"):
    j = flat.joints.index(jn)
    phys = physics.setup(flat, s.effects, [j], alpha=s.alpha, cutoff_hz=s.cutoff_hz, max_delay=s.max_delay)
    prob = phys._probs[j]
    nb = len(prob.base_names)
    out = []
    t0 = time.time()
    for it in range(8):
        f = prob.fit(["strap_compliance"])
        c, se = f.est["strap_compliance"], f.se["strap_compliance"]
        out.append(f"{1/c if c>0 else float('inf'):.1f} (z {c/se:.1f}, held {np.mean(prob.held_sq(f)):.4g})")
        prob.ctx["base_theta"][j] = f.theta[:nb]
        prob._cols = {}
    print(jn, "base-only:", out[0], "| iterated:", " -> ".join(out[1:]), f"{time.time()-t0:.1f}s", flush=True)
