"""Robustness of physics first on a 1-DoF drive against perturbations a real drive has (probe, not a test)."""
import sys, json, time, numpy as np
from scipy.signal import butter, filtfilt
from exolan.diagnose.synthetic import _plateau_reference, write_layout2
from exolan.data import load
from exolan.diagnose import physics
from exolan.diagnose.candidates import FITTED
from exolan.diagnose.flat import prepare

def drive(seed, dt=0.001, seconds=25.0, mass=95.0, viscous=200.0, coulomb=20.0, offset=-3.0, stribeck=0.0, vs=0.01,
          cog=0.0, cog_period=0.02, lag=0.0, drift=0.0, asym=0.0, current_noise=3.0, force_noise=1.0, substeps=10):
    rng = np.random.default_rng(seed)
    x_ref, v_ref = _plateau_reference(dt)
    T = int(round(seconds / dt)); reps = int(np.ceil(T / len(x_ref)))
    x_ref = np.tile(x_ref, reps)[:T]; v_ref = np.tile(v_ref, reps)[:T]
    w = 2 * np.pi * 10.0; kp, kd = mass * w * w, 2 * 0.7 * mass * w
    phi = 0.95; n_cl = np.zeros(T); e = rng.standard_normal(T) * current_noise * np.sqrt(1 - phi ** 2)
    for t in range(1, T): n_cl[t] = phi * n_cl[t - 1] + e[t]
    x = np.zeros(T); F = np.zeros(T); xs = vs_ = 0.0; h = dt / substeps
    for t in range(T):
        xm = np.round(xs / 1e-6) * 1e-6; vm = (xm - x[t - 1]) / dt if t else 0.0; x[t] = xm
        F[t] = kp * (x_ref[t] - xm) + kd * (v_ref[t] - vm) + n_cl[t]
        b = viscous * (1 + drift * t / T)
        for _ in range(substeps):
            fc = coulomb * (1 + asym * np.sign(vs_)) + stribeck * coulomb * np.exp(-(vs_ / vs) ** 2)
            a = (F[t] - b * vs_ - fc * np.tanh(vs_ / 1e-3) - offset - cog * np.sin(2 * np.pi * xs / cog_period)) / mass
            vs_ += a * h; xs += vs_ * h
    Fm = F.copy()
    if lag > 0:       # the recorded force through a first-order lag (current loop, sensor)
        al = dt / (lag + dt)
        for t in range(1, T): Fm[t] = Fm[t - 1] + al * (F[t] - Fm[t - 1])
    return np.arange(T) * dt, x, Fm + force_noise * rng.standard_normal(T)

def plain_ls(t, x, F, cut=20.0):
    dt = t[1] - t[0]; bb, aa = butter(4, cut * 2 * dt)
    xf = filtfilt(bb, aa, x); Ff = filtfilt(bb, aa, F)
    v = np.gradient(xf, dt); a = np.gradient(v, dt)
    A = np.column_stack([a, v, np.sign(v) * (np.abs(v) > 0.005), np.ones_like(v)])
    n = len(t) * 3 // 4
    th = np.linalg.lstsq(A[:n], Ff[:n], rcond=None)[0]
    return dict(mass=th[0], viscous=th[1], coulomb=th[2], offset=th[3])

CASES = dict(base={}, stribeck=dict(stribeck=0.5), cog=dict(cog=5.0), lag2ms=dict(lag=0.002), lag5ms=dict(lag=0.005),
             hz500=dict(dt=0.002), hz2000=dict(dt=0.0005, substeps=5), drift=dict(drift=0.15), asym=dict(asym=0.2),
             noisy=dict(current_noise=10.0, force_noise=5.0))
seed = int(sys.argv[1]); names = sys.argv[2].split(",") if len(sys.argv) > 2 else list(CASES)
for name in names:
    t, x, F = drive(seed, **CASES[name])
    p = f"{sys.argv[3] if len(sys.argv) > 3 else '/tmp/drv'}/{name}_{seed}"; write_layout2(p, t, x, F)
    tr = list(load(p + ".csv"))
    t0 = time.time(); res = physics.identify(prepare(tr), FITTED, [0]); el = time.time() - t0
    est = {e: round(v.estimate, 3) for (e, j), v in res.estimates.items()}
    base = res.base.get("x", {}); const = base.get("const", {}).get("value") if isinstance(base, dict) else None
    print(name, "physics:", est, "mass", round(base.get("qdd0*h0", {}).get("value", float("nan")), 2), "const", const,
          f"({el:.1f} s)", "| plain LS:", {k: round(v, 2) for k, v in plain_ls(t, x, F).items()}, flush=True)
