"""Tables, statistics, figures and the written report of ``exolan reproduce``.

Everything printed as "ours" is computed here from the runs' stored results; the only hard-coded numbers
are the paper's (``PAPER``), always labelled as the paper's, measured on its real EPIC-lab data.

Statistics. Each claim compares two methods on the same held-out people. The unit of the paired test is
the held-out user: a user's MSE is pooled over that user's samples and averaged over seeds (the seeds
estimate training noise; the users are what the claim generalises over). The test is the Wilcoxon
signed-rank test (scipy.stats.wilcoxon, two-sided, exact for small n): per-user MSEs are skewed and
heteroscedastic across people, so a rank test is safer than a paired t-test; with 7 users its smallest
attainable p is 1/64 ~ 0.016. Where there are at least two seeds, a paired t-test over seeds (each seed's
pooled MSE; scipy.stats.ttest_rel) is reported beside it. A claim "holds" when our change has the paper's
sign, the user-level p < 0.05 and its size is at least a quarter of the paper's relative change (``verdict``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .runio import write_json
from .study import (ARCHITECTURES, LABELS, PLOT_TASKS, RunSpec, Scale, is_cyclic,
                        method_label, method_name)

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
            "per_user": {u: {c: float(np.mean(v)) for c, v in d.items() if v} for u, d in users.items()}}


def _pooled(rows, what) -> float:
    n = sum(x["n_" + what] for x in rows)
    k = len(rows[0]["sse_" + what])
    return float(sum(sum(x["sse_" + what]) for x in rows) / (n * k)) if n else float("nan")


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


ALPHA = 0.05                 # significance over held-out users (two-sided Wilcoxon)
SIZE_FRACTION = 0.25         # a claim holds only at ≥ a quarter of the paper's relative change ...
DIRECTION_ONLY_SIZE = 0.05   # ... or ≥ 5 % where the paper gives a direction only


def verdict(rel: float | None, p: float, paper_rel: float | None) -> str:
    """'holds' when the change has the paper's sign, is significant over held-out users (p < ALPHA) and is at
    least a quarter of the paper's relative change (direction-only claims, paper_rel None: at least 5 %);
    else 'same direction, negligible' (too small, significant or not), 'same direction, not significant',
    or 'reversed' (with '(significant)' where p < ALPHA). A sign alone is not a result."""
    if rel is None or not np.isfinite(rel):
        return "n/a"
    if abs(rel) < 1e-12:
        return "no difference"
    direction = -1.0 if paper_rel is None else float(np.sign(paper_rel))   # direction-only claims: lower error
    significant = np.isfinite(p) and p < ALPHA
    if np.sign(rel) != direction:
        return "reversed (significant)" if significant else "reversed, not significant"
    needed = DIRECTION_ONLY_SIZE if paper_rel is None else SIZE_FRACTION * abs(paper_rel)
    if abs(rel) < needed:
        return "same direction, negligible"
    return "holds" if significant else "same direction, not significant"


def _holds(res: dict, paper_rel: float | None) -> str:
    return verdict(res.get("rel_change"), res.get("p_wilcoxon_users", float("nan")), paper_rel)


# ----------------------------------------------------------------------------------------------------
# Build: tables -> results.json, figures, report.md
# ----------------------------------------------------------------------------------------------------

def build(out: Path, scale: Scale, specs: list[RunSpec], results: dict[str, dict], meta: dict, log=print) -> dict:
    out = Path(out)
    figdir = out / "figures"
    figdir.mkdir(exist_ok=True)
    groups = meta.get("task_groups") or {}

    def runs_of(dataset, arch, lim, w_fd=0.0, w_ms=0.0, ms_norm="state"):
        return [results[s.run_id] for s in specs if s.dataset == dataset and s.arch == arch and s.lim == lim
                and s.w_fd == w_fd and s.w_ms == w_ms and (not w_ms or s.ms_norm == ms_norm)
                and s.run_id in results]

    summary: dict[str, Any] = {"meta": meta, "paper": PAPER}
    # --- human intention estimation
    methods = {}
    for arch in scale.architectures:
        for lim in sorted(set(scale.lims) | ({False} if arch in scale.nolim_also else set()), reverse=True):
            rr = runs_of("world", arch, lim)
            if rr:
                methods[method_name(arch, lim)] = {"arch": arch, "lim": lim, "label": method_label(arch, lim),
                                                   **torque_stats(rr, groups, ("seen", "unseen"))}
    summary["intention"] = methods
    summary["intention_claims"] = _intention_claims(methods)
    # --- forward dynamics
    fd, fd_runs = {}, {}
    if scale.fd_study:
        for key, wfd, wms, label in FD_VARIANTS:
            if key == PAPER_NORM_KEY and scale.ms_norm == "state":
                continue                               # the same runs as "w_fd+w_ms"
            norm = "state" if key == PAPER_NORM_KEY else scale.ms_norm
            rr = runs_of("world", "exolan", True, scale.w_fd if wfd is None else wfd,
                         scale.w_ms if wms is None else wms, norm)
            if rr:
                fd[key] = {"label": label + (f" [{norm} normalisation]" if wms != 0.0 else ""), "ms_norm": norm,
                           **fd_stats(rr, scale.horizons, meta.get("dt"))}
                fd_runs[key] = (fd[key]["label"], rr)
    for mode, rows in (meta.get("reference_fd_rows") or {}).items():
        fd[f"{REFERENCE_KEY}: {mode}"] = {"label": f"the world's true leg, {mode} (reference)",
                                          **fd_stats([{"fd_rows": rows, "torque_rows": []}], scale.horizons,
                                                     meta.get("dt"))}
    summary["forward_dynamics"] = fd
    summary["grad_norms"] = _grad_norms(fd_runs)
    summary["fd_claims"] = _fd_claims(fd)
    # --- task identification
    summary["task_identification"] = _taskid(
        {a: runs_of("world", a, True) for a in ("exolan", "mlp-tcn")})
    # --- real recordings
    real = {}
    for arch in scale.architectures:
        rr = runs_of("real", arch, True)
        if rr:
            real[method_name(arch, True)] = {"arch": arch, "label": method_label(arch, True),
                                             **torque_stats(rr, groups, ("seen", "unseen_task", "unseen_user"))}
    summary["real"] = real
    summary["real_claims"] = _real_claims(real)
    summary["timing"] = {rid: {"train_seconds": r.get("train_seconds"), "eval_seconds": r.get("eval_seconds")}
                         for rid, r in results.items()}

    figs = _figures(figdir, scale, specs, results, summary)
    summary["figures"] = figs
    write_json(out / "results.json", summary, indent=1)
    (out / "report.md").write_text(_markdown(scale, summary, figs))
    log(f"[report] wrote {out / 'report.md'}, {out / 'results.json'} and {len(figs)} figures")
    return summary


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
    if "w_fd" in fd and "w_fd+w_ms" in fd:
        A, B = fd["w_fd+w_ms"], fd["w_fd"]
        for col, paper_rel in PAPER["fd_relative"].items():
            au = {u: d[col] for u, d in A["per_user"].items() if col in d}
            bu = {u: d[col] for u, d in B["per_user"].items() if col in d}
            res = paired(au, bu, A["per_seed"][col], B["per_seed"][col])
            out.append({"claim": f"multi-step loss lowers {col} MSE (w_fd+w_ms vs w_fd)", "metric": col,
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

def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    plt.rcParams.update({"font.size": 10, "axes.grid": True, "grid.alpha": 0.3, "figure.dpi": 110})
    return plt


def _arrays(results, specs, dataset, arch, lim, w_fd, w_ms, seed, ms_norm="state"):
    for s in specs:
        if ((s.dataset, s.arch, s.lim, s.w_fd, s.w_ms, s.seed) == (dataset, arch, lim, w_fd, w_ms, seed)
                and (not w_ms or s.ms_norm == ms_norm) and s.run_id in results):
            return results[s.run_id].get("arrays", {})
    return {}


# the three forward-dynamics variants as plotted: key, legend, colour and line style (distinct line styles
# too: variants trained for few epochs can overlap almost exactly)
_FD_PLOT = (("inverse", "inverse loss only", "tab:red", "-"), ("w_fd", "+ w_fd", "tab:green", "--"),
            ("w_fd+w_ms", "+ w_fd, w_ms", "tab:blue", ":"))


def _figures(figdir: Path, scale: Scale, specs, results, summary) -> dict[str, str]:
    """Every figure the data allows, by name -> path relative to the report (absent where nothing to draw)."""
    seed0 = scale.seeds[0]
    va = {k: _arrays(results, specs, "world", "exolan", True, wf, wm, seed0, scale.ms_norm)
          for k, wf, wm in (("inverse", 0.0, 0.0), ("w_fd", scale.w_fd, 0.0),
                            ("w_fd+w_ms", scale.w_fd, scale.w_ms))}
    drawn = {
        "mse_bars": _fig_mse_bars(figdir, scale, summary["intention"]),
        "torque_tasks": _fig_torque_tasks(figdir, _arrays(results, specs, "world", "exolan", True, 0.0, 0.0, seed0),
                                          _arrays(results, specs, "world", "mlp-tcn", True, 0.0, 0.0, seed0)),
        "accelerations": _fig_accelerations(figdir, va),
        "rollouts": _fig_rollouts(figdir, va),
        "rollout_error_growth": _fig_rollout_error_growth(figdir, scale.horizons, summary["forward_dynamics"]),
        "task_identification": _fig_task_identification(figdir, summary["task_identification"]),
        "real_mse_bars": _fig_real_mse_bars(figdir, scale.architectures, summary.get("real") or {}),
    }
    return {k: v for k, v in drawn.items() if v is not None}


def _fig_mse_bars(figdir: Path, scale: Scale, methods: dict) -> str | None:
    """MSE bars per method, with / without LIM, seen and unseen tasks."""
    if not methods:
        return None
    plt = _plt()
    archs = [a for a in scale.architectures if method_name(a, True) in methods or method_name(a, False) in methods]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2), sharey=False)
    for ax, split, title in zip(axes, ("seen", "unseen"), ("seen tasks", "unseen tasks")):
        x = np.arange(len(archs))
        vals = []
        for j, lim in enumerate(scale.lims):
            m = [methods.get(method_name(a, lim), {}).get(split, {}).get("mse", (np.nan, np.nan)) for a in archs]
            mu = np.array([v[0] for v in m]); sd = np.array([v[1] for v in m])
            vals += [v for v in mu if np.isfinite(v) and v > 0]
            w = 0.38
            ax.bar(x + (j - 0.5) * w, mu, w, yerr=sd, capsize=3, color=("tab:blue" if lim else "tab:gray"),
                   label="with LIM" if lim else "without LIM")
        ax.set_xticks(x, [LABELS[a].replace(" (DeLaN-TCN)", "") for a in archs], rotation=30, ha="right")
        ax.set_ylabel("torque MSE [N² m²]")
        ax.set_title(f"Held-out users, {title} (mean ± std over {len(scale.seeds)} seeds)")
        if vals and max(vals) / min(vals) > 30:
            ax.set_yscale("log")
        ax.legend()
    fig.tight_layout()
    return _save(fig, figdir / "mse_bars.png", plt)


def _fig_torque_tasks(figdir: Path, ea: dict, ma: dict) -> str | None:
    """Torque trajectories of ExoLaN (`ea`) vs MLP-TCN (`ma`), both + LIM, for the tasks the arrays hold."""
    tasks = sorted({k.split("/")[1] for k in ea if k.startswith("torque/")},
                   key=lambda t: (PLOT_TASKS.index(t) if t in PLOT_TASKS else 99, t))
    if not tasks:
        return None
    plt = _plt()
    fig, axes = plt.subplots(len(tasks), 2, figsize=(12, 2.4 * len(tasks) + 0.6), squeeze=False)
    for i, task in enumerate(tasks):
        t = ea[f"torque/{task}/t"]
        subj = str(ea.get(f"torque/{task}/subject", ""))
        for j, joint in enumerate(("hip", "knee")):
            ax = axes[i, j]
            ax.plot(t, ea[f"torque/{task}/meas"][:, j], "k-", lw=1.6, label="measured (inverse dynamics + exo)")
            ax.plot(t, ea[f"torque/{task}/pred"][:, j], "-", color="tab:blue", lw=1.1, label="ExoLaN + LIM")
            if f"torque/{task}/pred" in ma:
                ax.plot(ma[f"torque/{task}/t"], ma[f"torque/{task}/pred"][:, j], "--", color="tab:orange",
                        lw=1.1, label="MLP-TCN + LIM")
            ax.set_title(f"{task}, {joint} ({subj}, held-out user)")
            ax.set_ylabel("torque [N m]")
            if i == len(tasks) - 1:
                ax.set_xlabel("time [s]")
    axes[0, 0].legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return _save(fig, figdir / "torque_tasks.png", plt)


def _fig_accelerations(figdir: Path, va: dict[str, dict]) -> str | None:
    """Predicted vs measured accelerations of the forward-dynamics variants (`va`: their arrays by key)."""
    acc_tasks = [t for t in ("walk", "squat", "run") if any(f"acc/{t}/t" in a for a in va.values())]
    if not acc_tasks:
        return None
    plt = _plt()
    fig, axes = plt.subplots(len(acc_tasks), 2, figsize=(12, 2.6 * len(acc_tasks) + 0.6), squeeze=False)
    for i, task in enumerate(acc_tasks):
        for j, joint in enumerate(("hip", "knee")):
            ax = axes[i, j]
            meas = None
            for k, lab, col, ls in _FD_PLOT:
                a = va[k]
                if f"acc/{task}/t" not in a:
                    continue
                meas = a[f"acc/{task}/meas"][:, j]
                ax.plot(a[f"acc/{task}/t"], a[f"acc/{task}/pred"][:, j], ls, color=col, lw=1.2,
                        label=f"ExoLaN {lab}")
                tt = a[f"acc/{task}/t"]
            if meas is not None:
                ax.plot(tt, meas, "k-", lw=1.6, label="measured (Savitzky-Golay)")
                lo, hi = np.nanmin(meas), np.nanmax(meas)
                pad = 0.5 * (hi - lo + 1e-9)
                ax.set_ylim(lo - pad, hi + pad)  # a diverging model would otherwise flatten the trace
            ax.set_title(f"{task}, {joint}: forward dynamics q̈ (held-out user; y-axis clipped)")
            ax.set_ylabel("q̈ [rad/s²]")
            if i == len(acc_tasks) - 1:
                ax.set_xlabel("time [s]")
    axes[0, 0].legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return _save(fig, figdir / "accelerations.png", plt)


def _fig_rollouts(figdir: Path, va: dict[str, dict]) -> str | None:
    """Open-loop rollouts of the forward-dynamics variants (`va`: their arrays by key) over the measured trace."""
    if not any("roll/q_pred" in a for a in va.values()):
        return None
    plt = _plt()
    fig, axes = plt.subplots(2, 2, figsize=(12, 6.5))
    ref = next(a for a in va.values() if "roll/q_pred" in a)
    dt = float(ref["roll/dt"])
    for row, (key, name, unit) in enumerate((("q", "position", "rad"), ("qd", "velocity", "rad/s"))):
        for j, joint in enumerate(("hip", "knee")):
            ax = axes[row, j]
            tr = ref[f"roll/trace_{key}"][:, j]
            ax.plot(ref["roll/trace_t"], tr, "k-", lw=1.6, label="measured")
            for k, lab, col, ls in _FD_PLOT:
                a = va[k]
                if "roll/q_pred" not in a:
                    continue
                P = a[f"roll/{key}_pred"]
                for si, s in enumerate(a["roll/starts"]):
                    ax.plot((s + np.arange(P.shape[1])) * dt, P[si, :, j], ls, color=col, lw=1.4,
                            label=f"ExoLaN {lab}" if si == 0 else None)
                    ax.plot(s * dt, P[si, 0, j], "o", color="k", ms=3)
            lo, hi = np.nanmin(tr), np.nanmax(tr)
            pad = 0.3 * (hi - lo + 1e-9)
            ax.set_ylim(lo - pad, hi + pad)
            ax.set_title(f"{joint} {name}: open-loop rollouts, {P.shape[1] - 1} steps "
                         f"({(P.shape[1] - 1) * dt * 1000:.0f} ms), task {ref['roll/task']}")
            ax.set_ylabel(f"{key.replace('qd', 'q̇')} [{unit}]")
            ax.set_xlabel("time [s]")
    axes[0, 0].legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return _save(fig, figdir / "rollouts.png", plt)


def _fig_rollout_error_growth(figdir: Path, horizons, fd: dict) -> str | None:
    """Rollout error growth with the horizon, per forward-dynamics variant (`fd`: the report's statistics)."""
    if not fd:
        return None
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    for k, lab, col, ls in _FD_PLOT:
        if k not in fd:
            continue
        ms = fd[k]["mean_std"]
        for ax, key in zip(axes, ("q", "qd")):
            y = [ms.get(f"{key}{h}", (np.nan, np.nan))[0] for h in horizons]
            e = [ms.get(f"{key}{h}", (np.nan, np.nan))[1] for h in horizons]
            ax.errorbar(horizons, y, yerr=e, marker="o", ls=ls, color=col, capsize=3, label=f"ExoLaN {lab}")
    for ax, unit in zip(axes, ("q MSE [rad²]", "q̇ MSE [rad²/s²]")):
        ax.set_yscale("log"); ax.set_xlabel("open-loop steps (5 ms each)"); ax.set_ylabel(unit)
        ax.set_xticks(horizons)
        ax.set_title("held-out users, all tasks")
        ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, figdir / "rollout_error_growth.png", plt)


