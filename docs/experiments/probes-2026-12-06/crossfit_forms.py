"""Probe: a physics-first subject form judged on the held-out segments alone (the rule until 2026-12-06) and
cross-fitted over every segment (`JointProblem.cross_sq`, the rule since), on two-user knee-damping worlds.

    python crossfit_forms.py OUT SEED:S01:S02 [SEED:S01:S02 ...]      (a size 0: that user without the damping)

Each world: `exolan simulate`'s 2 users x walk, squat, calisthenics, turn x 16 s (the slow suite's), physics first
on both joints, then every accepted linear term's split by subject: θ ± HAC SE, and its advantage over the shared
term, (N m/kg)², mean [95 % block-bootstrap CI], both ways."""
import sys
import time
from pathlib import Path

import numpy as np

from exolan.diagnose import physics
from exolan.diagnose.flat import prepare
from exolan.diagnose.procedure import load_trials
from exolan.diagnose.settings import FITTED
from exolan.world import simulate


def world(out: Path, seed: int, sizes: dict) -> Path:
    root = out / f"w{seed}_{'_'.join(f'{u}{v}' for u, v in sizes.items())}"
    if not root.exists():
        simulate(root, users=2, tasks="walk,squat,calisthenics,turn", seconds=16, seed=seed, progress=False,
                 effects=[f"viscous_damping:knee:{v}:{u}" for u, v in sizes.items() if v])
    return root


def probe(root: Path) -> None:
    flat = prepare(load_trials(root), max_delay=0.1, seed=0)
    res = physics.identify(flat, FITTED, [0, 1])
    users, row_user = flat.user_index()
    print(root.name, "accepted", res.accepted, flush=True)
    for e, j in res.accepted:
        prob = res._probs[j]
        prob.split = {}
        shared = prob.fit(res._fits[j].terms, intervals=False)
        masks = [(row_user == k).astype(float) for k in range(len(users))]
        th, se, split = prob.fit_split(shared, e, masks)
        one = physics._held_gain(prob.held_sq(shared), prob.held_sq(split), 400)
        cross = physics._held_gain(prob.cross_sq(shared), prob.cross_sq(shared, e, masks), 400)
        print(f"  {e} on joint {j}: θ {np.round(th, 3)} ± {np.round(se, 3)}; held-out segments "
              f"{one['gain']:.3g} [{one['ci'][0]:.3g}, {one['ci'][1]:.3g}]; cross-fitted "
              f"{cross['gain']:.3g} [{cross['ci'][0]:.3g}, {cross['ci'][1]:.3g}]", flush=True)


if __name__ == "__main__":
    out = Path(sys.argv[1])
    for spec in sys.argv[2:]:
        seed, a, b = spec.split(":")
        t0 = time.time()
        probe(world(out, int(seed), {"S01": float(a), "S02": float(b)}))
        print(f"  {time.time() - t0:.0f} s", flush=True)
