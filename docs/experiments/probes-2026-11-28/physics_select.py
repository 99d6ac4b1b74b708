"""Physics first alone on a world (setup + select, both joints, no gate): what it accepts and the strap/gain statuses."""
import sys, time, warnings
warnings.simplefilter("ignore")
from exolan.diagnose import physics
from exolan.diagnose.procedure import load_trials
from exolan.diagnose.flat import prepare
from exolan.diagnose.settings import Settings
s = Settings()
flat = prepare(load_trials(sys.argv[1]), max_delay=s.max_delay, seed=s.seed)
t0 = time.time()
res = physics.setup(flat, s.effects, [0, 1], alpha=s.alpha, cutoff_hz=s.cutoff_hz, max_delay=s.max_delay)
physics.select(res, flat, n_boot=200)
print(sys.argv[1], round(time.time() - t0, 1), "s")
print(res.summary(flat.joints))
for (e, j), (st, why) in res.status.items():
    if e in ("strap_compliance", "torque_gain"):
        print(" ", e, flat.joints[j], st, "-", why[:200])
