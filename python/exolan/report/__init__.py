"""Tables, statistics, figures and the written report of ``exolan reproduce``.

Everything printed as "ours" is computed here from the runs' stored results; the only hard-coded numbers
are the paper's (``PAPER``), always labelled as the paper's, measured on its real EPIC-lab data.

Layout: ``stats`` (the paper's numbers, aggregation, paired tests, verdicts), ``figures`` (one function per
figure), ``markdown`` (one function per section of report.md); ``build`` here ties them together.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from ..runio import write_json
from ..study import RunSpec, Scale, method_label, method_name
from .figures import _figures
from .markdown import _markdown
from .stats import (FD_VARIANTS, PAPER, PAPER_NORM_KEY, REFERENCE_KEY, _fd_claims, _grad_norms, horizon_key,
                    _intention_claims, _real_claims, _taskid, amplification, fd_stats, paired, torque_stats,
                    verdict)

__all__ = ["PAPER", "amplification", "build", "fd_stats", "paired", "torque_stats", "verdict"]


def build(out: Path, scale: Scale, specs: list[RunSpec], results: dict[str, dict], meta: dict, log=print) -> dict:
    out = Path(out)
    figdir = out / "figures"
    figdir.mkdir(exist_ok=True)
    groups = meta.get("task_groups") or {}

    def runs_of(dataset, arch, lim, w_fd=0.0, w_ms=0.0, ms_norm="state", h=None):
        h = scale.ms_horizons[0] if h is None else h
        return [results[s.run_id] for s in specs if s.dataset == dataset and s.arch == arch and s.lim == lim
                and s.w_fd == w_fd and s.w_ms == w_ms and (not w_ms or (s.ms_norm, s.ms_horizon) == (ms_norm, h))
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
        for h in scale.ms_horizons[1:]:
            rr = runs_of("world", "exolan", True, scale.w_fd, scale.w_ms, scale.ms_norm, h)
            if rr:
                key = horizon_key(h)
                starts = rr[0].get("spec", {}).get("ms_starts")
                fd[key] = {"label": f"ExoLaN (w_fd, w_ms, H = {h}" + (f", {starts} starts" if starts else "")
                           + f") [{scale.ms_norm} normalisation]", "ms_norm": scale.ms_norm, "ms_horizon": h,
                           "ms_starts": starts, **fd_stats(rr, scale.horizons, meta.get("dt"))}
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