def _fig_task_identification(figdir: Path, ti: dict) -> str | None:
    """Task-identification accuracy per model and split, against the majority-class baseline."""
    if not ti.get("sample_split"):
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 3.8))
    names, vals, errs, cols, majs = [], [], [], [], []
    for split, sl in (("sample_split", "80/20 by sample"), ("trajectory_split", "80/20 by trajectory")):
        for arch, col in (("exolan", "tab:blue"), ("mlp-tcn", "tab:orange")):
            if arch in ti.get(split, {}):
                names.append(f"{LABELS[arch].split(' ')[0]}\n{sl}")
                vals.append(ti[split][arch]["accuracy"][0]); errs.append(ti[split][arch]["accuracy"][1])
                cols.append(col); majs.append(ti[split][arch]["majority"][0])
    ax.bar(range(len(vals)), vals, yerr=errs, capsize=3, color=cols)
    # the majority-class baseline of each split (its test set's share of the training majority class)
    ax.hlines(majs, np.arange(len(vals)) - 0.45, np.arange(len(vals)) + 0.45, colors="k", linestyles="--",
              label="majority-class baseline")
    ax.set_xticks(range(len(vals)), names, fontsize=8)
    ax.set_ylabel("test accuracy"); ax.set_ylim(0, 1)
    ax.set_title("Task identification from z (mean ± std over seeds)")
    ax.legend()
    fig.tight_layout()
    return _save(fig, figdir / "task_identification.png", plt)


