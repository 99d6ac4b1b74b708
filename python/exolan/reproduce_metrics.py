"""Evaluation of one trained model for the reproduce sweep: rollout errors, plot arrays, task identification."""
from __future__ import annotations

import numpy as np

from .study import PLOT_TASKS, Scale

def _model_dtype(model):
    import torch
    for p in model.parameters():
        return p.dtype
    return torch.float32


def _t(x, dtype):
    import torch
    return torch.as_tensor(np.asarray(x), dtype=dtype)


def _context(model, backend, tr, dtype):
    import torch
    x = backend.context_features(tr)
    with torch.no_grad():
        z = model.context(_t(x, dtype)[None])[0]
    return z


def _inverse(model, tr, z, dtype) -> np.ndarray:
    import torch
    with torch.no_grad():
        tau = model.inverse(_t(tr.q, dtype), _t(tr.qd, dtype), _t(tr.qdd, dtype), z, _t(tr.f_v, dtype))
    return tau.double().numpy()


def _forward(model, q, qd, tau, z, f_v):
    import torch
    with torch.no_grad():
        return model.forward_dynamics(q, qd, tau, z, f_v)


def _fd_metrics(model, items, dtype, scale: Scale) -> list[dict]:
    """Per trial: q̈ MSE on every valid sample, and open-loop rollout errors (semi-implicit Euler with the
    recorded τ, z and f_v, DESIGN section 5) from start points every `rollout_stride` samples."""
    def forward(q, qd, tau, z, fv, cop_x, owner, t):
        args = (_t(a, dtype) for a in (q, qd, tau, z, fv))
        return _forward(model, *args).double().numpy()

    return rollout_metrics(forward, [(split, tr, z.double().numpy()) for split, tr, z in items], scale)


def reference_fd_rows(items, scale: Scale, mode: str) -> list[dict]:
    """`_fd_metrics` of the world's true leg under one of exolan.world.reference.MODES of inputs."""
    from exolan.world import reference

    if mode == "recorded":
        legs = reference.true_legs(scale.users, scale.world_seed)
        params = [legs[tr.subject] for _, tr, _ in items]
    else:
        truths = [reference.TrueTrial(scale.users, scale.world_seed, scale.seconds, tr.subject, tr.task, tr.side)
                  for _, tr, _ in items]

    def forward(q, qd, tau, z, fv, cop_x, owner, t):
        out = np.empty_like(q)
        for j in np.unique(owner):                     # one leg per trial
            m = owner == j
            out[m] = (reference.recorded_forward(params[j], q[m], qd[m], tau[m], fv[m], cop_x[m]) if mode == "recorded"
                      else truths[j].forward(q[m], qd[m], tau[m], t[m], mode == "true inputs"))
        return out

    return rollout_metrics(forward, items, scale)


def rollout_metrics(forward, items, scale: Scale) -> list[dict]:
    """q̈ MSE and open-loop rollout errors of any forward dynamics `forward(q, qd, tau, z, f_v, cop_x, owner, t)`
    -> q̈ (numpy rows; `owner` = each row's item index, `t` its sample index in that trial). The rollouts of all
    trials run as one batch (a few forward-dynamics calls instead of thousands)."""
    H = max(scale.horizons)
    rows, Q0, QD0, TAU, Z, FV, CX, QT, QDT, owner, T0 = [], [], [], [], [], [], [], [], [], [], []
    for j, (split, tr, z) in enumerate(items):
        z = np.zeros((len(tr.q), 0)) if z is None else z
        cx = tr.cop[:, 0]
        qdd_hat = forward(tr.q, tr.qd, tr.tau, z, tr.f_v, cx, np.full(len(tr.q), j), np.arange(len(tr.q)))
        ok = tr.valid
        e = (qdd_hat - tr.qdd) ** 2
        n_j = tr.q.shape[1]
        rows.append({"subject": tr.subject, "task": tr.task, "split": split, "dt": float(tr.dt),
                     "n_qdd": int(ok.sum()),
                     "sse_qdd": np.where(ok[:, None], e, 0.0).sum(axis=0).tolist(),
                     "horizons": {str(h): {"n": 0, "sse_q": [0.0] * n_j, "sse_qd": [0.0] * n_j, "nonfinite": 0}
                                  for h in scale.horizons}})
        T = len(tr.q)
        if T <= H:
            continue
        # a start is usable when every sample it touches is valid
        win_ok = np.convolve(ok.astype(int), np.ones(H + 1, int), "valid") == H + 1
        starts = np.flatnonzero(win_ok)[:: scale.rollout_stride]
        if len(starts) == 0:
            continue
        w = starts[:, None] + np.arange(H + 1)[None]
        Q0.append(tr.q[starts]); QD0.append(tr.qd[starts])
        TAU.append(tr.tau[w[:, :H]]); FV.append(tr.f_v[w[:, :H]]); Z.append(z[w[:, :H]]); CX.append(cx[w[:, :H]])
        QT.append(tr.q[w]); QDT.append(tr.qd[w])
        owner.append(np.full(len(starts), j))
        T0.append(starts)
    if not owner:
        return rows
    Q0, QD0, TAU, FV, Z, CX, QT, QDT, owner, T0 = (np.concatenate(a) for a in (Q0, QD0, TAU, FV, Z, CX, QT, QDT, owner,
                                                                               T0))
    dt = float(items[0][1].dt)
    for a in range(0, len(owner), 20000):  # bounded memory on the paper's world
        sl = slice(a, a + 20000)
        qs, qds = Q0[sl], QD0[sl]
        for k in range(H):
            qdd_k = forward(qs, qds, TAU[sl, k], Z[sl, k], FV[sl, k], CX[sl, k], owner[sl], T0[sl] + k)
            qds = qds + dt * qdd_k
            qs = qs + dt * qds
            h = k + 1
            if h not in scale.horizons:
                continue
            with np.errstate(over="ignore", invalid="ignore"):
                eq = (qs - QT[sl, h]) ** 2
                eqd = (qds - QDT[sl, h]) ** 2
            bad = ~(np.isfinite(eq).all(1) & np.isfinite(eqd).all(1))
            # diverged rollouts count as infinite error: dropping them would flatter the model
            eq[bad] = np.inf
            eqd[bad] = np.inf
            own = owner[sl]
            for j in np.unique(own):
                m = own == j
                r = rows[j]["horizons"][str(h)]
                r["n"] += int(m.sum())
                r["nonfinite"] += int(bad[m].sum())
                r["sse_q"] = [float(x) for x in np.asarray(r["sse_q"]) + eq[m].sum(0)]
                r["sse_qd"] = [float(x) for x in np.asarray(r["sse_qd"]) + eqd[m].sum(0)]
    return rows


