"""Evaluation: held-out torque errors, forward dynamics and open-loop rollouts, physics checks.

All figures are in SI units squared and *not* mass-normalised: torque MSE in N² m², q̈ MSE in rad²/s⁴,
q MSE in rad², q̇ MSE in rad²/s². Every trial is encoded from its start in one causal pass, as the Rust
streaming encoder does.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from .rollout import free_rollout, rollout
from .data import context_features, load, paper_split
from .runio import load_run, write_json

HORIZONS = (4, 10, 20)


def _dtype(model) -> torch.dtype:
    return next(model.parameters()).dtype


def _device(model) -> torch.device:
    return next(model.parameters()).device


def trial_tensors(model, trial) -> dict:
    """The trial's arrays as tensors of the model's dtype (invalid samples zeroed) and its z sequence."""
    dt, dev = _dtype(model), _device(model)
    valid = np.asarray(trial.valid, dtype=bool)
    clean = lambda a: torch.as_tensor(np.where(valid.reshape(-1, *([1] * (np.ndim(a) - 1))), a, 0.0),
                                      dtype=dt, device=dev)
    ctx = torch.as_tensor(np.asarray(context_features(trial), dtype=np.float64), dtype=dt, device=dev)
    with torch.no_grad():
        z = model.context(ctx.unsqueeze(0))[0]
    return dict(q=clean(trial.q), qd=clean(trial.qd), qdd=clean(trial.qdd), tau=clean(trial.tau),
                f_v=clean(trial.f_v), z=z, valid=torch.as_tensor(valid, device=dev))


def predict_torque(model, trial) -> np.ndarray:
    """Predicted total actuated torque (T, n), NaN where the sample is not valid."""
    d = trial_tensors(model, trial)
    with torch.no_grad():
        tau = model.inverse(d["q"], d["qd"], d["qdd"], d["z"], d["f_v"])
    out = tau.double().cpu().numpy()
    out[~np.asarray(trial.valid, dtype=bool)] = np.nan
    return out


class _Acc:
    """Sums of squared errors per joint, grouped."""

    def __init__(self, n):
        self.n = n
        self.sse: dict[str, np.ndarray] = {}
        self.cnt: dict[str, int] = {}

    def add(self, key, sq: np.ndarray) -> None:
        self.sse[key] = self.sse.get(key, np.zeros(self.n)) + sq.sum(axis=0)
        self.cnt[key] = self.cnt.get(key, 0) + sq.shape[0]

    def result(self, key, joints) -> dict:
        c = self.cnt.get(key, 0)
        if c == 0:
            return dict(mse=float("nan"), per_joint={j: float("nan") for j in joints}, n=0)
        pj = self.sse[key] / c
        return dict(mse=float(pj.mean()), per_joint={j: float(v) for j, v in zip(joints, pj)}, n=int(c))


def torque_errors(model, trials) -> dict:
    """Torque MSE (N² m²) over the valid samples: overall, per joint, per task (with per joint)."""
    if not trials:
        return dict(mse=float("nan"), per_joint={}, per_task={}, n=0, var=float("nan"), r2=float("nan"))
    joints = list(trials[0].joints)
    acc = _Acc(len(joints))
    taus = []
    for t in trials:
        tau_hat = predict_torque(model, t)
        v = np.asarray(t.valid, dtype=bool)
        sq = (tau_hat[v] - t.tau[v]) ** 2
        acc.add("all", sq)
        acc.add(t.task, sq)
        taus.append(t.tau[v])
    res = acc.result("all", joints)
    tau_all = np.concatenate(taus)
    var = tau_all.var(axis=0)
    res["var"] = float(var.mean())
    res["r2"] = float(1.0 - np.mean(np.array(list(res["per_joint"].values())) / var))
    res["per_task"] = {k: acc.result(k, joints) for k in sorted(acc.cnt) if k != "all"}
    return res


def forward_errors(model, trials, horizons: Sequence[int] = HORIZONS, stride: int = 5) -> dict:
    """q̈ MSE over valid samples and q, q̇ MSE after each horizon of open-loop semi-implicit Euler from
    start points every `stride` samples whose following max(horizons) samples are valid. The rollouts of
    all trials run as one batch (the horizon loop is sequential, so few large steps beat many small ones)."""
    joints = list(trials[0].joints)
    Hmax = max(horizons)
    acc = _Acc(len(joints))
    seq = {k: [] for k in ("tau", "z", "f_v", "q", "qd")}
    dt = float(trials[0].dt)
    for t in trials:
        d = trial_tensors(model, t)
        v = d["valid"]
        with torch.no_grad():
            qdd_hat = model.forward_dynamics(d["q"], d["qd"], d["tau"], d["z"], d["f_v"])
        acc.add("qdd", ((qdd_hat - d["qdd"])[v] ** 2).double().cpu().numpy())
        if len(t.q) <= Hmax:
            continue
        ok = np.lib.stride_tricks.sliding_window_view(np.asarray(t.valid, dtype=bool), Hmax + 1).all(axis=1)
        starts = np.nonzero(ok)[0][::stride]
        if len(starts) == 0:
            continue
        st = torch.as_tensor(starts, device=v.device)
        steps = st.unsqueeze(1) + torch.arange(Hmax + 1, device=v.device)
        for k in seq:
            seq[k].append(d[k][steps])
    if seq["q"]:
        cat = {k: torch.cat(v) for k, v in seq.items()}
        with torch.no_grad():
            q_hat, qd_hat = rollout(model, cat["q"][:, 0], cat["qd"][:, 0], cat["tau"][:, :Hmax], dt,
                                    cat["z"][:, :Hmax], cat["f_v"][:, :Hmax])
        for h in horizons:
            acc.add(f"q{h}", ((q_hat[:, h] - cat["q"][:, h]) ** 2).double().cpu().numpy())
            acc.add(f"qd{h}", ((qd_hat[:, h] - cat["qd"][:, h]) ** 2).double().cpu().numpy())
    out = {"qdd": acc.result("qdd", joints)}
    out["q"] = {str(h): acc.result(f"q{h}", joints) for h in horizons}
    out["qd"] = {str(h): acc.result(f"qd{h}", joints) for h in horizons}
    return out


class torch_threads:
    """Limit torch's CPU threads inside a block. Evaluation is made of small sequential ops (rollout
    steps, one trial at a time) where extra threads only add synchronisation, badly so on a shared CPU."""

    def __init__(self, n: int | None):
        self.n = n

    def __enter__(self):
        self.old = torch.get_num_threads()
        if self.n:
            torch.set_num_threads(self.n)

    def __exit__(self, *exc):
        torch.set_num_threads(self.old)


def evaluate(model, trials, horizons: Sequence[int] = HORIZONS, stride: int = 5, threads: int | None = 1) -> dict:
    """{"torque": torque_errors, "forward": forward_errors (DeLaN-based models only), "n_trials"}.

    torque: mse, per_joint, per_task {task: {mse, per_joint, n}}, n, var (torque variance), r2.
    forward: qdd {mse, per_joint, n}; q and qd {"4"|"10"|"20": {mse, per_joint, n}}."""
    model.eval()
    with torch_threads(threads):
        res = {"torque": torque_errors(model, trials), "n_trials": len(trials)}
        if getattr(model, "is_lagrangian", False) and trials:
            res["forward"] = forward_errors(model, trials, horizons, stride)
    return res


def physics_check(model, trials, max_samples: int = 20000, n_rollouts: int = 16, seconds: float = 1.0,
                  seed: int = 0, threads: int | None = 1) -> dict:
    """H positive definite with its condition number range on the data's states; energy conservation of
    the conservative model (τ = 0, no LIM, z frozen at a recorded value) under semi-implicit Euler, at the
    data's dt and at dt/4 (the drift of a first-order integrator shrinks about linearly with dt)."""
    if not getattr(model, "is_lagrangian", False):
        return {}
    with torch_threads(threads):
        return _physics_check(model, trials, max_samples, n_rollouts, seconds, seed)


