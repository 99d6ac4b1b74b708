"""A revolute test bench (my own, not synthetic.py): a link swinging in a vertical plane, PD + feedforward-free
position loop tracking a reference of sine sweeps and slow ramps; plant J q'' + mgl sin q + b q' + Fc tanh(q'/vs) + off = tau."""
import json, sys
import numpy as np
seed, J, mgl, b, Fc, off = int(sys.argv[1]), *map(float, sys.argv[2:7])
out = sys.argv[7]
rng = np.random.default_rng(seed)
dt, T = 0.001, 30000
t = np.arange(T) * dt
ref = 0.5 * np.sin(2 * np.pi * 0.25 * t) + 0.25 * np.sin(2 * np.pi * 0.9 * t + 1.0) * (t > 10) \
      + 0.15 * np.sign(np.sin(2 * np.pi * 0.1 * t)) * (t > 20)
ref = np.convolve(ref, np.ones(80) / 80, mode="same")
w = 2 * np.pi * 6.0
kp, kd = J * w * w * 3, 2 * 0.8 * J * w * 3
q = np.zeros(T); tau = np.zeros(T)
qs, vs_, h = 0.0, 0.0, dt / 10
noise = np.zeros(T); e = rng.standard_normal(T) * 0.08 * np.sqrt(1 - 0.9 ** 2)
for k in range(1, T): noise[k] = 0.9 * noise[k - 1] + e[k]
vref = np.gradient(ref, dt)
for k in range(T):
    qm = np.round(qs / 1e-4) * 1e-4
    vm = (qm - q[k - 1]) / dt if k else 0.0
    q[k] = qm
    tau[k] = kp * (ref[k] - qm) + kd * (vref[k] - vm) + mgl * np.sin(qm) + noise[k]
    for _ in range(10):
        a = (tau[k] - mgl * np.sin(qs) - b * vs_ - Fc * np.tanh(vs_ / 1e-3) - off) / J
        vs_ += a * h; qs += vs_ * h
tau_rec = tau + 0.05 * rng.standard_normal(T)
np.savetxt(out + ".csv", np.column_stack([t, q, tau_rec]), delimiter=",", fmt="%.9g", header="time,q_j,tau_j", comments="")
json.dump({"joints": [{"name": "j", "type": "revolute"}], "units": {"q": "rad", "tau": "N m"}}, open(out + ".json", "w"))
print("q range", q.min(), q.max(), "qd rms", np.gradient(q, dt).std(), "tau rms", tau.std())