def _fig_real_mse_bars(figdir: Path, architectures, real: dict) -> str | None:
    """Torque MSE on the real recordings per method (with LIM) and split."""
    if not real:
        return None
    plt = _plt()
    archs = [a for a in architectures if method_name(a, True) in real]
    splits = ("seen", "unseen_task", "unseen_user")
    fig, ax = plt.subplots(figsize=(11, 4))
    x = np.arange(len(archs)); w = 0.27
    for j, (split, col) in enumerate(zip(splits, ("tab:blue", "tab:orange", "tab:green"))):
        m = [real[method_name(a, True)].get(split, {}).get("mse", (np.nan, np.nan)) for a in archs]
        ax.bar(x + (j - 1) * w, [v[0] for v in m], w, yerr=[v[1] for v in m], capsize=3, color=col,
               label=split.replace("_", " "))
    ax.set_xticks(x, [LABELS[a].replace(" (DeLaN-TCN)", "") + " + LIM" for a in archs], rotation=30, ha="right")
    ax.set_ylabel("torque MSE [N² m²]"); ax.set_yscale("log")
    ax.set_title("Real recordings (shared/real): held-out time, tasks and people")
    ax.legend(loc="center left", bbox_to_anchor=(1.0, 0.5))  # outside: no bar hidden
    fig.tight_layout()
    return _save(fig, figdir / "real_mse_bars.png", plt)


