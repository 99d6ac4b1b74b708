"""The report's figures, one function each; every one returns its path, or None where nothing is drawn."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..study import LABELS, PLOT_TASKS, Scale, method_name


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


JOINTS = ("hip", "knee")
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


def _task_joint_grid(tasks: list[str], row_height: float, ylabel: str, draw, path: Path) -> str:
    """One row per task, hip and knee side by side; `draw(ax, task, j)` fills a panel (and sets its title)."""
    plt = _plt()
    fig, axes = plt.subplots(len(tasks), 2, figsize=(12, row_height * len(tasks) + 0.6), squeeze=False)
    for i, task in enumerate(tasks):
        for j in range(2):
            ax = axes[i, j]
            draw(ax, task, j)
            ax.set_ylabel(ylabel)
            if i == len(tasks) - 1:
                ax.set_xlabel("time [s]")
    axes[0, 0].legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return _save(fig, path, plt)


def _fig_torque_tasks(figdir: Path, ea: dict, ma: dict) -> str | None:
    """Torque trajectories of ExoLaN (`ea`) vs MLP-TCN (`ma`), both + LIM, for the tasks the arrays hold."""
    tasks = sorted({k.split("/")[1] for k in ea if k.startswith("torque/")},
                   key=lambda t: (PLOT_TASKS.index(t) if t in PLOT_TASKS else 99, t))
    if not tasks:
        return None

    def draw(ax, task, j):
        t = ea[f"torque/{task}/t"]
        subj = str(ea.get(f"torque/{task}/subject", ""))
        ax.plot(t, ea[f"torque/{task}/meas"][:, j], "k-", lw=1.6, label="measured (inverse dynamics + exo)")
        ax.plot(t, ea[f"torque/{task}/pred"][:, j], "-", color="tab:blue", lw=1.1, label="ExoLaN + LIM")
        if f"torque/{task}/pred" in ma:
            ax.plot(ma[f"torque/{task}/t"], ma[f"torque/{task}/pred"][:, j], "--", color="tab:orange",
                    lw=1.1, label="MLP-TCN + LIM")
        ax.set_title(f"{task}, {JOINTS[j]} ({subj}, held-out user)")
    return _task_joint_grid(tasks, 2.4, "torque [N m]", draw, figdir / "torque_tasks.png")


def _fig_accelerations(figdir: Path, va: dict[str, dict]) -> str | None:
    """Predicted vs measured accelerations of the forward-dynamics variants (`va`: their arrays by key)."""
    acc_tasks = [t for t in ("walk", "squat", "run") if any(f"acc/{t}/t" in a for a in va.values())]
    if not acc_tasks:
        return None

    def draw(ax, task, j):
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
        ax.set_title(f"{task}, {JOINTS[j]}: forward dynamics q̈ (held-out user; y-axis clipped)")
    return _task_joint_grid(acc_tasks, 2.6, "q̈ [rad/s²]", draw, figdir / "accelerations.png")


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