def _physics_check(model, trials, max_samples, n_rollouts, seconds, seed) -> dict:
    rng = np.random.default_rng(seed)
    qs, qds, zs = [], [], []
    for t in trials:
        d = trial_tensors(model, t)
        v = d["valid"]
        qs.append(d["q"][v]); qds.append(d["qd"][v]); zs.append(d["z"][v])
    q, qd, z = torch.cat(qs), torch.cat(qds), torch.cat(zs)
    pick = torch.as_tensor(rng.choice(len(q), size=min(max_samples, len(q)), replace=False), device=q.device)
    with torch.no_grad():
        H = model.delan.inertia(q[pick], z[pick])
        eig = torch.linalg.eigvalsh(H.double())
    cond = (eig[:, -1] / eig[:, 0]).cpu().numpy()
    res = dict(n_states=int(len(pick)), min_eigenvalue=float(eig[:, 0].min()),
               max_eigenvalue=float(eig[:, -1].max()), positive_definite=bool((eig[:, 0] > 0).all()),
               cond_min=float(cond.min()), cond_median=float(np.median(cond)), cond_max=float(cond.max()))
    dt = float(trials[0].dt)
    sel = torch.as_tensor(rng.choice(len(q), size=min(n_rollouts, len(q)), replace=False), device=q.device)
    # float64 so that the drift measured is the integrator's, not round-off
    m64 = _as_double(model)
    q0, qd0, z0 = q[sel].double(), qd[sel].double(), z[sel].double()
    energy = {}
    for label, h in (("dt", dt), ("dt/4", dt / 4)):
        steps = int(round(seconds / h))
        with torch.no_grad():
            _, _, T, V = free_rollout(m64, q0, qd0, h, steps, z0)
        E = T + V
        drift = (E - E[:, :1]).abs().amax(dim=1)
        # the energy exchanged between T and V sets the scale (T_0 alone is ~0 for a start at rest)
        scale = T.amax(dim=1).clamp_min(1e-9)
        rel = (drift / scale).cpu().numpy()
        finite = bool(torch.isfinite(E).all())
        energy[label] = dict(dt=h, steps=steps, max_abs_drift_J=float(drift.max()),
                             median_rel_drift=float(np.median(rel)), max_rel_drift=float(rel.max()),
                             finite=finite)
    res["energy"] = energy
    res["energy_note"] = ("relative drift = max_k |E_k − E_0| / max_k T_k over a free rollout (no input, no LIM) of "
                          f"{seconds} s from {len(sel)} recorded states; semi-implicit Euler is first order, "
                          "so the drift should shrink roughly 4x from dt to dt/4")
    return res