def _pick(trials, task, prefer_side="l"):
    cands = [t for t in trials if t.task == task]
    if not cands:
        return None
    cands.sort(key=lambda t: (t.subject, t.side != prefer_side, t.name))
    return cands[0]


def _plot_arrays(model, backend, spec, tests, zcache, dtype, scale) -> dict[str, np.ndarray]:
    """Arrays for the figures, from the first seed's models only (figures show one seed)."""
    out: dict[str, np.ndarray] = {}
    alltests = [(s, i, t) for s, ts in tests.items() for i, t in enumerate(ts)]

    def z_of(tr):
        for s, i, t in alltests:
            if t is tr:
                return zcache[(s, i)]
        return _context(model, backend, tr, dtype)

    if spec.arch in ("exolan", "mlp-tcn") and spec.lim and spec.w_fd == 0 and spec.w_ms == 0:
        tasks = [t for t in PLOT_TASKS if any(x.task == t for _, _, x in alltests)]
        # fill up to four tasks with what the held-out set offers (small worlds may lack some)
        for _, _, x in alltests:
            if len(tasks) >= 4:
                break
            if x.task not in tasks:
                tasks.append(x.task)
        for task in tasks[:4]:
            tr = _pick([x for _, _, x in alltests], task)
            pred = _inverse(model, tr, z_of(tr), dtype)
            n = min(len(tr.q), int(round(3.0 / tr.dt)))  # first 3 s
            out[f"torque/{task}/t"] = np.arange(n) * tr.dt
            out[f"torque/{task}/meas"] = tr.tau[:n]
            out[f"torque/{task}/pred"] = pred[:n]
            out[f"torque/{task}/subject"] = np.array(tr.subject)
    if spec.arch == "exolan" and spec.lim:
        tests_all = [x for _, _, x in alltests]
        for task in ("walk", "squat", "run"):
            tr = _pick(tests_all, task)
            if tr is None:
                continue
            z = z_of(tr)
            qdd_hat = _forward(model, _t(tr.q, dtype), _t(tr.qd, dtype), _t(tr.tau, dtype), z,
                               _t(tr.f_v, dtype)).double().numpy()
            n = min(len(tr.q), int(round(2.0 / tr.dt)))
            out[f"acc/{task}/t"] = np.arange(n) * tr.dt
            out[f"acc/{task}/meas"] = tr.qdd[:n]
            out[f"acc/{task}/pred"] = qdd_hat[:n]
        tr = _pick(tests_all, "walk") or tests_all[0]
        out.update(_rollout_arrays(model, tr, z_of(tr), dtype))
    return out


