"""The paper's numbers, aggregation of the runs' results, paired statistics and the claims' verdicts.

Statistics. Each claim compares two methods on the same held-out people. The unit of the paired test is
the held-out user: a user's MSE is pooled over that user's samples and averaged over seeds (the seeds
estimate training noise; the users are what the claim generalises over). The test is the Wilcoxon
signed-rank test (scipy.stats.wilcoxon, two-sided, exact for small n): per-user MSEs are skewed and
heteroscedastic across people, so a rank test is safer than a paired t-test; with 7 users its smallest
attainable p is 1/64 ~ 0.016. Where there are at least two seeds, a paired t-test over seeds (each seed's
pooled MSE; scipy.stats.ttest_rel) is reported beside it and must agree: a claim "holds" when our change has
the paper's sign, p < 0.05 over users and (with ≥ 2 seeds) over seeds, and its size is at least a quarter of the
paper's relative change (``verdict``). Every user is scored with the same seed's model, so a change that training
noise alone can flip is "significant" over users; the seeds are the replicates of training.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..study import ARCHITECTURES, LABELS, is_cyclic


# ----------------------------------------------------------------------------------------------------
# The paper's published numbers (real EPIC-lab data; Schulze et al. 2026). Labelled wherever printed.
# ----------------------------------------------------------------------------------------------------
PAPER: dict[str, Any] = {
    "source": "Schulze et al., ExoLaN (2026), real EPIC-lab exoskeleton data",
    "intention_relative": {
        "seen: ExoLaN+LIM vs TCN+LIM": -0.02, "seen: ExoLaN+LIM vs MLP-TCN+LIM": -0.04,
        "unseen: ExoLaN+LIM vs MLP-TCN+LIM": -0.07, "unseen: ExoLaN+LIM vs TCN+LIM": -0.09,
        "unseen: MLP-TCN+LIM vs TCN+LIM": -0.02,
    },
    "cyclic_seen": {"tcn": 464.0, "exolan": 468.0},
    "noncyclic_seen": {"exolan": 411.0, "tcn": 450.0},
    "per_task": {"calisthenics": {"mlp-tcn": 1130.0, "exolan": 1104.0}, "run": {"mlp-tcn": 4680.0, "exolan": 2875.0},
                 "squat": {"mlp-tcn": 441.0, "exolan": 146.0}, "ball_toss": {"mlp-tcn": 605.0, "exolan": 300.0}},
    "fd": {
        "inverse": {"tau": 434, "qdd": 4.97e8, "q4": 2.78e-1, "qd4": 2352, "q10": 16.6, "qd10": 3.68e4,
                    "q20": 459, "qd20": 2.55e5},
        "w_fd": {"tau": 475, "qdd": 337, "q4": 1.41e-3, "qd4": 0.184, "q10": 7.63e-3, "qd10": 2.42,
                 "q20": 0.0817, "qd20": 79.7},
        "w_fd+w_ms": {"tau": 507, "qdd": 139, "q4": 1.38e-3, "qd4": 0.0787, "q10": 6.62e-3, "qd10": 0.900,
                      "q20": 0.0329, "qd20": 5.79},
    },
    "fd_relative": {"qdd": -0.59, "qd4": -0.57, "qd10": -0.63, "qd20": -0.93, "q20": -0.60},
    "acc_per_task": {"run": {"mlp-tcn": 2841, "exolan": 1394}, "squat": {"mlp-tcn": 194, "exolan": 68}},
    "dt": 0.005,   # 200 Hz
    "taskid": {"exolan": (0.673, 0.023), "mlp-tcn": (0.642, 0.021), "majority": 0.310,
               "majority_class": "jump_in_place"},
}

REFERENCE_KEY = "reference"
PAPER_NORM_KEY = "w_fd+w_ms (paper's normalisation)"   # trained only where the scale's ms_norm is another
FD_VARIANTS = (("inverse", 0.0, 0.0, "ExoLaN (inverse loss only)"), ("w_fd", None, 0.0, "ExoLaN (w_fd)"),
               ("w_fd+w_ms", None, None, "ExoLaN (w_fd, w_ms)"), (PAPER_NORM_KEY, None, None, "ExoLaN (w_fd, w_ms)"))

FD_COLS = ("tau", "qdd", "q4", "qd4", "q10", "qd10", "q20", "qd20")
FD_HEAD = ("τ [N²m²]", "q̈ [rad²/s⁴]", "q₄ [rad²]", "q̇₄ [rad²/s²]", "q₁₀", "q̇₁₀", "q₂₀", "q̇₂₀")


def horizon_key(h: int) -> str:
    """The forward-dynamics key of the w_fd+w_ms runs with a rollout horizon H other than the scale's first; the
    entry holds H as `ms_horizon`."""
    return f"w_fd+w_ms (H = {h})"


# ----------------------------------------------------------------------------------------------------
# Aggregation
# ----------------------------------------------------------------------------------------------------

def _mse(rows) -> float:
    n = sum(r["n"] for r in rows)
    if n == 0:
        return float("nan")
    k = len(rows[0]["sse"])
    return float(sum(sum(r["sse"]) for r in rows) / (n * k))


def _mse_joints(rows) -> list[float]:
    """MSE of each joint (hip, knee) pooled over the rows' samples."""
    n = sum(r["n"] for r in rows)
    k = len(rows[0]["sse"])
    return [float(sum(r["sse"][j] for r in rows) / n) if n else float("nan") for j in range(k)]


