"""Physics first alone (setup, then selection on both joints) on the main job's diagnosis data (held-out users, seen tasks): its seconds."""
import sys, time, warnings
warnings.simplefilter("ignore")
from exolan import data
from exolan.diagnose import physics
from exolan.diagnose.flat import prepare
from exolan.diagnose.settings import Settings
s = Settings()
sp = data.paper_split(data.load(sys.argv[1]))
flat = prepare(list(sp.test_seen), max_delay=s.max_delay, seed=s.seed)
t0 = time.time()
res = physics.setup(flat, s.effects, [0, 1], alpha=s.alpha, cutoff_hz=s.cutoff_hz, max_delay=s.max_delay)
t1 = time.time()
physics.select(res, flat, n_boot=200)
print(sys.argv[2], "setup", round(t1 - t0, 1), "select", round(time.time() - t1, 1), res.summary(flat.joints)[:80])
