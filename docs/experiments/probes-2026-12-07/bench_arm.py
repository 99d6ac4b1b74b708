"""A 2-link vertical arm (my own generator): links with centre-of-mass offsets and own inertia, PD tracking,
friction planted on joint 2 only (viscous b2, Coulomb Fc2); joint 1 clean. Layout 2, 500 Hz."""
import json, sys
import numpy as np
seed, b2, Fc2 = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]); out = sys.argv[4]
rng = np.random.default_rng(seed)
m1, m2, l1, c1, c2, I1, I2, g = 3.0, 2.0, 0.45, 0.2, 0.18, 0.06, 0.03, 9.81
def M(q):
    a = I1 + I2 + m1 * c1**2 + m2 * (l1**2 + c2**2 + 2 * l1 * c2 * np.cos(q[1]))
    bb = I2 + m2 * (c2**2 + l1 * c2 * np.cos(q[1]))
    return np.array([[a, bb], [bb, I2 + m2 * c2**2]])
def bias(q, v):
    h = m2 * l1 * c2 * np.sin(q[1])
    cor = np.array([-h * (2 * v[0] * v[1] + v[1]**2), h * v[0]**2])
    gr = np.array([(m1 * c1 + m2 * l1) * g * np.sin(q[0]) + m2 * c2 * g * np.sin(q[0] + q[1]), m2 * c2 * g * np.sin(q[0] + q[1])])
    return cor + gr
dt, T, sub = 0.002, 20000, 8
t = np.arange(T) * dt
ref = np.stack([0.6 * np.sin(2 * np.pi * 0.2 * t) + 0.2 * np.sin(2 * np.pi * 0.7 * t + 0.5),
                0.8 + 0.5 * np.sin(2 * np.pi * 0.33 * t + 1.0) + 0.2 * np.sin(2 * np.pi * 1.1 * t)], 1)
vref = np.gradient(ref, dt, axis=0)
kp, kd = np.array([250.0, 80.0]), np.array([25.0, 6.0])
q = np.zeros((T, 2)); tau = np.zeros((T, 2)); qs = ref[0].copy(); vs = np.zeros(2); h = dt / sub
noise = np.zeros((T, 2)); e = rng.standard_normal((T, 2)) * np.array([0.15, 0.06]) * np.sqrt(1 - 0.9**2)
for k in range(1, T): noise[k] = 0.9 * noise[k - 1] + e[k]
for k in range(T):
    qm = np.round(qs / 2e-4) * 2e-4
    vm = (qm - q[k - 1]) / dt if k else np.zeros(2)
    q[k] = qm
    tau[k] = kp * (ref[k] - qm) + kd * (vref[k] - vm) + bias(qm, np.zeros(2)) + noise[k]
    for _ in range(sub):
        fr = np.array([0.0, b2 * vs[1] + Fc2 * np.tanh(vs[1] / 1e-3)])
        a = np.linalg.solve(M(qs), tau[k] - bias(qs, vs) - fr)
        vs = vs + a * h; qs = qs + vs * h
tau_rec = tau + 0.03 * rng.standard_normal((T, 2))
np.savetxt(out + ".csv", np.column_stack([t, q, tau_rec]), delimiter=",", fmt="%.9g", header="time,q_sh,q_el,tau_sh,tau_el", comments="")
json.dump({"joints": [{"name": "sh", "type": "revolute"}, {"name": "el", "type": "revolute"}], "units": {"q": "rad", "tau": "N m"}}, open(out + ".json", "w"))
print("q", q.min(0), q.max(0), "qd rms", np.gradient(q, dt, axis=0).std(0), "tau rms", tau.std(0))