def _by(rows, key):
    out: dict[Any, list] = {}
    for r in rows:
        out.setdefault(key(r), []).append(r)
    return out


def _ms(values) -> tuple[float, float]:
    v = np.asarray([x for x in values], float)
    if len(v) == 0:
        return float("nan"), float("nan")
    return float(np.mean(v)), float(np.std(v, ddof=1)) if len(v) > 1 else 0.0


def torque_stats(runs: list[dict], groups: dict[str, str], splits) -> dict:
    """For one method: per split, seed-level pooled MSE (mean ± std), cyclic/non-cyclic, per task and
    per user (seed-averaged)."""
    out: dict[str, Any] = {}
    for split in splits:
        per_seed, cyc, non, tasks, users, trials = [], [], [], {}, {}, {}
        joints, task_joints = [], {}
        for r in runs:
            rows = [x for x in r["torque_rows"] if x["split"] == split]
            if not rows:
                continue
            per_seed.append(_mse(rows))
            joints.append(_mse_joints(rows))
            for t, rr in _by(rows, lambda x: x["task"]).items():
                task_joints.setdefault(t, []).append(_mse_joints(rr))
            c = [x for x in rows if is_cyclic(x["task"], groups)]
            nc = [x for x in rows if not is_cyclic(x["task"], groups)]
            cyc.append(_mse(c) if c else float("nan"))
            non.append(_mse(nc) if nc else float("nan"))
            for t, rr in _by(rows, lambda x: x["task"]).items():
                tasks.setdefault(t, []).append(_mse(rr))
            for u, rr in _by(rows, lambda x: x["subject"]).items():
                users.setdefault(u, []).append(_mse(rr))
            for k, rr in _by(rows, lambda x: f"{x['subject']}/{x.get('name', x['task'])}/{x['side']}").items():
                if sum(x["n"] for x in rr):
                    trials.setdefault(k, []).append(_mse(rr))
        out[split] = {
            "mse": _ms(per_seed), "per_seed": per_seed, "cyclic": _ms(cyc), "noncyclic": _ms(non),
            "per_task": {t: _ms(v) for t, v in sorted(tasks.items())},
            "per_joint": [_ms(v) for v in zip(*joints)],
            "per_task_joint": {t: [float(np.mean(v)) for v in zip(*jj)] for t, jj in sorted(task_joints.items())},
            "per_user": {u: float(np.mean(v)) for u, v in sorted(users.items())},
            "per_trial": {u: float(np.mean(v)) for u, v in sorted(trials.items())},
        }
    return out


