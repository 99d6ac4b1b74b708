import sys, numpy as np
from exolan.world import simulate
from exolan.diagnose import physics, physics_subjects
from exolan.diagnose.procedure import load_trials
from exolan.diagnose.flat import prepare
from exolan.diagnose.candidates import FITTED
from pathlib import Path
seed = int(sys.argv[1]); out = Path(sys.argv[2])
large = float(np.round(2.0 + (seed % 1000) / 1000.0, 4)); small = float(sys.argv[3])
sizes = {"S01": small, "S02": large} if seed % 2 else {"S01": large, "S02": small}
if not (out / "world").exists():
    simulate(out / "world", users=2, tasks="walk,squat,calisthenics,turn", seconds=16, seed=seed, progress=False,
             effects=[f"viscous_damping:knee:{v}:{u}" for u, v in sizes.items()])
flat = prepare(load_trials(out / "world"), max_delay=0.1, seed=0)
res = physics.setup(flat, FITTED, [0, 1])
physics.select(res, flat, n_boot=200, joints=[1])
print(sizes, res.summary(flat.joints))
users, row_user = flat.user_index()
prob = res._probs[1]
print("split at selection:", list(prob.split)); prob.split = {}
shared = prob.fit(res._fits[1].terms, intervals=False)
masks = [(row_user == k).astype(float) for k in range(len(users))]
th, se, split = prob.fit_split(shared, "viscous_damping", masks)
print("by subject", users, th, se)
g = physics._held_gain(prob.held_sq(shared), prob.held_sq(split), 400)
print("held-out advantage of the split", g["gain"], g["ci"])
print("form", {k: v for k, v in (physics_subjects.form_of(prob, shared, "viscous_damping", users, row_user, flat, 400) or {}).items() if k in ("kind", "advantage_over_shared", "heterogeneity")})
