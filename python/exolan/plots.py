"""Trial plots (``exolan plot TRIAL_DIR [--out PNG]``): what a person looks at to judge a recording.

Four panels over time, both legs: joint angles (deg), biological joint moments (N m/kg), the
exoskeleton's recorded torque (N m) and the insoles' vertical force (in body weights when the
subject's mass is known from ``<root>/subjects.csv``, else N), with stance shaded.
Values are shown as recorded in the files (layout 1 units).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from .data import DataError, read_subjects
from .recording import _col, _read_csv

COLORS = {"l": "tab:blue", "r": "tab:red"}
LEG = {"l": "left", "r": "right"}


def plot_trial(trial_dir, out=None, window: float | None = 8.0) -> Path:
    """Draw one layout-1 trial directory to a PNG; returns its path.

    ``window``: seconds shown from the start (None = the whole trial); long trials are
    unreadable at full length."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    td = Path(trial_dir)
    exo_p, mom_p = td / "Exo.csv", td / "Joint_Moments_Filt.csv"
    exo = _read_csv(exo_p)
    mom = _read_csv(mom_p) if mom_p.exists() else {}
    t = _col(exo, "time", exo_p)
    mass = None
    subj_csv = td.parent.parent / "subjects.csv"
    if subj_csv.exists():
        try:
            mass = read_subjects(subj_csv)[0].get(td.parent.name)
        except DataError:
            mass = None
    sel = np.ones(len(t), bool) if window is None else (t <= t[0] + window)
    tt = t[sel]

    fig, axes = plt.subplots(4, 1, figsize=(11, 10), sharex=True, constrained_layout=True)
    ax_a, ax_m, ax_e, ax_f = axes
    for s in ("l", "r"):
        c = COLORS[s]
        for joint, ls in (("hip", "-"), ("knee", "--")):
            name = f"{joint}_angle_{s}"
            if name in exo:
                ax_a.plot(tt, _col(exo, name, exo_p)[sel], ls, color=c, lw=1.2, label=f"{joint} {LEG[s]}")
            mname = f"hip_flexion_{s}_moment" if joint == "hip" else f"knee_angle_{s}_moment"
            if mname in mom:
                ax_m.plot(tt, _col(mom, mname, mom_p)[sel], ls, color=c, lw=1.2, label=f"{joint} {LEG[s]}")
            ename = f"{joint}_angle_{s}_torque_measured"
            if ename in exo:
                ax_e.plot(tt, _col(exo, ename, exo_p)[sel], ls, color=c, lw=1.2, label=f"{joint} {LEG[s]}")
        fname = f"insole_{s}_force_y"
        if fname in exo:
            f = _col(exo, fname, exo_p)[sel]
            scale = (mass * 9.81) if mass else 1.0
            ax_f.plot(tt, f / scale, color=c, lw=1.2, label=f"{LEG[s]} foot")
            on = np.nan_to_num(f) > 20
            ax_f.fill_between(tt, 0, 1, where=on, transform=ax_f.get_xaxis_transform(), color=c, alpha=0.07,
                              lw=0)
    ax_a.set_ylabel("joint angle [deg]\n(flexion +)")
    ax_m.set_ylabel("biological moment\n[N m/kg] (flexion +)")
    ax_e.set_ylabel("exoskeleton torque\n[N m] (recorded)")
    ax_f.set_ylabel("insole vertical force\n" + ("[body weights]" if mass else "[N]"))
    ax_f.set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.axhline(0, color="k", lw=0.5)
        if ax.get_lines():
            ax.legend(loc="upper right", fontsize=8, ncol=4, framealpha=0.8)
    shown = "" if window is None or t[-1] - t[0] <= window else f" (first {window:g} s of {t[-1] - t[0]:.1f} s)"
    who = f"{td.parent.name} / {td.name}" + (f", {mass:g} kg" if mass else "")
    fig.suptitle(f"{who}{shown}; shaded: foot loaded (> 20 N)")
    if out is None:
        out = Path.cwd() / f"{td.parent.name}_{td.name}.png"
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".tmp-{out.name}")
    fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    tmp.replace(out)
    return out


def cli_plot(args: argparse.Namespace) -> int:
    out = plot_trial(args.trial_dir, args.out)  # errors: one line from exolan.cli.main
    print(f"wrote {out}")
    return 0
