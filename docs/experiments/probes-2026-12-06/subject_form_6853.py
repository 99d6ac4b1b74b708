import numpy as np, sys
from exolan.world import simulate
from exolan.diagnose import physics, physics_subjects
from exolan.diagnose.procedure import load_trials
from exolan.diagnose.flat import prepare
from exolan.diagnose.settings import FITTED
from exolan.diagnose.subjects import carriers
root = sys.argv[1] if len(sys.argv) > 1 else "w6853"
import os
if not os.path.exists(root):
    simulate(root, users=2, tasks="walk,squat,calisthenics,turn", seconds=16, seed=6853, progress=False,
             effects=["viscous_damping:knee:1.4619:S01", "viscous_damping:knee:2.853:S02"])
flat = prepare(load_trials(root), max_delay=0.1, seed=0)
res = physics.identify(flat, FITTED, [0, 1], log=print)
print("accepted", res.accepted)
users, row_user = flat.user_index()
for (e, j) in res.accepted:
    prob = res._probs[j]; prob.split = {}
    shared = prob.fit(res._fits[j].terms, intervals=False)
    masks = [(row_user == k).astype(float) for k in range(len(users))]
    th, se, split = prob.fit_split(shared, e, masks)
    print(e, j, "θ by subject", th, "se", se)
    print(" carriers", carriers(e, users, th, se))
    print(" form", {k: v for k, v in (physics_subjects.form_of(prob, shared, e, users, row_user, flat, 400) or {}).items() if k != "fit"})
    g = physics._held_gain(prob.held_sq(shared), prob.held_sq(split), 400)
    print(" held-out advantage of the split", g)
    hs, hp = prob.held_sq(shared), prob.held_sq(split)
    print(" held-out MSE shared", np.nanmean(hs), "split", np.nanmean(hp), "rows", np.isfinite(hs).sum())