def _rollout_arrays(model, tr, z, dtype, n_starts=4, H=40) -> dict[str, np.ndarray]:
    """Open-loop rollouts of H steps (200 ms at 200 Hz) from a few evenly spaced starts of one trial."""
    import torch
    T = len(tr.q)
    ok = tr.valid
    cand = [s for s in range(0, max(T - H - 1, 0)) if ok[s:s + H + 1].all()]
    if not cand:
        return {}
    starts = np.array([cand[int(i)] for i in np.linspace(0, len(cand) - 1, n_starts)])
    q, qd, tau, fv = (_t(a, dtype) for a in (tr.q, tr.qd, tr.tau, tr.f_v))
    idx = torch.as_tensor(starts)
    qs, qds = q[idx].clone(), qd[idx].clone()
    Q, QD = [qs.double().numpy()], [qds.double().numpy()]
    for k in range(H):
        qdd_k = _forward(model, qs, qds, tau[idx + k], z[idx + k], fv[idx + k])
        qds = qds + tr.dt * qdd_k
        qs = qs + tr.dt * qds
        Q.append(qs.double().numpy())
        QD.append(qds.double().numpy())
    steps = np.arange(H + 1)
    return {
        "roll/starts": starts, "roll/dt": np.array(tr.dt), "roll/task": np.array(tr.task),
        "roll/q_pred": np.stack(Q, 1), "roll/qd_pred": np.stack(QD, 1),
        "roll/q_meas": np.stack([tr.q[s + steps] for s in starts]),
        "roll/qd_meas": np.stack([tr.qd[s + steps] for s in starts]),
        "roll/trace_t": np.arange(min(T, starts[-1] + H + 20)) * tr.dt,
        "roll/trace_q": tr.q[: min(T, starts[-1] + H + 20)],
        "roll/trace_qd": tr.qd[: min(T, starts[-1] + H + 20)],
    }


def _task_identification(model, backend, train, dtype, seed: int, scale: Scale) -> dict:
    """z over the training trajectories -> task label with an MLP 3 x 64 (ReLU), softmax cross-entropy
    with inverse-training-frequency class weights (the paper's protocol). Two 80/20 splits per seed:
    by sample (as the paper) and by trajectory (no temporal leakage: neighbouring samples share z)."""
    rng = np.random.default_rng(seed)
    Z, Y, G = [], [], []
    tasks = sorted({t.task for t in train})
    for gi, tr in enumerate(train):
        z = _context(model, backend, tr, dtype).double().numpy()
        ok = np.flatnonzero(tr.valid & np.isfinite(z).all(1))
        if len(ok) == 0:
            continue
        take = ok if len(ok) <= scale.taskid_per_trial else np.sort(rng.choice(ok, scale.taskid_per_trial, False))
        Z.append(z[take])
        Y.append(np.full(len(take), tasks.index(tr.task)))
        G.append(np.full(len(take), gi))
    Z, Y, G = np.concatenate(Z), np.concatenate(Y), np.concatenate(G)
    out = {"tasks": tasks, "n_samples": int(len(Y))}
    # split 1: samples
    perm = rng.permutation(len(Y))
    n_tr = int(0.8 * len(Y))
    out["sample_split"] = _classify(Z, Y, perm[:n_tr], perm[n_tr:], len(tasks), seed, scale)
    # split 2: whole trajectories
    # stratified by task: 80 % of each task's trajectories train, so every task appears on both sides
    g_tr = set()
    for c in range(len(tasks)):
        gs = rng.permutation(np.unique(G[Y == c]))
        g_tr.update(gs[: max(1, int(round(0.8 * len(gs))))].tolist())
    m = np.array([g in g_tr for g in G])
    out["trajectory_split"] = _classify(Z, Y, np.flatnonzero(m), np.flatnonzero(~m), len(tasks), seed, scale)
    out["tasks_names_majority"] = {k: tasks[v["majority_class"]] for k, v in out.items()
                                   if isinstance(v, dict) and "majority_class" in v}
    return out


def _classify(Z, Y, itr, ite, k, seed, scale: Scale) -> dict:
    import torch
    from torch import nn
    g = torch.Generator().manual_seed(seed)
    mu, sd = Z[itr].mean(0), Z[itr].std(0) + 1e-8
    Xtr = torch.as_tensor((Z[itr] - mu) / sd, dtype=torch.float32)
    Xte = torch.as_tensor((Z[ite] - mu) / sd, dtype=torch.float32)
    ytr, yte = torch.as_tensor(Y[itr]), torch.as_tensor(Y[ite])
    counts = np.bincount(Y[itr], minlength=k).astype(float)
    w = np.where(counts > 0, counts.sum() / np.maximum(counts, 1) / k, 0.0)
    torch.manual_seed(seed)
    net = nn.Sequential(nn.Linear(Z.shape[1], 64), nn.ReLU(), nn.Linear(64, 64), nn.ReLU(),
                        nn.Linear(64, 64), nn.ReLU(), nn.Linear(64, k))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3, weight_decay=1e-4, fused=True)
    lossf = nn.CrossEntropyLoss(weight=torch.as_tensor(w, dtype=torch.float32))
    bs = 4096
    for _ in range(scale.taskid_epochs):
        perm = torch.randperm(len(ytr), generator=g)
        for a in range(0, len(ytr), bs):
            b = perm[a:a + bs]
            opt.zero_grad()
            loss = lossf(net(Xtr[b]), ytr[b])
            loss.backward()
            opt.step()
    with torch.no_grad():
        acc = float((net(Xte).argmax(1) == yte).float().mean())
    maj = int(np.argmax(counts))
    return {"accuracy": acc, "majority_accuracy": float((Y[ite] == maj).mean()), "majority_class": maj,
            "n_train": int(len(itr)), "n_test": int(len(ite))}