def _save(fig, path: Path, plt) -> str:
    fig.savefig(path)
    plt.close(fig)
    return f"figures/{path.name}"


# ----------------------------------------------------------------------------------------------------
# Markdown
# ----------------------------------------------------------------------------------------------------

def _f(v, digits=3) -> str:
    if v is None:
        return "—"
    if isinstance(v, str):
        return v
    if not np.isfinite(v):
        return "∞" if v > 0 else "n/a"
    a = abs(v)
    if a != 0 and (a >= 1e5 or a < 1e-2):
        return f"{v:.{digits - 1}e}"
    return f"{v:.{digits}g}" if a < 1000 else f"{v:.0f}"


def _pm(t) -> str:
    if t is None:
        return "—"
    m, s = t
    return f"{_f(m)} ± {_f(s, 2)}" if np.isfinite(m) else "n/a"


def _pct(v) -> str:
    return "—" if v is None or not np.isfinite(v) else f"{100 * v:+.1f}%"


def _p(v) -> str:
    return "—" if v is None or not np.isfinite(v) else f"{v:.3g}"


def _grad_norm_table(gn: dict) -> list[str]:
    """Median over epochs (and seeds) of each weighted loss term's gradient norm, per forward-dynamics run."""
    if not gn:
        return []
    L = ["Gradient norm of each weighted loss term (‖∂(w·loss)/∂θ‖ on the first batch of every epoch; median "
         "over epochs and seeds): which term drives the update.", "",
         "| run | torque | w_fd · q̈ | w_ms · multi-step |", "|---|---|---|---|"]
    for label, d in gn.items():
        L.append(f"| {label} | " + " | ".join(_f(d.get(k)) for k in ("gn_tau", "gn_fd", "gn_ms")) + " |")
    return L + [""]


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