def _as_double(model):
    import copy

    m = copy.deepcopy(model)
    return m.double()


# -- command line ----------------------------------------------------------------------------------

def _table(res: dict) -> str:
    lines = []
    for part in ("seen", "unseen"):
        r = res.get(part)
        if not r or not r["torque"]["n"]:
            continue
        tq = r["torque"]
        joints = list(tq["per_joint"])
        lines.append(f"== {part} tasks, held-out users: torque MSE [N² m²]  (R² {tq['r2']:.3f}, "
                     f"{r['n_trials']} trials, {tq['n']} samples)")
        lines.append(f"  {'task':<22}{'all':>12}" + "".join(f"{j:>12}" for j in joints))
        lines.append(f"  {'(all)':<22}{tq['mse']:>12.4g}" + "".join(f"{tq['per_joint'][j]:>12.4g}" for j in joints))
        for task, t in tq["per_task"].items():
            lines.append(f"  {task:<22}{t['mse']:>12.4g}" + "".join(f"{t['per_joint'][j]:>12.4g}" for j in joints))
        fw = r.get("forward")
        if fw:
            hs = list(fw["q"])
            head = f"  {'q̈ [rad²/s⁴]':<14}" + "".join(f"{'q'+h:>11}{'q̇'+h:>11}" for h in hs)
            vals = f"  {fw['qdd']['mse']:<14.4g}" + "".join(f"{fw['q'][h]['mse']:>11.3g}{fw['qd'][h]['mse']:>11.3g}" for h in hs)
            lines += ["  forward dynamics (q [rad²], q̇ [rad²/s²] after k open-loop steps):", head, vals]
    pc = res.get("physics")
    if pc:
        lines.append(f"== physics: H positive definite on {pc['n_states']} states: {pc['positive_definite']}, "
                     f"cond(H) in [{pc['cond_min']:.3g}, {pc['cond_max']:.3g}] (median {pc['cond_median']:.3g})")
        for k, e in pc["energy"].items():
            lines.append(f"   free rollout at {k} = {e['dt']:.4g} s, {e['steps']} steps: energy drift / max T median "
                         f"{e['median_rel_drift']:.3g}, max {e['max_rel_drift']:.3g}")
    return "\n".join(lines)


def evaluate_run(run_dir, data, horizons: Sequence[int] = HORIZONS, threads: int | None = 1) -> dict:
    """Load a run and evaluate it on the held-out users of `data` (a directory or a Split)."""
    with torch_threads(threads):
        return _evaluate_run(run_dir, data, horizons)


def _evaluate_run(run_dir, data, horizons) -> dict:
    model, meta = load_run(run_dir)
    if isinstance(data, (str, Path)):
        split = paper_split(load(data))
    else:
        split = data
    res = dict(run=str(run_dir), method=meta["spec"]["method"], lim=meta["spec"]["lim"], epochs=meta["epoch"],
               seen=evaluate(model, list(split.test_seen), horizons),
               unseen=evaluate(model, list(split.test_unseen), horizons))
    held_out = list(split.test_seen) + list(split.test_unseen)
    if model.is_lagrangian and held_out:
        res["physics"] = physics_check(model, held_out)
    return res


def cli_evaluate(args) -> int:
    res = evaluate_run(args.run, args.data)
    out = Path(args.out) if args.out else Path(args.run) / "evaluation.json"
    write_json(out, res)
    print(_table(res))
    print(f"-> {out}")
    return 0
