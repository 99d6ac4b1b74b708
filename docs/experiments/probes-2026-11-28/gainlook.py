"""Replay a world, then: each physics-first accepted term alone held in the learned base (refit), vs the reference."""
import sys, time, warnings, numpy as np, torch
warnings.simplefilter("ignore")
from exolan.world import simulate
from exolan.diagnose import QUICK
from exolan.diagnose.settings import Settings
from exolan.diagnose.procedure import run, load_trials
from exolan.diagnose import physics_path, stats
from exolan.diagnose.fit import sq_errors
from exolan.diagnose.refits import refit_terms_frozen
root, effect, seed = sys.argv[1], sys.argv[2], int(sys.argv[3])
if not __import__("os").path.exists(root):      # an existing world is replayed as it is (EFFECT, SEED unused)
    simulate(root, users=2, tasks="walk,squat,calisthenics,turn", seconds=16, seed=seed,
             effects=[] if effect == "none" else [effect], progress=False)
torch.set_num_threads(1)
cfg = dict(QUICK); cfg.update(steps_base=1500, steps_refit=400, hidden=64, verbose=False)
s = Settings(**cfg)
t0 = time.time()
res = run(None, settings=s, trials_loaded=load_trials(root))
print("run", time.time() - t0, [(f["effect"], f["joint"], f["estimate"], f.get("note")) for f in res["report"]["findings"]])
flat, base, ref = res["flat"], res["base"], res["ref"]
held = flat.index("held")
e_ref = sq_errors(ref, flat, held).sum(1)
phys_acc = [(e["effect"], flat.joints.index(e["joint"])) for e in res["results"] if e["status"] == "accepted" and e.get("parametric") and e.get("decision_gain", {}).get("scale", "").startswith("parametric")]
print("physics-first accepted", phys_acc)
# reconstruct the phys object is not returned; rebuild from estimates in entries
class P: pass
from exolan.diagnose import physics
for key in phys_acc:
    e = next(x for x in res["results"] if (x["effect"], flat.joints.index(x["joint"])) == key)
    m = physics.TermEstimate(**e["parametric"])
    ph = P(); ph.estimates = {key: m}; ph.forms = {}
    t1 = time.time()
    ext = physics_path.extended_model(base, flat, s, [key], ph, refit_terms_frozen)
    e_ext = sq_errors(ext, flat, held).sum(1)
    d = (e_ext - e_ref)
    b = stats.bootstrap_mean(d, n_boot=400)
    print(key, "held at", m.estimate, "(form ignored)", "ext-ref", b["mean"], b["ci"], "rel", b["mean"] / e_ref.mean(), f"{time.time()-t1:.0f}s")