def amplification(qd_mse: float, qdd_mse: float, steps: int, dt: float) -> float:
    """q̇ MSE after `steps` open-loop steps over what a persistent q̈ error of the same MSE integrates to,
    (steps·dt)² · q̈ MSE: about 1 when the per-step error is integrated as it is, below 1 when it changes sign
    within the horizon, far above 1 when errors compound through the rolled-out state."""
    return float(qd_mse / ((steps * dt) ** 2 * qdd_mse))


def fd_stats(runs: list[dict], horizons, dt: float | None = None) -> dict:
    """Per seed and per held-out user: torque, q̈ and rollout MSEs; with the sample period `dt`, the rollout
    amplification at every horizon (`amplification`)."""
    per_seed: dict[str, list] = {c: [] for c in FD_COLS}
    per_seed.update({f"amp{h}": [] for h in horizons} if dt else {})
    users: dict[str, dict[str, list]] = {}
    diverged = {str(h): [] for h in horizons}
    for r in runs:
        rows = r.get("fd_rows", [])
        if not rows:
            continue
        per_seed["tau"].append(_mse(r["torque_rows"]))
        per_seed["qdd"].append(_pooled(rows, "qdd"))
        for h in horizons:
            per_seed[f"q{h}"].append(_pooled_h(rows, h, "sse_q"))
            per_seed[f"qd{h}"].append(_pooled_h(rows, h, "sse_qd"))
            n = sum(x["horizons"][str(h)]["n"] for x in rows)
            bad = sum(x["horizons"][str(h)]["nonfinite"] for x in rows)
            diverged[str(h)].append(bad / n if n else float("nan"))
            if dt:
                per_seed[f"amp{h}"].append(amplification(per_seed[f"qd{h}"][-1], per_seed["qdd"][-1], h, dt))
        for u, rr in _by(rows, lambda x: x["subject"]).items():
            d = users.setdefault(u, {c: [] for c in FD_COLS})
            d["tau"].append(_mse([x for x in r["torque_rows"] if x["subject"] == u]))
            d["qdd"].append(_pooled(rr, "qdd"))
            for h in horizons:
                d[f"q{h}"].append(_pooled_h(rr, h, "sse_q"))
                d[f"qd{h}"].append(_pooled_h(rr, h, "sse_qd"))
    return {"mean_std": {c: _ms(v) for c, v in per_seed.items() if c in FD_COLS or v},
            "per_seed": per_seed, "diverged_fraction": {h: _ms(v) for h, v in diverged.items()},
            "per_user": {u: {c: float(np.mean(v)) for c, v in d.items() if v} for u, d in users.items()},
            **_fd_where(runs, horizons)}


def _fd_where(runs: list[dict], horizons) -> dict:
    """Where a forward-dynamics error sits: q̈ and q̇_h MSE per task (with its split) and per joint, each the
    seed mean of the seeds' pooled MSEs; per task also per joint."""
    tasks: dict[str, dict[str, list]] = {}
    split_of: dict[str, str] = {}
    joints: dict[str, list] = {}
    cols = {"qdd": lambda rr: _pooled_joints(rr, "qdd")}
    cols.update({f"qd{h}": (lambda rr, h=h: _pooled_h_joints(rr, h, "sse_qd")) for h in horizons})
    for r in runs:
        rows = r.get("fd_rows", [])
        if not rows:
            continue
        for c, f in cols.items():
            joints.setdefault(c, []).append(f(rows))
        for t, rr in _by(rows, lambda x: x["task"]).items():
            split_of[t] = rr[0]["split"]
            d = tasks.setdefault(t, {})
            for c, f in cols.items():
                d.setdefault(c, []).append(f(rr))
    with np.errstate(invalid="ignore"):
        per_joint = {c: [float(x) for x in np.mean(v, axis=0)] for c, v in joints.items()}
        per_task = {t: {"split": split_of[t],
                        **{c: float(np.mean(np.mean(v, axis=1))) for c, v in d.items()},
                        **{f"{c}_joints": [float(x) for x in np.mean(v, axis=0)] for c, v in d.items()}}
                    for t, d in sorted(tasks.items())}
    return {"per_joint": per_joint, "per_task": per_task}