def _claims_table(claims) -> list[str]:
    L = [f"A claim **holds** when our change has the paper's sign, is significant over held-out users "
         f"(Wilcoxon p < {ALPHA:g}) and is at least {SIZE_FRACTION:.0%} of the paper's relative change "
         f"(direction-only claims: at least {DIRECTION_ONLY_SIZE:.0%}); otherwise it is *same direction, negligible*, "
         f"*same direction, not significant* or *reversed*.", "",
         "| claim | paper's change (real data) | ours (seed-mean, pooled over users) | users better | "
         "p Wilcoxon (users) | p paired t (seeds) | verdict |", "|---|---|---|---|---|---|---|"]
    for c in claims:
        pr = c.get("paper_rel_change")
        prs = "direction only" if pr is None else _pct(pr)
        L.append(f"| {c['claim']} | {prs} | {_pct(c.get('rel_change'))} | {c.get('users_better', '—')}/"
                 f"{c.get('n_users', '—')} | {_p(c.get('p_wilcoxon_users'))} | {_p(c.get('p_ttest_seeds'))} | "
                 f"{c['verdict']} |")
    return L


def _markdown(scale: Scale, S: dict, figs: dict) -> str:
    meta = S["meta"]
    L = (_section_header(scale, meta)
         + _section_intention(S["intention"], S["intention_claims"], figs)
         + _section_forward_dynamics(scale, S["forward_dynamics"], S.get("grad_norms", {}), S["fd_claims"],
                                     figs)
         + _section_task_identification(scale, S["task_identification"], figs)
         + _section_real(scale, meta.get("real_data"), S.get("real") or {}, S["real_claims"], figs)
         + _section_runs(S["timing"]) + _section_deviations())
    return "\n".join(L)


def _section_header(scale: Scale, meta: dict) -> list[str]:
    """Title, scale, executor and timing, how to read the report, and the statistics used."""
    L = ["# ExoLaN reproduction report", "",
         f"Scale **{scale.name}**: {len(scale.seeds)} seeds ({', '.join(map(str, scale.seeds))}), "
         f"{scale.epochs} epochs, {len(scale.architectures)} architectures x "
         f"{'with/without LIM' if len(scale.lims) == 2 else 'LIM'}; data `{meta['data']}`"
         + (f" (simulated: {scale.users} users, tasks {scale.tasks}, {scale.seconds or 'default'} s per trial)"
            if meta['data'].endswith('/world') else "") + ".",
         f"Executor: {meta['executor']}, {meta['workers']} worker(s) x {meta['threads_per_worker']} thread(s), "
         f"device {meta['device']}. {meta['n_runs']} training runs. " + _wall_time(meta)
         + (f" **Failed runs, missing from the tables** (a re-run retries them): {', '.join(meta['failed_runs'])}."
            if meta.get("failed_runs") else ""), "",
         "**Reading this report.** Every number labelled *ours* was measured in this sweep. Numbers labelled "
         "*paper* are the published ones (Schulze et al., ExoLaN, 2026) on the **real EPIC-lab exoskeleton "
         "dataset**; ours come from a simulated world (or the data given by `--data`), so absolute values are "
         "not comparable - compare directions and ratios. "
         + ("At this scale the models are trained for a few epochs only: the study exercises the whole "
            "protocol, but its numbers are far from converged and say little about the paper's claims. "
            "The claims are tested at the `converge` scale (`exolan reproduce --scale converge`: every run "
            "early-stopped on validation users carved from the training users, 3 seeds); its published tables "
            "are in `docs/RESULTS.md` of the exolan source tree."
            if scale.name in ("small", "tiny", "micro") else "")
         + (f" Early stopping: patience {scale.patience} epochs on {scale.val_users} training users held out "
            f"as validation (at most {scale.epochs} epochs); the multi-step loss' normalisation is "
            f"*{scale.ms_norm}* (see section 2)." if scale.patience else ""), "",
         "Statistics: mean ± std over seeds (sample std). Each claim is tested paired over held-out users "
         "(per-user MSE pooled over the user's samples and averaged over seeds; Wilcoxon signed-rank, "
         "two-sided) and, with ≥ 2 seeds, paired over seeds (t-test on each seed's pooled MSE). A claim "
         "*holds* when our change has the paper's sign and the user-level p < 0.05. With 7 held-out users "
         "the smallest attainable Wilcoxon p is 0.016.", ""]
    return L


def _wall_time(meta: dict) -> str:
    """The sweep's wall time over every invocation (a resumed sweep adds up), and this invocation's."""
    clock = meta.get("sweep_clock")
    now = f"this invocation: world {meta['seconds']['world']:.0f} s, runs {meta['seconds']['runs']:.0f} s"
    if not clock:
        return f"Wall time of {now}."
    t = clock["total_seconds"]
    n = len(clock["sessions"])
    return (f"**Wall time of the sweep: {clock['total'] / 60:.1f} min** (world {t.get('world', 0):.0f} s, runs "
            f"{t.get('runs', 0):.0f} s, the world's reference rollouts {t.get('reference', 0):.0f} s; "
            f"{n} invocation{'s' if n > 1 else ''}, `sweep_clock.json`); {now}.")


