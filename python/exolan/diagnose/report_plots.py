"""The diagnosis report's plots (PNG): residual against velocity, the residual's cross-correlations, rollout errors,
and each candidate's held-out gain."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .flat import Flat
from .residuals import residuals


def plot_residual_vs_velocity(out: Path, flat: Flat, ref, ext=None, max_points: int = 4000) -> str:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    held = flat.index("held")
    if len(held) > max_points:
        held = held[torch.linspace(0, len(held) - 1, max_points).long()]
    r0 = residuals(ref, flat, held)
    r1 = residuals(ext, flat, held) if ext is not None else None
    n = flat.n
    fig, axes = plt.subplots(1, n, figsize=(5 * n, 4), squeeze=False)
    for j in range(n):
        ax = axes[0, j]
        v = flat.qd[held, j].numpy()
        ax.scatter(v, r0[:, j], s=2, alpha=0.35, label="base model", color="tab:red")
        if r1 is not None:
            ax.scatter(v, r1[:, j], s=2, alpha=0.35, label="extended model", color="tab:blue")
        ax.axhline(0, color="k", lw=0.5)
        unit_v = "m/s" if flat.joint_types[j] == "prismatic" else "rad/s"
        unit_t = "N" if flat.joint_types[j] == "prismatic" else "N m"
        ax.set_xlabel(f"{flat.joints[j]} velocity [{unit_v}]")
        ax.set_ylabel(f"torque residual τ_rec − τ̂ [{unit_t}]")
        ax.set_title(f"{flat.joints[j]}: held-out residual vs velocity")
        ax.legend(markerscale=4, fontsize=8)
    fig.tight_layout()
    name = "residual_vs_velocity.png"
    fig.savefig(out / name, dpi=90)
    plt.close(fig)
    return name


def plot_ccf(out: Path, structure: dict, flat: Flat) -> str:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = flat.n
    fig, axes = plt.subplots(1, n, figsize=(5.5 * n, 4), squeeze=False)
    for j, name in enumerate(flat.joints):
        ax = axes[0, j]
        cc = structure[name]["ccf"]
        keys = [f"qd_{name}", f"qdd_{name}", f"q_{name}"]
        if flat.has_exo:
            keys += [f"tau_e_{name}", f"tau_e_rate_{name}"]
        if flat.has_insole:
            keys += ["f_v"]
        band = None
        for k in keys:
            if k not in cc:
                continue
            ax.plot(cc[k]["lags"], cc[k]["ccf"], label=k, lw=1)
            band = cc[k]["band"] if band is None or not np.isfinite(band) else max(band, cc[k]["band"])
        if band is not None and np.isfinite(band):
            ax.axhspan(-band, band, color="0.85", label="95% band (no relation)")
        ax.set_xlabel("lag [samples] (feature leads at positive lag)")
        ax.set_ylabel("cross-correlation with residual")
        ax.set_title(f"{name}: residual cross-correlations (base model)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fname = "residual_ccf.png"
    fig.savefig(out / fname, dpi=90)
    plt.close(fig)
    return fname


def plot_rollouts(out: Path, flat: Flat, ro_base: dict, ro_ext: dict | None) -> str:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    H = np.arange(1, len(ro_base["q"]) + 1)
    for ax, key, lab in ((axes[0], "q", "q MSE [rad²]"), (axes[1], "qd", "q̇ MSE [rad²/s²]")):
        ax.semilogy(H, ro_base[key], "o-", color="tab:red", label="base model", ms=3)
        if ro_ext is not None and len(ro_ext[key]):
            ax.semilogy(H, ro_ext[key], "o-", color="tab:blue", label="extended model", ms=3)
        ax.set_xlabel(f"open-loop horizon [steps of {flat.dt * 1000:.0f} ms]")
        ax.set_ylabel(lab)
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.suptitle("open-loop rollout error vs horizon (held-out segments)")
    fig.tight_layout()
    fname = "rollout_error.png"
    fig.savefig(out / fname, dpi=90)
    plt.close(fig)
    return fname


def plot_gains(out: Path, results: list, unit: str = "N m/kg") -> str | None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [e for e in results if e.get("heldout_gain") is not None and e.get("heldout_gain_ci") is not None]
    if not rows:
        return None
    fig, ax = plt.subplots(figsize=(7, 0.3 * len(rows) + 1.5))
    colors = {"accepted": "tab:green", "rejected": "0.5", "absorbable": "tab:orange", "ambiguous": "tab:purple"}
    for i, e in enumerate(rows):
        g, (lo, hi) = e["heldout_gain"], e["heldout_gain_ci"]
        ax.errorbar([g], [i], xerr=[[g - lo], [hi - g]], fmt="o", color=colors.get(e["status"], "k"), ms=4)
    ax.set_yticks(range(len(rows)))
    ax.set_yticklabels([f"{e['effect']}:{e['joint']} ({e['status']})" for e in rows], fontsize=7)
    ax.axvline(0, color="k", lw=0.5)
    ax.set_xscale("symlog", linthresh=1e-3)
    what = "mass-normalised torque MSE" if unit == "N m/kg" else "torque MSE"
    ax.set_xlabel(f"held-out gain in {what} [({unit})²]\nwith 95% block-bootstrap CI")
    fig.tight_layout()
    fname = "candidate_gains.png"
    fig.savefig(out / fname, dpi=90, bbox_inches="tight")
    plt.close(fig)
    return fname
