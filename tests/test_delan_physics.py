"""DeLaN recovers known physics: trained on exact torques of an analytic two-link pendulum (no noise, no
context, no contact), it finds the inertia, the gravity torque and an accurate forward model.
Slow (a few minutes of training): run with `pytest -m slow tests/test_delan_physics.py`."""
import numpy as np
import pytest
import torch

from exolan.data import Trial
from exolan.evaluate import evaluate
from exolan.train import load_run, train

G = 9.81
M1, M2, L1, LC1, LC2, I1, I2 = 7.0, 4.0, 0.45, 0.2, 0.25, 0.12, 0.06


def true_terms(q, qd):
    c2, s2 = np.cos(q[:, 1]), np.sin(q[:, 1])
    H11 = I1 + I2 + M1 * LC1 ** 2 + M2 * (L1 ** 2 + LC2 ** 2 + 2 * L1 * LC2 * c2)
    H12 = I2 + M2 * (LC2 ** 2 + L1 * LC2 * c2)
    H22 = np.full_like(c2, I2 + M2 * LC2 ** 2)
    H = np.stack([np.stack([H11, H12], -1), np.stack([H12, H22], -1)], -2)
    h = M2 * L1 * LC2 * s2
    c = np.stack([-h * (2 * qd[:, 0] * qd[:, 1] + qd[:, 1] ** 2), h * qd[:, 0] ** 2], 1)
    g = np.stack([M1 * G * LC1 * np.sin(q[:, 0]) + M2 * G * (L1 * np.sin(q[:, 0]) + LC2 * np.sin(q[:, 0] + q[:, 1])),
                  M2 * G * LC2 * np.sin(q[:, 0] + q[:, 1])], 1)
    return H, c, g


def trials(n, seed, T=2000, dt=0.005):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        t = np.arange(T) * dt
        q, qd, qdd = np.zeros((T, 2)), np.zeros((T, 2)), np.zeros((T, 2))
        for j in range(2):
            for k in range(1, 4):
                a, w, ph = rng.normal() * 0.5 / k, 2 * np.pi * rng.uniform(0.3, 1.2) * k, rng.uniform(0, 6.3)
                q[:, j] += a * np.sin(w * t + ph)
                qd[:, j] += a * w * np.cos(w * t + ph)
                qdd[:, j] -= a * w * w * np.sin(w * t + ph)
        H, c, g = true_terms(q, qd)
        tau = np.einsum("tij,tj->ti", H, qdd) + c + g
        z = np.zeros(T)
        out.append(Trial(subject=f"P{i}", task="swing", name=f"swing_{i}", side="", mass=1.0, dt=dt,
                         joints=("hip", "knee"), joint_types=("revolute", "revolute"), q=q, qd=qd, qdd=qdd,
                         tau=tau, tau_e=np.zeros_like(tau), f_v=z, cop=np.full((T, 2), np.nan),
                         valid=np.ones(T, bool)))
    return out


@pytest.mark.slow
def test_delan_recovers_two_link_pendulum(tmp_path):
    train_set, test_set = trials(12, 0), trials(3, 1)
    rd = train(train_set, "delan", lim=False, epochs=150, seed=0, out=tmp_path / "run", progress=False,
               batch_size=2048, weight_decay=0.0, w_fd=1e-3, threads=1, physics_check=False)
    model, _ = load_run(rd)
    res = evaluate(model, test_set)
    assert res["torque"]["r2"] > 0.995, res["torque"]
    q = np.concatenate([t.q for t in test_set])
    qd = np.concatenate([t.qd for t in test_set])
    H, c, g = true_terms(q, qd)
    with torch.no_grad():
        Hm, cm, gm = (x.double().numpy() for x in model.terms(torch.as_tensor(q, dtype=torch.float32),
                                                              torch.as_tensor(qd, dtype=torch.float32)))
    rel = lambda a, b: np.linalg.norm(a - b) / np.linalg.norm(b)
    print(f"torque R² {res['torque']['r2']:.5f}; relative error H {rel(Hm, H):.3g}, g {rel(gm, g):.3g}, "
          f"c {rel(cm, c):.3g}; q MSE after 20 steps {res['forward']['q']['20']['mse']:.3g} rad²")
    assert rel(Hm, H) < 0.05 and rel(gm, g) < 0.03 and rel(cm, c) < 0.15, (rel(Hm, H), rel(gm, g), rel(cm, c))
    assert res["forward"]["q"]["20"]["mse"] < 1e-3