def _pooled(rows, what) -> float:
    n = sum(x["n_" + what] for x in rows)
    k = len(rows[0]["sse_" + what])
    return float(sum(sum(x["sse_" + what]) for x in rows) / (n * k)) if n else float("nan")


def _per_joint(n: int, sses: list) -> list[float]:
    """Each joint's MSE from the rows' per-joint squared-error sums over n samples (nan without samples)."""
    with np.errstate(invalid="ignore", over="ignore"):
        return [float(sum(s[j] for s in sses) / n) if n else float("nan") for j in range(len(sses[0]))]


def _pooled_joints(rows, what) -> list[float]:
    return _per_joint(sum(x["n_" + what] for x in rows), [x["sse_" + what] for x in rows])


def _pooled_h_joints(rows, h, key) -> list[float]:
    hs = [x["horizons"][str(h)] for x in rows]
    return _per_joint(sum(x["n"] for x in hs), [x[key] for x in hs])


def _pooled_h(rows, h, key) -> float:
    hs = [x["horizons"][str(h)] for x in rows]
    n = sum(x["n"] for x in hs)
    k = len(hs[0][key])
    with np.errstate(invalid="ignore", over="ignore"):
        return float(sum(sum(x[key]) for x in hs) / (n * k)) if n else float("nan")


# ----------------------------------------------------------------------------------------------------
# Paired tests
# ----------------------------------------------------------------------------------------------------

def paired(a_users: dict, b_users: dict, a_seeds=None, b_seeds=None) -> dict:
    """Change of A relative to B (negative = A better for an error) with the paired tests described in
    the module docstring."""
    from scipy import stats
    common = sorted(set(a_users) & set(b_users))
    a = np.array([a_users[u] for u in common], float)
    b = np.array([b_users[u] for u in common], float)
    fin = np.isfinite(a) & np.isfinite(b)
    a, b = a[fin], b[fin]
    res: dict[str, Any] = {"n_users": int(len(a))}
    if len(a):
        res["rel_change"] = float(a.mean() / b.mean() - 1.0)
        res["users_better"] = int((a < b).sum())
    if len(a) >= 2 and np.any(a != b):
        res["p_wilcoxon_users"] = float(stats.wilcoxon(a, b, alternative="two-sided").pvalue)
    else:
        res["p_wilcoxon_users"] = float("nan")
    if a_seeds is not None and b_seeds is not None and len(a_seeds) == len(b_seeds) >= 2:
        x, y = np.asarray(a_seeds, float), np.asarray(b_seeds, float)
        if np.all(np.isfinite(x)) and np.all(np.isfinite(y)) and np.any(x != y):
            res["p_ttest_seeds"] = float(stats.ttest_rel(x, y).pvalue)
            res["rel_change_seed_mean"] = float(x.mean() / y.mean() - 1.0)
    return res


ALPHA = 0.05                 # significance over held-out users (two-sided Wilcoxon) and over seeds (paired t)
SIZE_FRACTION = 0.25         # a claim holds only at ≥ a quarter of the paper's relative change ...
DIRECTION_ONLY_SIZE = 0.05   # ... or ≥ 5 % where the paper gives a direction only


def verdict(rel: float | None, p: float, paper_rel: float | None, p_seeds: float | None = None) -> str:
    """'holds' when the change has the paper's sign, is significant and is at least a quarter of the paper's
    relative change (direction-only claims, paper_rel None: at least 5 %); else 'same direction, negligible'
    (too small, significant or not), 'same direction, not significant', or 'reversed' (with '(significant)'
    where significant). Significant: p < ALPHA over held-out users and, where there are seeds to pair
    (p_seeds given), over seeds too: users share each seed's model, so a change that training noise alone
    can flip looks significant over users (docs/RESULTS.md, "Two sweeps"). A sign alone is not a result."""
    if rel is None or not np.isfinite(rel):
        return "n/a"
    if abs(rel) < 1e-12:
        return "no difference"
    direction = -1.0 if paper_rel is None else float(np.sign(paper_rel))   # direction-only claims: lower error
    significant = bool(np.isfinite(p) and p < ALPHA)
    if p_seeds is not None and np.isfinite(p_seeds):
        significant = significant and p_seeds < ALPHA
    if np.sign(rel) != direction:
        return "reversed (significant)" if significant else "reversed, not significant"
    needed = DIRECTION_ONLY_SIZE if paper_rel is None else SIZE_FRACTION * abs(paper_rel)
    if abs(rel) < needed:
        return "same direction, negligible"
    return "holds" if significant else "same direction, not significant"


