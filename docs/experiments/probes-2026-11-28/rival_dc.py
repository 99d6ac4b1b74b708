"""Would a Coulomb friction, put in an accepted damping's place (or the reverse), make it ambiguous in the physics
path's rival rule? (significant at the rival threshold, not worse on held-out data, a constant of the joint)"""
import sys, warnings, numpy as np
warnings.simplefilter("ignore")
from exolan.diagnose import physics, physics_subjects, consistency, ident
from exolan.diagnose.procedure import load_trials
from exolan.diagnose.flat import prepare
from exolan.diagnose.settings import Settings
s = Settings()
root, jn = sys.argv[1], sys.argv[2]
flat = prepare(load_trials(root), max_delay=s.max_delay, seed=s.seed)
j = flat.joints.index(jn)
phys = physics.setup(flat, s.effects, [j], alpha=s.alpha, cutoff_hz=s.cutoff_hz, max_delay=s.max_delay)
physics.select(phys, flat, n_boot=200, joints=[j])
terms = [e for e, jj in phys.accepted if jj == j]
print(root.split('/')[-1], "accepted", [(e, round(phys.estimates[(e, j)].estimate, 4)) for e in terms])
prob, cur = phys._probs[j], phys._fits[j]
thr = s.alpha / phys.family
for e, rv in (("viscous_damping", "coulomb_friction"), ("coulomb_friction", "viscous_damping")):
    if e not in terms or rv in terms:
        continue
    alt = prob.fit([x if x != e else rv for x in terms])
    p = physics._p(prob, alt, rv)
    cons = consistency.across_trials(prob, alt, rv, rv in alt.split, flat)["consistent"]
    d = physics._held_gain(prob.held_sq(alt), prob.held_sq(cur), 400)
    print(f"  {rv} in {e}'s place: p {p:.3g} (thr {thr:.3g}), consistent {cons}, held-out advantage of {e} {d['gain']:.3g} {d['ci']} ->",
          "ambiguous" if (p <= thr and cons is not False and d['ci'][0] <= 0) else "kept")
