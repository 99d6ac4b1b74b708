"""physics.identify on a world: the selection's records and its time (run from a tree's python/ on sys.path)."""
import json, sys, time
from exolan.diagnose.procedure import load_trials
from exolan.diagnose.flat import prepare
from exolan.diagnose.settings import Settings
from exolan.diagnose import physics
from exolan.diagnose.workers import Workers, running
s = Settings()
flat = prepare(load_trials(sys.argv[1]), max_delay=s.max_delay, seed=s.seed)
w = Workers(2)
t0 = time.time()
with running(w):
    res = physics.identify(flat, s.effects, [0, 1], alpha=s.alpha, cutoff_hz=s.cutoff_hz, max_delay=s.max_delay)
print("seconds", round(time.time() - t0, 1))
out = dict(tests=res.tests, status={f"{e}:{j}": v for (e, j), v in res.status.items()}, accepted=res.accepted)
json.dump(out, open(sys.argv[2], "w"), default=str, indent=0, sort_keys=True)
