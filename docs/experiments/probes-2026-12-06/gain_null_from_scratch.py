"""Usage: python docs/experiments/probes-2026-12-06/gain_null_from_scratch.py WORLD JOINT_INDEX LAG

Rule 3's track-lag null for a gain, fitted from scratch: the gain on the recorded exo torque against the same on
the exo torque LAG samples ahead, both with the networks fitted from scratch (the reference's recipe); held-out
per-sample squared error, mass-normalised, unweighted; their paired gain (`rules.paired_gain`)."""
import sys, time
import numpy as np, torch
from exolan.diagnose.settings import Settings
from exolan.diagnose.procedure import load_trials
from exolan.diagnose.flat import prepare
from exolan.diagnose.procedure import new_base
from exolan.diagnose.refits import fresh_fit
from exolan.diagnose.nulls import advanced
from exolan.diagnose.fit import predict
from exolan.diagnose.rules import paired_gain
from exolan.diagnose.workers import Workers, running

root, j, lag = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
s = Settings()
torch.manual_seed(s.seed)
flat = prepare(load_trials(root), max_delay=s.max_delay, seed=s.seed)
start = new_base(flat, s)
k = np.zeros(flat.n, dtype=int); k[j] = lag
adv = advanced(flat, k)
held = flat.index("held")
t0 = time.time()
w = Workers(2)
with running(w):
    m_now, m_fut = w.map([lambda: fresh_fit(flat, s, [("torque_gain", j)], {"torque_gain": 1.5}, start),
                          lambda: fresh_fit(adv, s, [("torque_gain", j)], {"torque_gain": 1.5}, start)])
print(f"fits {time.time() - t0:.0f} s; gain now {float(m_now.estimate('torque_gain', j)):.4f}, "
      f"ahead {float(m_fut.estimate('torque_gain', j)):.4f}")
m = flat.mass[held].numpy()[:, None]
e_now = (((flat.tau[held] - predict(m_now, flat, held)).numpy() / m) ** 2).sum(1)
e_fut = (((adv.tau[held] - predict(m_fut, adv, held)).numpy() / m) ** 2).sum(1)
g = paired_gain(e_fut, e_now, s)     # > 0: the gain on the recorded torque describes the held-out data better
print(f"now beats ahead by {g['gain']:.3g} [{g['ci'][0]:.3g}, {g['ci'][1]:.3g}] (unweighted, the diagnosis' block "
      f"bootstrap, block {g['block']})")