def _section_intention(M: dict, claims: list[dict], figs: dict) -> list[str]:
    """1. Human intention estimation: torque MSE per method, the claims, the per-task comparison."""
    L = ["## 1. Human intention estimation", "",
         "Torque MSE [N² m²] of the total actuated torque on held-out users (pooled over samples and both "
         "joints), mean ± std over seeds. Cyclic / non-cyclic uses the world's task groups.", "",
         "| method | seen tasks | unseen tasks | seen, cyclic | seen, non-cyclic | unseen, cyclic | "
         "unseen, non-cyclic |", "|---|---|---|---|---|---|---|"]
    for name, m in M.items():
        L.append(f"| {m['label']} | {_pm(m['seen']['mse'])} | {_pm(m['unseen']['mse'])} | "
                 f"{_pm(m['seen']['cyclic'])} | {_pm(m['seen']['noncyclic'])} | {_pm(m['unseen']['cyclic'])} | "
                 f"{_pm(m['unseen']['noncyclic'])} |")
    L += ["", f"{len(M)} methods present.", "",
          "*Paper (real data):* seen tasks, cyclic: TCN 464, ExoLaN 468 N² m²; non-cyclic: ExoLaN 411, "
          "TCN 450 N² m². The paper gives the other results as relative changes (below).", "",
          "### Claims", ""]
    L += _claims_table(claims)
    L += _where_claims_fail(M, claims)
    L += _per_task_table(M)
    if "mse_bars" in figs:
        L += ["", f"![MSE per method]({figs['mse_bars']})", ""]
    if "torque_tasks" in figs:
        L += [f"![torque trajectories]({figs['torque_tasks']})", "",
              "Torque trajectories of one held-out user (first seed): measured total torque, ExoLaN + LIM and "
              "MLP-TCN + LIM.", ""]
    return L


def _rel(a: float, b: float) -> float:
    return a / b - 1.0 if np.isfinite(a) and np.isfinite(b) and b > 0 else float("nan")


def _where_claims_fail(M: dict, claims: list[dict]) -> list[str]:
    """For every claim that does not hold: its change per joint, and per task and joint, so that a reader
    sees where it fails (a finding, not something to tune away)."""
    failing = [c for c in claims if c["verdict"] != "holds" and "per_joint" in M[c["a"]][c["split"]]]
    if not failing:
        return []
    L = ["", "### Where the claims that do not hold fail", "",
         "Relative change of the claim's first method against its second (negative = first better), seed-mean "
         "MSE of each joint; per task the same, hip / knee.", "",
         "| claim | total | hip | knee | verdict |", "|---|---|---|---|---|"]
    for c in failing:
        A, B = M[c["a"]][c["split"]], M[c["b"]][c["split"]]
        hk = [_pct(_rel(a[0], b[0])) for a, b in zip(A["per_joint"], B["per_joint"])]
        L.append(f"| {c['claim']} | {_pct(_rel(A['mse'][0], B['mse'][0]))} | {' | '.join(hk)} | {c['verdict']} |")
    for split in dict.fromkeys(c["split"] for c in failing):
        cs = [c for c in failing if c["split"] == split]
        tasks = sorted(set.intersection(*(set(M[c["a"]][split]["per_task_joint"]) &
                                          set(M[c["b"]][split]["per_task_joint"]) for c in cs)))
        L += ["", f"Per task, split *{split}* (total, then hip / knee):", "",
              "| task | " + " | ".join(f"{M[c['a']]['label']} vs {M[c['b']]['label']}" for c in cs) + " |", "|---" * (len(cs) + 1) + "|"]
        for t in tasks:
            cells = []
            for c in cs:
                A, B = M[c["a"]][split], M[c["b"]][split]
                hk = [_pct(_rel(a, b)) for a, b in zip(A["per_task_joint"][t], B["per_task_joint"][t])]
                cells.append(f"{_pct(_rel(A['per_task'][t][0], B['per_task'][t][0]))} ({' / '.join(hk)})")
            L.append(f"| {t} | " + " | ".join(cells) + " |")
    return L


def _per_task_table(M: dict) -> list[str]:
    """Per task: MLP-TCN + LIM vs ExoLaN + LIM, ours and the paper's."""
    L = ["", "### Per task: MLP-TCN + LIM vs ExoLaN + LIM [N² m²]", "",
         "| task | split | ours MLP-TCN | ours ExoLaN | ours change | paper MLP-TCN | paper ExoLaN | paper change |",
         "|---|---|---|---|---|---|---|---|"]
    if "exolan" in M and "mlp-tcn" in M:
        for split in ("seen", "unseen"):
            for task in sorted(set(M["exolan"][split]["per_task"]) & set(M["mlp-tcn"][split]["per_task"]),
                               key=lambda t: (t not in PAPER["per_task"], t)):
                a = M["mlp-tcn"][split]["per_task"][task]; b = M["exolan"][split]["per_task"][task]
                pt = PAPER["per_task"].get(task)
                L.append(f"| {task} | {split} | {_pm(a)} | {_pm(b)} | {_pct(b[0] / a[0] - 1)} | "
                         f"{_f(pt['mlp-tcn']) if pt else '—'} | {_f(pt['exolan']) if pt else '—'} | "
                         f"{_pct(pt['exolan'] / pt['mlp-tcn'] - 1) if pt else '—'} |")
    return L


