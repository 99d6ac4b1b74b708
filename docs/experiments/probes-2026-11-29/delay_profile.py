"""Probe: a delay sized by networks that never saw it: the base fitted from its start on the data with the exo
torque advanced by d (`compensate.data`), for d on a grid; held-out error against the reference."""
import sys, time, copy, numpy as np, torch
from pathlib import Path
from exolan.world import simulate
from exolan.diagnose.procedure import load_trials, fit_base
from exolan.diagnose.settings import Settings
from exolan.diagnose.flat import prepare
from exolan.diagnose.refits import refit
from exolan.diagnose.fit import sq_errors
from exolan.diagnose.rules import paired_gain
from exolan.diagnose import compensate
torch.set_num_threads(1)
seed, value, out = int(sys.argv[1]), float(sys.argv[2]), Path(sys.argv[3])
grid = [float(x) for x in sys.argv[4].split(",")]
if not (out / "world").exists():
    simulate(out / "world", users=2, tasks="walk,squat,calisthenics,turn", seconds=16, seed=seed, progress=False,
             effects=[f"actuation_delay:knee:{value}"])
flat = prepare(load_trials(out / "world"), max_delay=0.1, seed=0)
j = flat.joints.index("knee")
s = Settings(steps_base=1500, steps_refit=400, hidden=64, verbose=False)
held = flat.index("held")
base, start, _ = fit_base(flat, s, None)
ref = copy.deepcopy(base); refit(ref, flat, s)
e_ref = sq_errors(ref, flat, held).sum(1)
print("reference held-out MSE", e_ref.mean(), flush=True)
for d in grid:
    t = time.time()
    terms = [("actuation_delay", j)]; init = {"actuation_delay": {j: d}}
    m = compensate.fitted_without(flat, s, start, terms, init) if d > 0 else None
    if m is None:
        b = copy.deepcopy(start)
        from exolan.diagnose.fit import train
        train(b, flat, s.steps_base, lr=s.lr_base, batch=s.batch, seed=s.seed, w_acc=s.w_acc); refit(b, flat, s); m = b
    g = paired_gain(e_ref, sq_errors(m, flat, held).sum(1), s)
    print(f"d {1e3*d:.1f} ms: held-out gain {g['gain']:.3g} [{g['ci'][0]:.3g}, {g['ci'][1]:.3g}] ({100*g['rel']:+.1f} %), {time.time()-t:.0f} s", flush=True)
