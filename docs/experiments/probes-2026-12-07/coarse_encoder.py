"""The project's drive (`servo_drive`) with a coarse encoder (argv: encoder step in m, Coulomb in N, first seed): physics
first on four draws, what it accepts and why the frictions are or are not taken (docs/DIAGNOSIS.md, "Noise above the fit's band")."""
import sys, numpy as np
from exolan.diagnose import physics
from exolan.diagnose.candidates import FITTED
from exolan.diagnose.flat import prepare
from exolan.diagnose.synthetic import servo_trial
fn, fc = float(sys.argv[1]), float(sys.argv[2])
for seed in range(int(sys.argv[3]), int(sys.argv[3]) + 4):
    rng = np.random.default_rng(seed)
    truth = dict(mass=float(rng.uniform(80, 110)), viscous=float(rng.uniform(150, 250)), coulomb=fc, offset=-3.0)
    tr = servo_trial("d", seed=seed, encoder_step=fn, **truth)
    res = physics.identify(prepare([tr]), FITTED, [0])
    print(seed, [(e, round(res.estimates[(e, j)].estimate, 3)) for e, j in res.accepted], "truth v", round(truth["viscous"], 1), "c", fc, flush=True)
    print("   ", {k: v for k, v in res.status.items() if k[0] in ("coulomb_friction", "stribeck_friction")})
    print("   ", [ (t.get("effect") if isinstance(t, dict) else t) for t in res.tests][:6])