def _section_forward_dynamics(scale: Scale, fd: dict, grad_norms: dict, claims: list[dict],
                              figs: dict) -> list[str]:
    """2. Forward dynamics: the three loss variants (and the reference rows) against the paper's."""
    L = ["## 2. Forward dynamics", "",
         f"ExoLaN + LIM trained with the inverse loss only, + w_fd = {scale.w_fd:g}, + w_fd and w_ms = "
         f"{scale.w_ms:g} (H = 4). Held-out users, all tasks (seen and unseen). q and q̇ MSE after 4, 10, "
         "20 open-loop semi-implicit Euler steps (recorded τ, z and f_v; starts every "
         f"{scale.rollout_stride} samples). A diverged rollout (non-finite state) counts as infinite error.", "",
         "The multi-step loss divides each step's q and q̇ error by a variance: *state* is the paper's (the "
         "training variance of q and q̇); *increment* is the variance of their h-step change in the training "
         "data, so that an error as large as the motion within the horizon weighs 1 at every step. With the "
         "paper's, a 4-step error of a model that fits q̈ well is a tiny fraction of the range of motion and the "
         "term's gradient is a small fraction of the acceleration term's (table below); "
         f"this scale's w_fd + w_ms run uses *{scale.ms_norm}*"
         + (", and the paper's is trained beside it." if scale.ms_norm != "state" else "."),
         "The reference rows roll out the world's own leg the same way: *recorded* is fed exactly what the "
         "models are fed (τ, the vertical insole force at the recorded centre of pressure; no pelvis motion, no "
         "horizontal ground force: a learned context can absorb part of those, so it is no bound); *true inputs, "
         "recorded τ* adds the true pelvis motion and ground force; *true inputs* also has the true torque, leaving "
         "only sensor noise and the integrator: the floor of any model. The gap between the last two is what the "
         "recorded torque (filtered moments, the exoskeleton's measured torque) costs every model.", ""]
    L += _fd_table(fd)
    L += _amplification_table(fd, scale.horizons)
    if fd:
        div = "; ".join(f"{fd[k]['label']}: " + ", ".join(f"{h} steps {_f(100 * v[0])}%"
                        for h, v in fd[k]["diverged_fraction"].items()) for k in fd)
        L += ["", f"Diverged rollouts (fraction of starts, mean over seeds): {div}.", ""]
        L += _grad_norm_table(grad_norms)
        L += ["### Claims", ""]
        L += _claims_table(claims)
    for k in ("accelerations", "rollouts", "rollout_error_growth"):
        if k in figs:
            L += ["", f"![{k}]({figs[k]})"]
    L += [""]
    return L


def _fd_table(fd: dict) -> list[str]:
    """Held-out q̈, q and q̇ errors per forward-dynamics variant: ours, then the paper's."""
    L = ["| model | " + " | ".join(FD_HEAD) + " |", "|---|" + "---|" * len(FD_COLS)]
    for key in [k for k, _, _, _ in FD_VARIANTS] + [k for k in fd if k.startswith(REFERENCE_KEY)]:
        if key in fd:
            L.append(f"| **ours** {fd[key]['label']} | " + " | ".join(_pm(fd[key]["mean_std"].get(c)) for c in FD_COLS)
                     + " |")
    for key, _, _, label in FD_VARIANTS:
        if key not in PAPER["fd"]:
            continue
        L.append(f"| *paper (real data)* {label} | " + " | ".join(_f(PAPER['fd'][key][c]) for c in FD_COLS) + " |")
    return L


def _amplification_table(fd: dict, horizons) -> list[str]:
    """How much of each rollout error is the q̈ error integrated and how much compounds (`amplification`), and
    the multi-step loss' change of q̇ at the last horizon split into those two factors: ours and the paper's."""
    ours = [k for k, _, _, _ in FD_VARIANTS if k in fd and f"amp{horizons[-1]}" in fd[k]["mean_std"]]
    if not ours:
        return []
    h_last = horizons[-1]
    L = ["", f"**Rollout amplification** A_h = q̇_h MSE / ((h·dt)² · q̈ MSE): about 1 when a model's q̈ error "
         "persists over the horizon and is simply integrated, below 1 when it changes sign within it, far above 1 "
         "when errors compound through the rolled-out state (an unstable model). A multi-step loss can lower q̇_h "
         "by lowering the q̈ error and by lowering A_h; the second is what a one-step loss cannot see.", "",
         "| model | " + " | ".join(f"A_{h}" for h in horizons) + " |", "|---|" + "---|" * len(horizons)]
    for k in ours:
        L.append(f"| **ours** {fd[k]['label']} | " + " | ".join(_pm(fd[k]["mean_std"][f"amp{h}"]) for h in horizons)
                 + " |")
    P = PAPER["fd"]
    for k, _, _, label in FD_VARIANTS:
        if k in P:
            L.append(f"| *paper (real data)* {label} | "
                     + " | ".join(_f(amplification(P[k][f"qd{h}"], P[k]["qdd"], h, PAPER["dt"])) for h in horizons)
                     + " |")
    if "w_fd" in fd and "w_fd+w_ms" in fd:
        def split(a, b):          # (q̈ factor, A factor, product) of b over a
            fq = b["qdd"] / a["qdd"]
            fa = (b[f"qd{h_last}"] / b["qdd"]) / (a[f"qd{h_last}"] / a["qdd"])
            return fq, fa, fq * fa
        def m(k):
            return {c: fd[k]["mean_std"][c][0] for c in ("qdd", f"qd{h_last}")}
        rows = (("ours", split(m("w_fd"), m("w_fd+w_ms"))), ("paper", split(P["w_fd"], P["w_fd+w_ms"])))
        L += ["", f"The multi-step loss' change of q̇_{h_last} MSE (w_fd+w_ms over w_fd) = change of q̈ MSE x change "
              f"of A_{h_last}: " + "; ".join(f"{who} {_pct(fq - 1)} x {_pct(fa - 1)} = {_pct(t - 1)}"
                                           for who, (fq, fa, t) in rows) + "."]
    return L + [""]


