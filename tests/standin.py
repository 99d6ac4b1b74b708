"""A stand-in backend for the study's orchestration tests: the documented backend interface (simulate, load, split,
context features, train) over a tiny synthetic world and closed-form least-squares "models", so that planning,
resuming and the report are exercised in seconds (`exolan reproduce --backend standin:StandInBackend`)."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from exolan.data import Trial
FakeTrial = Trial            # real Trial records (the data contract), filled by least-squares stand-ins

TRAIN_TASKS = ("walk", "stand", "calisthenics", "push_pull", "jump_in_place", "turn", "cut")


def fake_world(users=6, tasks=TRAIN_TASKS + ("run", "squat", "ball_toss"), T=160, seed=0):
    rng = np.random.default_rng(seed)
    trials = []
    for u in range(users):
        mass = 60 + 5 * u
        for k, task in enumerate(tasks):
            for side in ("l", "r"):
                t = np.arange(T) * 0.005
                w = 2 * np.pi * (0.8 + 0.15 * k)
                ph = rng.uniform(0, 2 * np.pi, 2)
                amp = np.array([0.5, 0.8]) * (0.5 + 0.05 * k)
                q = amp * np.sin(w * t[:, None] + ph)
                qd = amp * w * np.cos(w * t[:, None] + ph)
                qdd = -amp * w ** 2 * np.sin(w * t[:, None] + ph)
                fv = np.maximum(0, np.sin(w * t + ph[0])) * mass * 9.81
                tau = mass * (0.02 * qdd + 0.5 * np.sin(q) + 0.01 * qd) + 0.03 * fv[:, None]
                tau = tau + rng.normal(0, 0.5, tau.shape)
                valid = np.ones(T, bool)
                valid[:3] = False
                trials.append(FakeTrial(f"S{u:02d}", task, f"{task}_1_1", side, float(mass), 0.005,
                                        ("hip", "knee"), ("revolute", "revolute"), q, qd, qdd, tau,
                                        np.zeros_like(tau), fv, np.zeros((T, 2)), valid))
    return trials


class FakeModel(torch.nn.Module):
    """tau = a*qdd + W [sin q, cos q, qd, f_v, z, 1]: linear, so forward dynamics is (tau - rest)/a."""

    def __init__(self, dz, seed):
        super().__init__()
        g = torch.Generator().manual_seed(1234)
        self.dz = dz
        self.Wz = torch.nn.Parameter(torch.randn(7, dz, generator=g, dtype=torch.float64) * 0.1,
                                     requires_grad=False)
        self.a = torch.nn.Parameter(torch.ones(2, dtype=torch.float64), requires_grad=False)
        self.W = torch.nn.Parameter(torch.zeros(7 + dz, 2, dtype=torch.float64), requires_grad=False)

    def context(self, x):
        x = torch.nan_to_num(x)
        return torch.tanh(x @ self.Wz / 50.0)

    def _feat(self, q, qd, z, fv):
        return torch.cat([torch.sin(q), torch.cos(q), qd, fv[..., None] / 100, z], -1)

    def inverse(self, q, qd, qdd, z, f_v):
        return self.a * qdd + self._feat(q, qd, z, f_v) @ self.W

    def forward_dynamics(self, q, qd, tau, z, f_v):
        return (tau - self._feat(q, qd, z, f_v) @ self.W) / self.a


class StandInBackend:
    def simulate(self, out, scale):
        Path(out).mkdir(parents=True, exist_ok=True)
        (Path(out) / "fake.json").write_text(json.dumps({"users": scale.users, "seed": scale.world_seed}))

    def load(self, data_dir):
        if (Path(data_dir) / "real.json").exists():  # stand-in for shared/real: REAL01 + two other people
            trials = []
            for tr in fake_world(users=3, T=200, seed=5):
                subj = {"S00": "REAL01", "S01": "REAL02", "S02": "REAL03"}[tr.subject]
                task = tr.task if subj == "REAL01" or tr.task == "walk" else None
                if task is None:
                    continue
                if subj == "REAL01" and task in ("squat", "ball_toss"):
                    task = task + "_asym"  # unseen variants of the one person with many trials
                trials.append(dataclasses.replace(tr, subject=subj, task=task, name=f"{task}_1_1"))
            return trials
        p = Path(data_dir) / "fake.json"
        cfg = json.loads(p.read_text()) if p.exists() else {"users": 6, "seed": 0}
        return fake_world(users=cfg["users"], seed=cfg["seed"])

    def split(self, trials):
        subs = sorted({t.subject for t in trials})
        held = set(subs[len(subs) - len(subs) // 3:])
        train = [t for t in trials if t.subject not in held and t.task in TRAIN_TASKS]
        seen = [t for t in trials if t.subject in held and t.task in TRAIN_TASKS]
        unseen = [t for t in trials if t.subject in held and t.task not in TRAIN_TASKS]
        return train, seen, unseen

    def context_features(self, tr):
        return np.concatenate([tr.q, tr.qd, tr.f_v[:, None], tr.cop], 1)

    def task_groups(self):
        return {"walk": "cyclic", "run": "cyclic"}

    def train(self, spec, train, run_dir, data_dir, device, threads):
        dz = 0 if spec.arch in ("mlp", "delan") else 3
        m = FakeModel(dz, spec.seed)
        ckpt = Path(run_dir) / "model.pt"
        if ckpt.exists():  # resume = reuse
            m.load_state_dict(torch.load(ckpt))
            return m
        X, Y = [], []
        with torch.no_grad():
            for tr in train:
                z = m.context(torch.as_tensor(self.context_features(tr))[None])[0]
                f = m._feat(torch.as_tensor(tr.q), torch.as_tensor(tr.qd), z, torch.as_tensor(tr.f_v))
                X.append(torch.cat([f, torch.as_tensor(tr.qdd)], 1).numpy()[tr.valid])
                Y.append(tr.tau[tr.valid])
        X, Y = np.concatenate(X), np.concatenate(Y)
        rng = np.random.default_rng(spec.seed)
        lam = 1e-3 * (1 + rng.random()) * (10 if not spec.lim else 1)
        coef = np.linalg.solve(X.T @ X + lam * len(X) * np.eye(X.shape[1]), X.T @ Y)
        with torch.no_grad():
            m.W.copy_(torch.as_tensor(coef[:-2]))
            m.a.copy_(torch.as_tensor(np.clip(np.diag(coef[-2:]), 1e-3, None)))
        torch.save(m.state_dict(), ckpt)
        return m
