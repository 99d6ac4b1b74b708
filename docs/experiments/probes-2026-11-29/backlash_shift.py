"""How well a state shift by a side signal s(t) describes what a backlash does to the measured kinematics.

    python backlash_shift.py WIDTH [THRESHOLDS]      (e.g. 0.04 0.05,0.1,0.2)

One simulated user, the knee of one leg, 20 s of walk, run, squat, sit-to-stand and jump in place, recorded twice
with the same seeds and noise: clean and with a backlash (play operator) of WIDTH rad on the knee encoder. Both
recordings go through physics first's own differentiation (4th-order zero-phase low-pass 25 Hz, central
differences); D = backlash − clean in q, q̇, q̈. Each is regressed on the same processing of two side signals:

- `tanh`: s = tanh(q̇ / 0.2), the direction of motion as a smooth sign;
- `dwell`: s = sign(q̇) outside the dwells (|q̇| < threshold), and across a dwell that ends in a reversal the
  constant-acceleration path 1 − 2 (t/T)² of the true angle through the gap (the play operator holds the
  measured angle while the limb crosses the gap);
- `raw dwell`: the same path across the dwells found in the *raw* angle: runs of samples whose step stays within
  k √2 σ, σ the encoder noise (robust SD of the angle minus its 40 Hz low-pass), that end in a reversal.

A backlash of width w moves the measured angle by −(w/2) s, so a perfect s gives θ = −w/2 with R² = 1 in all three.
"""
import sys

import numpy as np
from scipy import signal

from exolan.world.anthropometry import make_users
from exolan.world.effects import Effect
from exolan.world.generate import DT, ENC_NOISE_DEG, FS, TrialWorld

TASKS = ("walk", "run", "squat", "sit_to_stand", "jump_in_place")
SOS = signal.butter(4, 25.0, fs=FS, output="sos")


def recorded_knee(user, task, effects):
    world = TrialWorld(user, task, np.random.default_rng(7), effects)
    t = np.arange(int(20 * FS)) * DT
    q = world.evaluate(t)["q_meas"][:, 0, 1]
    return q + np.radians(np.random.default_rng(99).normal(0, ENC_NOISE_DEG, len(t)))


def kinematics(q):
    qf = signal.sosfiltfilt(SOS, q)
    qd = np.gradient(qf, DT)
    return qf, qd, np.gradient(qd, DT)


def dwell_side(qd, thr):
    s = np.sign(qd).astype(float)
    slow = np.abs(qd) < thr
    i, n = 0, len(qd)
    while i < n:
        if not slow[i]:
            i += 1
            continue
        j = i
        while j < n and slow[j]:
            j += 1
        before = s[i - 1] if i > 0 else 0.0
        after = s[j] if j < n else before
        k = np.arange(1, j - i + 1)
        if before != 0 and after == -before:
            s[i:j] = before * (1 - 2 * (k / (j - i + 1)) ** 2)
        else:
            s[i:j] = before if before != 0 else after
        i = j
    return s


def raw_dwell_side(q, qd, k):
    r = q - signal.sosfiltfilt(signal.butter(4, 40.0, fs=FS, output="sos"), q)
    sigma = 1.4826 * np.median(np.abs(r - np.median(r)))
    s = np.sign(qd).astype(float)
    flat = np.abs(np.diff(q)) < k * sigma * np.sqrt(2)      # the step i -> i + 1 within the noise
    i, n = 1, len(q)
    while i < n - 1:
        if not flat[i]:
            i += 1
            continue
        j = i
        while j < n - 1 and flat[j]:
            j += 1
        before, after = np.sign(q[i] - q[max(i - 3, 0)]), np.sign(q[min(j + 3, n - 1)] - q[j])
        if j - i >= 2 and before != 0 and after == -before:
            s[i:j + 1] = before * (1 - 2 * (np.arange(j - i + 1) / (j - i + 1)) ** 2)
        i = j
    return s


def regress(y, x):
    th = float(x @ y / (x @ x))
    return th, 1 - float(np.var(y - th * x) / np.var(y))


def main():
    width = float(sys.argv[1])
    thresholds = [float(v) for v in (sys.argv[2] if len(sys.argv) > 2 else "0.05,0.1,0.2").split(",")]
    user = make_users(1, np.random.default_rng(3))[0]
    print(f"backlash {width} rad: perfect θ = {-width / 2:.4f}")
    for task in TASKS:
        kc = kinematics(recorded_knee(user, task, []))
        qb = recorded_knee(user, task, [Effect("backlash", "knee", width)])
        kb = kinematics(qb)
        D = [b - c for b, c in zip(kb, kc)]
        sides = ({"tanh": np.tanh(kb[1] / 0.2)} | {f"dwell {t}": dwell_side(kb[1], t) for t in thresholds}
                 | {f"raw k={k}": raw_dwell_side(qb, kb[1], k) for k in (3, 4)})
        for name, s in sides.items():
            ks = kinematics(s)
            cells = [f"{lab}: θ {th:+.4f} R² {r2:.2f}" for lab, (th, r2) in
                     zip(("q", "q̇", "q̈"), (regress(d, x) for d, x in zip(D, ks)))]
            print(f"{task:14s} {name:10s} " + "  ".join(cells) + f"  (rms Δq̈ {np.std(D[2]):.1f} rad/s²)")


if __name__ == "__main__":
    main()
