"""Twelve clean drives with a 0.1 mm encoder: physics first must accept nothing."""
import numpy as np
from exolan.diagnose import physics
from exolan.diagnose.candidates import FITTED
from exolan.diagnose.flat import prepare
from exolan.diagnose.synthetic import servo_trial
false = 0
for seed in range(200, 212):
    rng = np.random.default_rng(seed)
    truth = dict(mass=float(rng.uniform(80, 110)), viscous=0.0, coulomb=0.0, offset=float(rng.uniform(-5, -1)))
    tr = servo_trial("clean", seed=seed, seconds=10.0, encoder_step=1e-4, **truth)
    res = physics.identify(prepare([tr]), FITTED, [0])
    print(seed, res.accepted, flush=True); false += bool(res.accepted)
print("false", false)
