"""The 4-user world's hip Coulomb from scratch with parts of the learned base switched off (which part shares the
friction's column?), beside the warm single-term refit in the same base."""
import sys, time, copy
from dataclasses import replace
import torch
torch.set_num_threads(1)
from exolan.diagnose.flat import prepare
from exolan.diagnose.procedure import load_trials
from exolan.diagnose.settings import Settings
from exolan.diagnose.base import make_base
from exolan.diagnose.fit import train, misfit_weights
from exolan.diagnose import refits
from exolan.diagnose.export import extend
for variant in sys.argv[2].split(","):
    s = Settings()
    if variant == "nosurge": s = replace(s, pelvis_surge=False)
    if variant == "nocop": s = replace(s, lim_cop=False)
    if variant == "neither": s = replace(s, pelvis_surge=False, lim_cop=False)
    flat = prepare(load_trials(sys.argv[1]), max_delay=s.max_delay, seed=s.seed)
    t = time.time()
    base = make_base(flat, hidden=s.hidden, z_dim=s.z_dim, seed=s.seed, pelvis_surge=s.pelvis_surge, lim_cop=s.lim_cop)
    start = copy.deepcopy(base)
    train(base, flat, s.steps_base, lr=s.lr_base, batch=s.batch, seed=s.seed, w_acc=s.w_acc)
    flat.weight = misfit_weights(base, flat)
    ref = copy.deepcopy(base); refits.refit(ref, flat, s)
    warm = extend(ref, flat, [("coulomb_friction", 0)], init={"coulomb_friction": {0: 1.0}}, max_delay=s.max_delay)
    refits.refit(warm, flat, s, 2)
    m = refits.fresh_fit(flat, s, [("coulomb_friction", 0)], {"coulomb_friction": 2.011}, start)
    print(f"{variant}: hip Coulomb from scratch {m.estimate('coulomb_friction', 0):.4f}, warm {warm.estimate('coulomb_friction', 0):.4f} ({time.time()-t:.0f} s)", flush=True)