def _holds(res: dict, paper_rel: float | None) -> str:
    return verdict(res.get("rel_change"), res.get("p_wilcoxon_users", float("nan")), paper_rel,
                   res.get("p_ttest_seeds"))


def _claim(methods, split, a, b, paper_rel, title, unit="per_user"):
    if a not in methods or b not in methods:
        return None
    A, B = methods[a][split], methods[b][split]
    res = paired(A[unit], B[unit], A["per_seed"], B["per_seed"])
    if unit != "per_user":
        res["paired_over"] = unit
    return {"claim": title, "split": split, "a": a, "b": b, "paper_rel_change": paper_rel, **res,
            "verdict": _holds(res, paper_rel)}


def _intention_claims(methods) -> list[dict]:
    P = PAPER["intention_relative"]
    spec = [
        ("seen", "exolan", "tcn", P["seen: ExoLaN+LIM vs TCN+LIM"], "ExoLaN+LIM vs TCN+LIM (seen tasks)"),
        ("seen", "exolan", "mlp-tcn", P["seen: ExoLaN+LIM vs MLP-TCN+LIM"], "ExoLaN+LIM vs MLP-TCN+LIM (seen tasks)"),
        ("unseen", "exolan", "mlp-tcn", P["unseen: ExoLaN+LIM vs MLP-TCN+LIM"],
         "ExoLaN+LIM vs MLP-TCN+LIM (unseen tasks)"),
        ("unseen", "exolan", "tcn", P["unseen: ExoLaN+LIM vs TCN+LIM"], "ExoLaN+LIM vs TCN+LIM (unseen tasks)"),
        ("unseen", "mlp-tcn", "tcn", P["unseen: MLP-TCN+LIM vs TCN+LIM"], "MLP-TCN+LIM vs TCN+LIM (unseen tasks)"),
    ]
    out = [_claim(methods, s, a, b, r, t) for s, a, b, r, t in spec]
    # "LIM improves every model" (paper: yes, no per-model number given -> direction only)
    for arch in ARCHITECTURES:
        for split in ("seen", "unseen"):
            out.append(_claim(methods, split, arch, arch + "-nolim", None,
                              f"LIM improves {LABELS[arch]} ({split} tasks)"))
    # "TCN variants beat LSTM variants" (direction only)
    for a, b in (("exolan", "delan-lstm"), ("mlp-tcn", "mlp-lstm"), ("tcn", "lstm")):
        out.append(_claim(methods, "seen", a, b, None, f"{LABELS[a]}+LIM vs {LABELS[b]}+LIM (seen tasks)"))
    return [c for c in out if c is not None]