def _section_task_identification(scale: Scale, ti: dict, figs: dict) -> list[str]:
    """3. Task identification from the context z, by sample and by trajectory."""
    P = PAPER["taskid"]
    L = ["## 3. Task identification from the context z", "",
         "z of the trained ExoLaN + LIM and MLP-TCN + LIM over the training trajectories; MLP 3 x 64 ReLU, "
         "softmax cross-entropy with inverse-frequency class weights, Adam (lr 1e-3, wd 1e-4, batch 4096, "
         f"{scale.taskid_epochs} epochs), one 80/20 split per seed. *By sample* is the paper's protocol; "
         "neighbouring samples of one trajectory share nearly the same z, so we also split *by trajectory* "
         "(no temporal leakage).", "",
         "| model | ours, by sample | ours, by trajectory | paper (real data) |", "|---|---|---|---|"]
    for arch in ("exolan", "mlp-tcn"):
        a = ti.get("sample_split", {}).get(arch); b = ti.get("trajectory_split", {}).get(arch)
        L.append(f"| {LABELS[arch]} | {_pm(a['accuracy']) if a else '—'} | {_pm(b['accuracy']) if b else '—'} | "
                 f"{P[arch][0]:.3f} ± {P[arch][1]:.3f} |")
    a = ti.get("sample_split", {}).get("exolan") or ti.get("sample_split", {}).get("mlp-tcn")
    b = ti.get("trajectory_split", {}).get("exolan") or ti.get("trajectory_split", {}).get("mlp-tcn")
    L.append(f"| majority class | {_pm(a['majority']) + ' (' + a['majority_class'] + ')' if a else '—'} | "
             f"{_pm(b['majority']) + ' (' + b['majority_class'] + ')' if b else '—'} | "
             f"{P['majority']:.3f} ({P['majority_class']}) |")
    for split in ("sample_split", "trajectory_split"):
        d = ti.get(split, {})
        if "exolan_vs_mlp-tcn" in d:
            c = d["exolan_vs_mlp-tcn"]
            L.append(f"\n{split.replace('_', ' ')}: ExoLaN − MLP-TCN accuracy = {c['diff']:+.3f} "
                     f"(paired t over seeds p = {_p(c['p_ttest_seeds'])}; paper +0.031).")
        for arch in ("exolan", "mlp-tcn"):
            if arch in d and "p_vs_majority_ttest_seeds" in d[arch]:
                L.append(f"{split.replace('_', ' ')}: {LABELS[arch]} vs majority class, paired t over seeds "
                         f"p = {_p(d[arch]['p_vs_majority_ttest_seeds'])}.")
    if "task_identification" in figs:
        L += ["", f"![task identification]({figs['task_identification']})"]
    L += [""]
    return L


def _section_real(scale: Scale, real_data, R: dict, claims: list[dict], figs: dict) -> list[str]:
    """4. Real recordings: the split, torque MSE per method and split, the claims."""
    L = ["## 4. Real recordings (`shared/real`)", ""]
    if not R:
        L += ["Not run: the real recordings were not found (set `EXOLAN_REAL_DATA` or place them at "
              "`<repo>/../shared/real`) or this scale skips them.", ""]
    else:
        L += [f"Data: `{real_data}` - five real people (OpenSim inverse dynamics, force plates "
              "converted to insole channels), **no exoskeleton** (exo torque is zero), 15 tasks, one person "
              "(REAL01) with 24 of the 28 trials. The paper's 14/7 user split is impossible, so the split is:",
              "",
              "* **train**: REAL01, tasks walk (+ trunk sway, toe in, toe out), squat, sit-to-stand, drop jump, "
              "stand; repetitions 1-2 where a task has three, else the first 70 % of the trial;",
              "* **seen**: the same person and tasks, repetition 3 or the last 30 % of the trial (unseen time);",
              "* **unseen task**: REAL01's asymmetric and weak-legs variants (squat_asym, sit_to_stand_asym, "
              "sit_to_stand_weak_legs, drop_jump_asym);",
              "* **unseen user**: REAL02-REAL05 (fast walking with turns, sprint, overground walk, treadmill "
              "walk; REAL05's hip angle is trunk-referenced and its left leg unmeasured).", "",
              f"{len(scale.architectures)} architectures with LIM, {len(scale.real_seeds or scale.seeds)} seed(s), "
              f"{scale.real_epochs or scale.epochs} epochs. Torque MSE [N² m²], mean ± std over seeds:", "",
              "| method | seen (held-out time) | unseen task | unseen user |", "|---|---|---|---|"]
        for name, m in R.items():
            L.append(f"| {m['label']} | {_pm(m['seen']['mse'])} | {_pm(m['unseen_task']['mse'])} | "
                     f"{_pm(m['unseen_user']['mse'])} |")
        L += ["", "DeLaN-based vs black-box. Two of the splits hold one person only, so here the paired "
              "Wilcoxon test runs over held-out *trials* (subject, recording, leg; per-trial MSE averaged over "
              "seeds) - trials of one person are not independent, so read p as descriptive. The 'users "
              "better' column counts trials here.", ""]
        L += _claims_table(claims)
        L += _where_claims_fail(R, claims)
        if "real_mse_bars" in figs:
            L += ["", f"![real data]({figs['real_mse_bars']})"]
        L += [""]
    return L


def _section_runs(timing: dict) -> list[str]:
    """Runs and reproducibility: training times and where every run's files are."""
    tt = [v["train_seconds"] or 0 for v in timing.values()]
    L = ["## Runs and reproducibility", "",
         f"{len(tt)} runs; training time per run {_f(min(tt) if tt else float('nan'))}-"
         f"{_f(max(tt) if tt else float('nan'))} s (sum {sum(tt):.0f} s). Every run lives in "
         "`runs/<dataset>/<method>_fd<w_fd>_ms<w_ms>_e<epochs>_s<seed>/` with its training directory, "
         "`result.json` and a `DONE` marker; re-running the same command skips finished runs. The raw "
         "numbers behind every table are in `results.json`.", ""]
    return L


def _section_deviations() -> list[str]:
    """Deviations from the paper's protocol."""
    L = ["## Deviations from the paper's protocol", "",
         "* Data: a simulated world (issue 3) instead of the EPIC-lab recordings; the real-data section uses "
         "five public recordings with no exoskeleton.",
         "* Task identification is also reported with a by-trajectory split (see section 3).",
         "* Acceleration MSE per task for MLP-TCN (paper: run 2841 vs 1394) is not reproduced: a black-box "
         "inverse model has no forward dynamics, and the paper does not say how it obtained q̈ from MLP-TCN.",
         ""]
    return L
