"""3227: the gain's own share with the damping held too (all vs all-but-gain), beside rule 6's single-term look."""
import sys, time, warnings, torch
warnings.simplefilter("ignore")
from exolan.diagnose import QUICK
from exolan.diagnose.settings import Settings
from exolan.diagnose.procedure import run, load_trials
from exolan.diagnose import physics_path, stats, physics
from exolan.diagnose.fit import sq_errors
from exolan.diagnose.refits import refit_terms_frozen
torch.set_num_threads(1)
cfg = dict(QUICK); cfg.update(steps_base=1500, steps_refit=400, hidden=64, verbose=False, workers=1)
s = Settings(**cfg)
captured = {}
orig = physics_path.learned_check
def spy(phys, base, ref, flat, s, joint_ids, log):
    captured.update(phys=phys, base=base, ref=ref, flat=flat)
    return orig(phys, base, ref, flat, s, joint_ids, log)
physics_path.learned_check = spy
res = run(None, settings=s, trials_loaded=load_trials(sys.argv[1]))
phys, base, ref, flat = captured["phys"], captured["base"], captured["ref"], captured["flat"]
print("rule 6:", phys.learned_check)
held = flat.index("held")
e_ref = sq_errors(ref, flat, held).sum(1)
keys = list(phys.accepted)
print("accepted", keys)
models = {}
for combo in ([k for k in keys if k[0] != "torque_gain"], keys):
    m = physics_path.extended_model(base, flat, s, combo, phys, refit_terms_frozen)
    models[tuple(combo)] = sq_errors(m, flat, held).sum(1)
a, b = models.values()
d = stats.bootstrap_mean(a - b, n_boot=400)     # > 0: the gain helps beside the damping
print("gain's own share beside the damping (all-but-gain minus all):", d["mean"], d["ci"], "rel", d["mean"] / a.mean())
d0 = stats.bootstrap_mean(e_ref - a, n_boot=400)
print("damping (form) alone vs ref:", d0["mean"], d0["ci"])
