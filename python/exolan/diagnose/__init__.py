"""Diagnosis (`exolan diagnose DATA [--model RUN] --out DIR`): what the model's physics gets wrong, the
physical cause, the extended model and its measured gain on held-out data.

API for the pipeline::

    from exolan.diagnose import diagnose
    report = diagnose("path/to/world", model=None, out="out/diagnosis")   # -> the diagnosis.json dict

`data`: a dataset path (layout 1 or 2, read by `exolan.data.load`) or a list of `Trial`s. `model`: None
(a slow-context DeLaN + LIM is trained on the training segments first), a run directory, or a DeLaN-based
`ExoModel`; a given model's context is pooled per trial (a slow context, DIAGNOSIS_PITFALLS.md) and the model
is fitted to the training segments at that context first (`adapt_model=False`: judged as given). `out`:
directory for diagnosis.json, diagnosis.md, the plots and (when something is accepted) the extended
model's `ext.*` tensors. `quick=True` uses short fits (tests); keyword `settings` overrides any
`procedure.Settings` field.

The procedure is `exolan.diagnose.procedure` (its steps in their own modules) and its decision rule is in docs/DIAGNOSIS.md; the candidate library
in `exolan.diagnose.candidates`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .candidates import CONFUSABLE, LIBRARY
from .procedure import Settings, load_trials, run

__all__ = ["diagnose", "cli_diagnose", "Settings", "LIBRARY", "CONFUSABLE"]

QUICK = dict(steps_base=1500, steps_refit=300, hidden=32, n_boot=400, batch=2048)


def _pooled_base(model, trials, pelvis_surge: bool = True, lim_cop: bool = True):
    """A trained DeLaN-based model with z averaged over each trial: the trials' starting codes (`base.PooledContext`)."""
    from ..train import context_of
    from .base import PooledContext
    from .flat import DTYPE

    if not getattr(model, "is_lagrangian", False):
        raise ValueError("diagnosis needs a DeLaN-based model: its physics is what is diagnosed")
    model = model.to(DTYPE)
    zs = []
    with torch.no_grad():
        for t in trials:
            ctx = torch.as_tensor(np.nan_to_num(context_of(t)), dtype=DTYPE)
            z = model.context(ctx.unsqueeze(0))[0]
            ok = torch.as_tensor(np.asarray(t.valid, bool))
            zs.append(z[ok].mean(0) if ok.any() and z.shape[-1] else z.mean(0) if z.shape[-1] else z[0])
    # the other leg's load term is active only where a trial's partner (other side) is in the data
    return PooledContext(model, torch.stack(zs), other_leg_load=True, pelvis_surge=pelvis_surge, lim_cop=lim_cop)


def diagnose(data, model=None, out=None, quick: bool = False, **settings) -> dict:
    """Run the diagnosis; returns the diagnosis.json dict (also written to `out` when given).

    Torch and numpy's BLAS run on `EXOLAN_THREADS` threads (default 1) for the call: on two cores shared with other
    jobs, two threads made a base-fit step slower than one, and physics first's least squares 2x slower (10 %
    faster alone; docs/DIAGNOSIS.md, "Measurements behind the code")."""
    import os

    from threadpoolctl import threadpool_limits

    threads, n = torch.get_num_threads(), max(1, int(os.environ.get("EXOLAN_THREADS", 1)))
    torch.set_num_threads(n)
    try:
        with threadpool_limits(limits=n, user_api="blas"):
            return _diagnose(data, model, out, quick, **settings)
    finally:
        torch.set_num_threads(threads)


def _diagnose(data, model=None, out=None, quick: bool = False, **settings) -> dict:
    from . import report as _report

    cfg = dict(QUICK) if quick else {}
    cfg.update(settings)
    tools = cfg.pop("tools", None)      # stubs for the learned path's fits and judgements (tests)
    s = Settings(**cfg)
    trials = load_trials(data)
    base = None
    if model is not None:
        if isinstance(model, (str, Path)):
            from ..train import load_run
            model, _meta = load_run(model)
        base = _pooled_base(model, trials, pelvis_surge=s.pelvis_surge, lim_cop=s.lim_cop)
    res = run(None, model=base, settings=s, trials_loaded=trials, tools=tools)
    if out is not None:
        out = Path(out)
        rep = _report.write(out, res)
        if res.get("ext_model") is not None:
            _save_ext(out, res)
        return rep
    return res["report"]


def _subject_terms(ext, flat) -> str:
    """"effect:joint -> subjects" of an extended model's subject-specific (gated) terms, for file metadata."""
    parts = []
    for eff, per_joint in ext.gate_trials().items():
        for j, on in per_joint.items():
            users = sorted({flat.trial_meta[i]["subject"] for i in np.flatnonzero(on > 0)})
            parts.append(f"{eff}:{flat.joints[j]} -> {'+'.join(users)}")
    for eff, per_joint in ext.size_values().items():
        for j in per_joint:
            parts.append(f"{eff}:{flat.joints[j]} -> every user at their own size")
    return "; ".join(parts)


