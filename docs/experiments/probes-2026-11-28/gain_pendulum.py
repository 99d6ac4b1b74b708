import sys, numpy as np
from types import SimpleNamespace
from exolan.diagnose import physics
from exolan.diagnose.flat import prepare

def gain_pendulum(rng, k, misfit):
    dt, T = 0.005, 8000
    t = np.arange(T) * dt
    wave = lambda n, a, f: sum(rng.uniform(*a) * np.sin(2 * np.pi * rng.uniform(*f) * t + rng.uniform(0, 6)) for _ in range(n))
    q = wave(4, (0.1, 0.3), (0.3, 1.5))
    qdd = np.gradient(np.gradient(q, dt), dt)
    D = 0.3 * qdd + 4.0 * np.sin(q) + misfit * np.sin(8 * q)       # the last part: no column of the base
    lag = 6
    applied = 0.5 * np.concatenate([np.full(lag, D[0]), D[:-lag]]) + wave(3, (0.1, 0.3), (0.5, 3.0))
    te = k * applied                                      # the exo torque as recorded (the sensor's gain k)
    tau = D + (te - applied) + 0.02 * rng.standard_normal(T)
    return SimpleNamespace(subject="S", task="bench", name="p", side="", mass=1.0, dt=dt, joints=("knee",),
                           joint_types=("revolute",), q=q[:, None], qd=np.gradient(q, dt)[:, None], qdd=qdd[:, None],
                           tau=tau[:, None], tau_e=te[:, None], f_v=np.zeros(T), cop=np.full((T, 2), np.nan),
                           valid=np.ones(T, bool))

for arg in sys.argv[1:]:
    k, mis = map(float, arg.split(","))
    for seed in range(3):
        rng = np.random.default_rng(seed)
        res = physics.identify(prepare([gain_pendulum(rng, k, mis)]), ("viscous_damping", "torque_gain"), [0])
        print(k, mis, seed, res.summary(("knee",)), "|", res.status.get(("torque_gain", 0)))