def _fd_claims(fd) -> list[dict]:
    out = []
    ms_keys = [k for k in fd if k == "w_fd+w_ms" or "ms_horizon" in fd[k]] if "w_fd" in fd else []
    for key in ms_keys:
        A, B = fd[key], fd["w_fd"]
        for col, paper_rel in PAPER["fd_relative"].items():
            au = {u: d[col] for u, d in A["per_user"].items() if col in d}
            bu = {u: d[col] for u, d in B["per_user"].items() if col in d}
            res = paired(au, bu, A["per_seed"][col], B["per_seed"][col])
            out.append({"claim": f"multi-step loss lowers {col} MSE ({key} vs w_fd)", "metric": col,
                        "paper_rel_change": paper_rel, **res, "verdict": _holds(res, paper_rel)})
    if "inverse" in fd and "w_fd" in fd:
        A, B = fd["w_fd"], fd["inverse"]
        for col in ("qdd", "q20", "qd20"):
            au = {u: d[col] for u, d in A["per_user"].items() if col in d}
            bu = {u: d[col] for u, d in B["per_user"].items() if col in d}
            res = paired(au, bu, A["per_seed"][col], B["per_seed"][col])
            pr = PAPER["fd"]["w_fd"][col] / PAPER["fd"]["inverse"][col] - 1
            out.append({"claim": f"forward loss lowers {col} MSE (w_fd vs inverse only)", "metric": col,
                        "paper_rel_change": pr, **res, "verdict": _holds(res, pr)})
        au = {u: d["tau"] for u, d in A["per_user"].items()}
        bu = {u: d["tau"] for u, d in B["per_user"].items()}
        res = paired(au, bu, A["per_seed"]["tau"], B["per_seed"]["tau"])
        pr = PAPER["fd"]["w_fd"]["tau"] / PAPER["fd"]["inverse"]["tau"] - 1
        out.append({"claim": "forward loss costs torque accuracy (τ MSE, w_fd vs inverse only)", "metric": "tau",
                    "paper_rel_change": pr, **res, "verdict": _holds(res, pr)})
    return out


def _taskid(runs: dict[str, list[dict]]) -> dict:
    from scipy import stats
    out: dict[str, Any] = {}
    for split in ("sample_split", "trajectory_split"):
        d: dict[str, Any] = {}
        accs = {}
        for arch, rr in runs.items():
            t = [r["taskid"][split] for r in rr if "taskid" in r]
            if not t:
                continue
            accs[arch] = [x["accuracy"] for x in t]
            d[arch] = {"accuracy": _ms(accs[arch]), "per_seed": accs[arch],
                       "majority": _ms([x["majority_accuracy"] for x in t])}
            names = [r["taskid"]["tasks"][r["taskid"][split]["majority_class"]] for r in rr if "taskid" in r]
            d[arch]["majority_class"] = min(set(names), key=lambda c: (-names.count(c), c))  # ties: first by name
            maj = np.array([x["majority_accuracy"] for x in t])
            if len(t) >= 2:
                d[arch]["p_vs_majority_ttest_seeds"] = float(stats.ttest_rel(accs[arch], maj).pvalue)
        if "exolan" in accs and "mlp-tcn" in accs and len(accs["exolan"]) == len(accs["mlp-tcn"]) >= 2:
            a, b = np.array(accs["exolan"]), np.array(accs["mlp-tcn"])
            d["exolan_vs_mlp-tcn"] = {"diff": float(a.mean() - b.mean()),
                                      "p_ttest_seeds": float(stats.ttest_rel(a, b).pvalue)
                                      if np.any(a != b) else float("nan")}
        out[split] = d
    return out


def _real_claims(real) -> list[dict]:
    out = []
    pairs = (("exolan", "mlp-tcn"), ("exolan", "tcn"), ("delan", "mlp"), ("delan-lstm", "mlp-lstm"))
    for split in ("seen", "unseen_task", "unseen_user"):
        for a, b in pairs:
            # one person in two of the splits: pair over held-out trials (subject, task, leg) instead
            c = _claim(real, split, a, b, None, f"{LABELS[a]}+LIM vs {LABELS[b]}+LIM (real, {split})",
                       unit="per_trial")
            if c:
                out.append(c)
    return out


# ----------------------------------------------------------------------------------------------------
# Figures
# ----------------------------------------------------------------------------------------------------

def _grad_norms(fd_runs: dict[str, tuple[str, list[dict]]]) -> dict:
    out = {}
    for key, (label, runs) in fd_runs.items():
        d = {}
        for k in ("gn_tau", "gn_fd", "gn_ms"):
            v = [x for r in runs for x in (r.get("training", {}).get("grad_norms", {}).get(k) or []) if x is not None]
            if v:
                d[k] = float(np.median(v))
        if d:
            out[label] = d
    return out
