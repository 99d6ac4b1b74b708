"""What dissipation a world without any effect shows to a base that cannot imitate one: the residual of the
world's own leg (its true segments) fed (a) what the recordings hold (recorded q, q̇, q̈, τ, the vertical insole
force at the recorded CoP, plain gravity, the pelvis-relative hip angle) and (b) the true inputs (the pelvis'
tilt and acceleration, the horizontal ground force), regressed per joint on q̇ and tanh(q̇/ε): alone, per task, and
beside a flexible linear base (per-trial constants; every product of the hip's and knee's cos/sin terms with
1, q̈, q̇ products and f_v; no column odd in q̇). Reads the simulator's truth (a probe, not the diagnosis).

    python true_leg_background.py WORLD SEED        # a world of `exolan simulate --users 4 --seconds 20`
"""
import sys

import numpy as np

from exolan.data import load
from exolan.world import dynamics as dyn
from exolan.world.reference import TrueTrial, true_legs

EPS = 0.01          # the world's and the candidate's Coulomb smoothing (rad/s)


def residuals(tr, p, seed):
    """(q̇, r_recorded, r_true) on a trial's valid rows: τ minus the true leg's inverse dynamics."""
    tt = TrueTrial(4, seed, 20.0, tr.subject, tr.task, tr.side)
    v = tr.valid
    t = np.nonzero(v)[0]
    q, qd, qdd, tau, fv = tr.q[v], tr.qd[v], tr.qdd[v], tr.tau[v], tr.f_v[v]
    cop = np.where(fv > 0, np.nan_to_num(tr.cop[v, 0] if tr.cop.ndim == 2 else tr.cop[v]), 0.0)
    f = np.stack([np.zeros_like(fv), fv], -1)
    tau_c = np.where((fv > 0)[:, None], dyn.contact_torque(p, q, dyn.cop_point(p, q, cop), f), 0.0)
    r_rec = tau - (dyn.inverse_dynamics(p, q, qd, qdd) - tau_c)
    zero = np.zeros(len(t))
    off = [np.stack([x[t], zero], -1) for x in (tt.tilt, tt.tilt_d, tt.tilt_dd)]
    r_true = tau - (dyn.inverse_dynamics(p, q - off[0], qd - off[1], qdd - off[2], g_eff=tt.g_eff[t]) - tt.tau_c[t])
    return qd, r_rec, r_true


def base_features(tr):
    v = tr.valid
    q, qd, qdd, fv = tr.q[v], tr.qd[v], tr.qdd[v], tr.f_v[v]
    cop = np.nan_to_num(tr.cop[v, 0] if tr.cop.ndim == 2 else tr.cop[v])
    one = np.ones(len(q))
    a = [one, np.cos(q[:, 0]), np.sin(q[:, 0]), np.cos(q.sum(1)), np.sin(q.sum(1)), np.cos(q[:, 1]), np.sin(q[:, 1])]
    b = [one, qdd[:, 0], qdd[:, 1], qd[:, 0] ** 2, qd[:, 1] ** 2, qd[:, 0] * qd[:, 1], fv, fv * cop]
    return np.stack([x * y for x in a for y in b], -1)


def sizes(parts, j, cols, flexible):
    X, y = [], []
    for i, (qd, r, F) in enumerate(parts):
        c = [qd[:, j] if k == "b" else np.tanh(qd[:, j] / EPS) for k in cols]
        extra = [F, np.eye(len(parts))[i][None, :].repeat(len(qd), 0)] if flexible else [np.ones((len(qd), 1))]
        X.append(np.concatenate([np.stack(c, -1)] + extra, 1))
        y.append(r[:, j])
    X, y = np.concatenate(X), np.concatenate(y)
    th = np.linalg.lstsq(X, y, rcond=None)[0]
    return np.round(th[:len(cols)], 3)


def main(world: str, seed: int) -> None:
    ds = load(world)
    legs = true_legs(4, seed)
    data = {"recorded": [], "true": []}
    for tr in ds.trials:
        qd, r_rec, r_true = residuals(tr, legs[tr.subject], seed)
        F = base_features(tr)
        data["recorded"].append((tr.task, (qd, r_rec, F)))
        data["true"].append((tr.task, (qd, r_true, F)))
    for mode, rows in data.items():
        parts = [p for _, p in rows]
        for j, name in enumerate(("hip", "knee")):
            for flexible in (False, True):
                got = {" ".join(c): sizes(parts, j, c, flexible) for c in (["b"], ["fc"], ["b", "fc"])}
                print(f"{mode:8s} {name:4s} {'flexible base' if flexible else 'constant only'}: {got}")
        for task in sorted({t for t, _ in rows}):
            part = [p for t, p in rows if t == task]
            print(f"   {mode:8s} {task:14s} hip b {sizes(part, 0, ['b'], False)} Fc {sizes(part, 0, ['fc'], False)}"
                  f"  knee b {sizes(part, 1, ['b'], False)} Fc {sizes(part, 1, ['fc'], False)}")


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]))
