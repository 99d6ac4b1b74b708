"""Probe: a delay sized by a fixed point of networks that never saw the size so far. d_0 from the base's residual;
then d_{k+1} = the delay the residual (on the recorded data) of networks fitted from their start on the data with
the delay d_k taken out (compensate.data) still shows. If the networks imitate a fraction α of whatever delay is
left in their data, d_{k+1} = (1 − α) d + α d_k → d."""
import sys, time, numpy as np, torch
from pathlib import Path
from exolan.world import simulate
from exolan.diagnose import physics, ident, compensate
from exolan.diagnose.procedure import load_trials, fit_base
from exolan.diagnose.settings import Settings
from exolan.diagnose.flat import prepare
from exolan.diagnose.physics_path import learned_residual
from exolan.diagnose.candidates import FITTED
torch.set_num_threads(1)
seed, value, out, iters = int(sys.argv[1]), float(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4])
jn = "knee"
if not (out / "world").exists():
    simulate(out / "world", users=2, tasks="walk,squat,calisthenics,turn", seconds=16, seed=seed, progress=False,
             effects=[f"actuation_delay:{jn}:{value}"] if value > 0 else [])
flat = prepare(load_trials(out / "world"), max_delay=0.1, seed=0)
j = flat.joints.index(jn)
s = Settings(steps_base=1500, steps_refit=400, hidden=64, verbose=False)
res = physics.setup(flat, FITTED, list(range(flat.n)))
prob = res._probs[j]; sig = prob.sig; tr = prob.train
te = sig.tau_e[:, j]
grid = [0.0] + list(ident._delay_grid(sig, j, prob.ctx))

def size(model):
    r = sig.lp(learned_residual(model, flat)[:, j])
    sse = []
    for d in grid:
        c = np.nan_to_num(sig.lp(te - ident._delayed(te, sig, d))) if d > 0 else np.zeros_like(te)
        z = np.nan_to_num(r[tr]) - c[tr]
        ok = np.isfinite(r[tr])
        z = z[ok] - z[ok].mean()
        sse.append(float(z @ z))
    return grid[int(np.argmin(sse))]

t0 = time.time()
base, start, _ = fit_base(flat, s, None)
d = size(base) if len(sys.argv) < 6 else float(sys.argv[5])
print(f"truth {1e3*value:.1f} ms; d0 (base's residual) {1e3*d:.1f} ms ({time.time()-t0:.0f} s)", flush=True)
for k in range(iters):
    t0 = time.time()
    if d > 0:
        m = compensate.fitted_without(flat, s, start, [("actuation_delay", j)], {"actuation_delay": {j: d}}).base
    else:
        m = base
    dn = size(m)
    print(f"  d{k+1} = {1e3*dn:.1f} ms ({time.time()-t0:.0f} s)", flush=True)
    if dn == d:
        break
    d = dn