def _save_ext(out: Path, res: dict) -> None:
    """The extended model's `ext.*` tensors (float64, DESIGN.md section 4) as safetensors."""
    try:
        from safetensors.numpy import save_file
    except ImportError:
        return
    ext, flat = res["ext_model"], res["flat"]
    # subject-specific terms: the files hold their values, to apply for those users only
    who = _subject_terms(ext, flat) if ext.gated else None
    t = ext.ext_tensors()
    if "backlash" in ext.effects:       # a sensor term: not in the engine's tensors (`export_extended`'s metadata)
        t["ext.backlash"] = np.asarray(ext.physical()["backlash"], dtype=np.float64)
    if t:
        meta = {"format": "exolan-ext", "joint_names": str(list(flat.joints)), "coulomb_eps": str(ext.coulomb_eps)}
        if who:
            meta["subject_terms"] = who
        save_file({k: np.ascontiguousarray(v) for k, v in t.items()}, str(out / "ext.safetensors"), metadata=meta)
    # the whole extended model in the engine's weight format, at the mean context of the trials
    from .base import SlowContextDeLaN
    from .export import export_extended
    if isinstance(ext.base, SlowContextDeLaN):
        try:
            meta = {"train_note": "exolan diagnose: slow-context base at the mean trial context"}
            if who:
                meta["subject_terms"] = (who + " (this file applies them for every user; "
                                         "extended_<subject>.safetensors hold each user's own terms)")
            codes = ext.base.codes.weight.detach()
            export_extended(ext, out / "extended.safetensors", codes.mean(0), joint_names=flat.joints, dt=flat.dt,
                            meta=meta)
            # with subject-specific terms, one file per user: that user's terms at the mean of their trials' codes
            users = sorted({m["subject"] for m in flat.trial_meta}) if ext.gated else []
            for u in users:
                rows = [i for i, m in enumerate(flat.trial_meta) if m["subject"] == u]
                export_extended(ext, out / f"extended_{u}.safetensors", codes[rows].mean(0), joint_names=flat.joints,
                                dt=flat.dt, trial=rows[0],
                                meta={"train_note": f"exolan diagnose: slow-context base at the mean context of "
                                                    f"{u}'s trials, with {u}'s terms", "subject": u})
        except Exception as exc:  # the report stands without the export; say why
            (out / "extended_export_error.txt").write_text(repr(exc))


def cli_diagnose(args) -> int:
    settings = {}
    if getattr(args, "effects", None):
        eff = tuple(e.strip() for e in args.effects.split(",") if e.strip())
        unknown = [e for e in eff if e not in LIBRARY]
        if unknown:
            raise SystemExit(f"exolan diagnose: unknown effect(s) {', '.join(unknown)}; known: {', '.join(LIBRARY)}")
        settings["effects"] = tuple(e for e in eff if e in Settings().effects)
    if getattr(args, "joints", None):
        settings["joints"] = tuple(j.strip() for j in args.joints.split(",") if j.strip())
    if getattr(args, "seed", None) is not None:
        settings["seed"] = args.seed
    if getattr(args, "unweighted", False):
        settings["weighted"] = False
    if getattr(args, "pelvis_tilt", False):
        settings["pelvis_tilt"] = True
    if getattr(args, "no_pelvis_surge", False):
        settings["pelvis_surge"] = False
    if getattr(args, "no_lim_cop", False):
        settings["lim_cop"] = False
    if getattr(args, "no_adapt_model", False):
        settings["adapt_model"] = False
    if getattr(args, "measured_gain_limit", False):
        settings["inject_gain"] = True
    if getattr(args, "learned_only", False):
        settings["physics_first"] = False
    if getattr(args, "measured_delay_limit", False):
        settings["inject_delay"] = True
    if getattr(args, "no_rescue", False):
        settings["rescue"] = False
    if getattr(args, "rescue_frictions", False):
        settings["rescue_frictions"] = True
    if getattr(args, "optima", None) is not None:
        settings["n_optima"] = args.optima
    if getattr(args, "paired_seeds", None) is not None:
        settings["n_paired"] = args.paired_seeds
    if getattr(args, "fit_workers", None) is not None:
        settings["workers"] = args.fit_workers
    rep = diagnose(args.data, model=args.model, out=args.out, quick=bool(getattr(args, "quick", False)), **settings)
    found = rep["findings"]
    if found:
        for f in found:
            print(f"found: {f['effect']} on {f['joint']} = {f['estimate']:.4g} {f['unit']} "
                  f"(CI {f['ci'][0]:.4g} .. {f['ci'][1]:.4g}), held-out gain {f['heldout_gain']:.3g}")
    else:
        print("nothing found")
    print(f"report: {Path(args.out) / 'diagnosis.md'}")
    return 0
