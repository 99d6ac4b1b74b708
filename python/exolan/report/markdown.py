"""report.md, one function per section."""
from __future__ import annotations

import numpy as np

from ..study import LABELS, Scale
from .stats import (ALPHA, DIRECTION_ONLY_SIZE, FD_COLS, FD_HEAD, FD_VARIANTS, PAPER, REFERENCE_KEY,
                    SIZE_FRACTION, amplification)


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


def _claims_table(claims) -> list[str]:
    L = [f"A claim **holds** when our change has the paper's sign, is significant over held-out users "
         f"(Wilcoxon p < {ALPHA:g}) and, where there are ≥ 2 seeds, over seeds (paired t p < {ALPHA:g}: every user "
         f"is scored with the same seed's model, so training noise alone can look significant over users) and is "
         f"at least {SIZE_FRACTION:.0%} of the paper's relative change "
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
         "*holds* when our change has the paper's sign and p < 0.05 over users and over seeds. With 7 held-out users "
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
    cut = sum(1 for s in clock["sessions"] if not s.get("finished", True))
    cut_s = f", {cut} interrupted, each counted to its last finished run" if cut else ""
    return (f"**Wall time of the sweep: {clock['total'] / 60:.1f} min** (world {t.get('world', 0):.0f} s, runs "
            f"{t.get('runs', 0):.0f} s, the world's reference rollouts {t.get('reference', 0):.0f} s; "
            f"{n} invocation{'s' if n > 1 else ''}{cut_s}, `sweep_clock.json`); {now}.")


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
         f"{scale.w_ms:g} (H = {scale.ms_horizons[0]}"
         + "".join(f"; also H = {h}" for h in scale.ms_horizons[1:]) + "). Held-out users, all tasks (seen and unseen). q and q̇ MSE after 4, 10, "
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
        L += _fd_where_table(fd, scale.horizons[-1])
    for k in ("accelerations", "rollouts", "rollout_error_growth"):
        if k in figs:
            L += ["", f"![{k}]({figs[k]})"]
    L += [""]
    return L


def _fd_table(fd: dict) -> list[str]:
    """Held-out q̈, q and q̇ errors per forward-dynamics variant: ours, then the paper's."""
    L = ["| model | " + " | ".join(FD_HEAD) + " |", "|---|" + "---|" * len(FD_COLS)]
    for key in [k for k in fd if not k.startswith(REFERENCE_KEY)] + [k for k in fd if k.startswith(REFERENCE_KEY)]:
        if key in fd:
            L.append(f"| **ours** {fd[key]['label']} | " + " | ".join(_pm(fd[key]["mean_std"].get(c)) for c in FD_COLS)
                     + " |")
    for key, _, _, label in FD_VARIANTS:
        if key not in PAPER["fd"]:
            continue
        L.append(f"| *paper (real data)* {label} | " + " | ".join(_f(PAPER['fd'][key][c]) for c in FD_COLS) + " |")
    return L


FLOOR_KEY = f"{REFERENCE_KEY}: true inputs, recorded τ"


def _fd_where_table(fd: dict, h: int) -> list[str]:
    """Where the multi-step loss acts and where it does not: q̇_h MSE of w_fd and w_fd + w_ms per task and per
    joint, with the true leg fed the true unrecorded inputs and the recorded τ beside them (how far each task
    sits above what the recorded torque allows)."""
    a, b = fd.get("w_fd"), fd.get("w_fd+w_ms")
    if not a or not b or "per_task" not in a or "per_task" not in b:
        return []
    floor = fd.get(FLOOR_KEY, {}).get("per_task", {})
    c = f"qd{h}"
    L = ["", f"### Where the multi-step loss acts: q̇_{h} MSE per task and joint", "",
         f"Held-out users, seed means; change = w_fd + w_ms against w_fd (negative = the multi-step loss "
         f"helps), total then hip / knee; *floor*: the world's true leg fed the true pelvis motion and ground force "
         f"with the recorded τ. A learned model can sit below it (it learns what the recorded torque gets wrong) or "
         f"above it (it does not see the unrecorded inputs). Tasks by split, then by w_fd's error.", "",
         f"| task | split | w_fd q̈ | w_fd q̇_{h} | w_fd + w_ms q̇_{h} | change (hip / knee) | floor q̇_{h} | "
         "w_fd / floor |", "|---|---|---|---|---|---|---|---|"]
    tasks = sorted(set(a["per_task"]) & set(b["per_task"]),
                   key=lambda t: (a["per_task"][t]["split"], -a["per_task"][t][c]))

    def row(name, split, A, B, F):
        hk = " / ".join(_pct(_rel(x, y)) for x, y in zip(B[f"{c}_joints"], A[f"{c}_joints"]))
        floor_cells = f"{_f(F[c])} | {_f(A[c] / F[c])}" if F else "— | —"
        return (f"| {name} | {split} | {_f(A['qdd'])} | {_f(A[c])} | {_f(B[c])} | {_pct(_rel(B[c], A[c]))} ({hk}) | "
                f"{floor_cells} |")

    for t in tasks:
        L.append(row(t, a["per_task"][t]["split"], a["per_task"][t], b["per_task"][t], floor.get(t)))
    for split in ("seen", "unseen"):
        ts = [t for t in tasks if a["per_task"][t]["split"] == split]
        if ts:
            mean = lambda d, k: float(np.mean([d[t][k] for t in ts]))
            mj = lambda d, k: [float(x) for x in np.mean([d[t][k] for t in ts], axis=0)]
            A, B = ({"qdd": mean(d, "qdd"), c: mean(d, c), f"{c}_joints": mj(d, f"{c}_joints")}
                    for d in (a["per_task"], b["per_task"]))
            F = {c: mean(floor, c)} if all(t in floor for t in ts) else None
            L.append(row(f"**mean of the {len(ts)} {split} tasks**", split, A, B, F))
    return L


def _amplification_table(fd: dict, horizons) -> list[str]:
    """How much of each rollout error is the q̈ error integrated and how much compounds (`amplification`), and
    the multi-step loss' change of q̇ at the last horizon split into those two factors: ours and the paper's."""
    ours = [k for k in fd if not k.startswith(REFERENCE_KEY) and f"amp{horizons[-1]}" in fd[k]["mean_std"]]
    if not ours:
        return []
    h_last = horizons[-1]
    L = ["", "**Rollout amplification** A_h = q̇_h MSE / ((h·dt)² · q̈ MSE): about 1 when a model's q̈ error "
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
        rows = [("ours", split(m("w_fd"), m("w_fd+w_ms")))]
        rows += [(f"ours at H = {fd[k]['ms_horizon']}", split(m("w_fd"), m(k))) for k in fd if "ms_horizon" in fd[k]]
        rows += [("paper", split(P["w_fd"], P["w_fd+w_ms"]))]
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
