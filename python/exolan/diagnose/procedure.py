"""The diagnosis procedure, in order: fit the base, refit the reference, let the physics-first path decide where
the parametric base is adequate (`physics_path`), else the learned path: screen and test every candidate term by
term, the nulls of exo-driven terms, forward selection, the extended model. Each step lives in its own module;
this one reads as the sequence. The rules in plain words, and the significance budget: docs/DIAGNOSIS.md."""
from __future__ import annotations

import copy
import time

import numpy as np
import torch

from . import extended, nulls, selection, single
from . import residuals as R
from .candidates import LIBRARY
from .base import make_base
from . import weights
from .flat import prepare, sample_groups
from .limits import all_limits, torque_unit
from .refits import FitCache, base_fit, metrics, refit
from .results import public, strip
from .rules import paired_gain
from .session import Session, Tools
from .settings import Budget, Settings, log, step
from .workers import Ahead, Workers, running

__all__ = ["Settings", "Tools", "load_trials", "run"]


def load_trials(data):
    """A path (layout 1 or 2, through `exolan.data.load`) or an already loaded list of trials."""
    if isinstance(data, (list, tuple)):
        return list(data)
    from .. import data as _data
    ds = _data.load(str(data))
    return list(getattr(ds, "trials", ds))


def describe_base(base, flat, s: Settings, given: bool) -> str:
    """What the reference model is, in words, for the report: where it comes from and which contact and body
    terms it carries (a base trained here and a given run's pooled model carry the same optional parts)."""
    text = ("given model, context pooled per trial" if given else
            f"trained here: slow-context DeLaN{' + LIM' if flat.has_insole else ''}")
    if getattr(base, "body_load", None) is not None:
        text += " + gravity scaled by the other leg load"
    if getattr(base, "surge", None) is not None:
        text += " + pelvis fore-aft acceleration from both insoles"
    if getattr(base, "cop_lever", None) is not None:
        text += " + centre-of-pressure lever"
    if getattr(base, "lim_cop", None) not in (None, False):    # a flag here, a correction network on a given run
        text += " (insole lever arms see the centre of pressure)"
    if not given:
        return text + f", {s.steps_base} steps"
    return text + (f", adapted to the data's training segments ({s.steps_base} steps)" if s.adapt_model else "")


def new_base(flat, s: Settings):
    """The slow-context base before its fit (`base.make_base` with the settings' options)."""
    return make_base(flat, hidden=s.hidden, z_dim=s.z_dim, seed=s.seed, pelvis_tilt=s.pelvis_tilt,
                     pelvis_surge=s.pelvis_surge, lim_cop=s.lim_cop)


def fit_base(flat, s: Settings, model, start=None):
    """The base (slow-context DeLaN, or a given run's pooled model adapted to these data) and its state before the
    fit, from which fits from scratch start (None: a model judged as given, whose extended models are warm starts).
    A given run's networks and the diagnosis' terms are fitted with the base's own schedule (`base.PooledContext`).
    `start`: the slow-context base before its fit, where the caller made it already (`new_base`)."""
    t0 = time.time()
    base = model if model is not None else copy.deepcopy(start) if start is not None else new_base(flat, s)
    base_start = copy.deepcopy(base) if (model is None or s.adapt_model) else None
    if base_start is not None:
        base_fit(base, flat, s)
    log(s, f"base fitted in {time.time() - t0:.0f} s")
    if s.weighted:
        t1 = time.time()
        flat.weight = weights.of_base(base, flat, s)
        log(s, f"fit weights per trial and joint ({time.time() - t1:.0f} s; inverse misfit of the base" +
               (" less every candidate's column" if s.weights_explained else "") + "): " +
               ", ".join(f"{nm} {float(flat.weight[:, j].min()):.2g}..{float(flat.weight[:, j].max()):.2g}"
                         for j, nm in enumerate(flat.joints)))
    return base, base_start, describe_base(base, flat, s, given=model is not None)


def physics_first(flat, s: Settings, ref, joint_ids, phys, gate, ahead=None) -> dict:
    """The gate per joint equation (`gate`: `physics_path.adequacy` or a test's stub): the parametric family at its
    most (every linear term at once) against the learned reference; the selection runs on the candidates of the
    joints where it is not worse on held-out data, then the cross-check, then the gate again with the accepted terms
    only. Returns the gate with `paths`: joint name -> the path that decides its candidates. `ahead`: physics first's
    extended model started ahead, cancelled as soon as a joint fails the first gate (the learned path then decides
    that joint, and a model of physics first's alone is never handed over): its core goes to the selection."""
    from . import physics, physics_checks, physics_path

    first = gate(physics.saturated_held(phys, flat), ref, flat, joint_ids, n_boot=s.n_boot,
                 what="the parametric base with every linear candidate term")
    joints = {nm: dict(v, model=first["model"]) for nm, v in first["joints"].items()}
    passing = [j for j in joint_ids if joints[flat.joints[j]]["adequate"]]
    if ahead is not None and len(passing) < len(joint_ids):
        ahead.cancel()
    while passing:
        # a joint that fails the second gate leaves to the learned path: the selection runs again without it, so
        # its acceptances count in no other joint's Holm thresholds (the set only shrinks: at most one rerun a joint)
        physics_path.select_terms(phys, flat, s, passing, lambda m: log(s, m))
        log(s, phys.summary(flat.joints))
        residual = physics_path.learned_residual(ref, flat)
        physics_checks.cross_check(phys, flat, residual, passing, log=lambda m: log(s, m))
        physics_checks.rivals(phys, flat, residual, passing, n_boot=max(s.n_boot // 2, 200), log=lambda m: log(s, m))
        physics_checks.settle(phys, flat, residual, passing, n_boot=max(s.n_boot // 2, 200), log=lambda m: log(s, m))
        second = gate(phys.e_held, ref, flat, passing, n_boot=s.n_boot,
                      what="the parametric base with its accepted terms")
        joints.update({nm: dict(v, model=second["model"]) for nm, v in second["joints"].items()})
        still = [j for j in passing if joints[flat.joints[j]]["adequate"]]
        if still == passing:
            break
        log(s, f"{', '.join(flat.joints[j] for j in passing if j not in still)}: not adequate with the accepted terms; "
               "the selection runs again on " + (", ".join(flat.joints[j] for j in still) or "no joint"))
        passing = still
        if not passing:             # as if no joint had passed: physics first decides and reports nothing
            physics.reset(phys)
    adequate = physics_path.per_joint(joints, first.get("rule", ""))
    for nm, v in joints.items():
        log(s, f"{nm}: parametric base held-out MSE {v['parametric_mse']:.4g}, learned {v['learned_mse']:.4g} "
               f"({torque_unit(flat)})² ({v['model']}): the {adequate['paths'][nm]} path decides its candidates")
    return adequate


def twin_refit(base, flat, s: Settings, k: int):
    """Twin k of the reference: the same warm refit of the base with another minibatch order (seed offset 2 + k)."""
    m = copy.deepcopy(base)
    refit(m, flat, s, 2 + k)
    return m


def refit_noise(base, flat, s: Settings, e_ref, errors, n: int, scale: str, workers: Workers | None = None,
                first: Ahead | None = None) -> dict:
    """The refit noise σ_r: the RMS held-out difference between the reference and `n` twin refits that differ
    from it only in their minibatch order (rule 2). `first`: twin 0, started beside the reference's refit
    (`reference`); the same bits as made here."""
    def twin(k):
        return errors(first.result() if k == 0 and first is not None else twin_refit(base, flat, s, k))[1]
    order = list(range(1, n)) + [0]        # twin 0 last: started ahead, it is most likely made when asked for
    made = dict(zip(order, (workers or Workers()).map([lambda k=k: twin(k) for k in order])))
    deltas, twin_d, floor = [], [], None
    for k in range(n):
        e_twin = made[k]
        if k == 0:
            floor = paired_gain(e_ref, e_twin, s)
        deltas.append(float((e_ref - e_twin).mean()))
        twin_d.append(e_ref - e_twin)
    sigma_r = float(np.sqrt(np.mean(np.square(deltas))))
    return dict(gain=floor["gain"], ci=floor["ci"], sigma=sigma_r, twin_differences=deltas, scale=scale,
                twin_d=twin_d)


def reference(flat, s: Settings, model, tools: Tools, workers: Workers, joint_ids, start=None) -> tuple[Session, str]:
    """Step 1: the base, the fit weights and the reference refit, in the learned path's `Session` (every decision
    compares held-out errors weighted as the fits are; what the report calls a held-out gain is the unweighted one,
    the user's torque error). Returns it and the base's description."""
    base, base_start, base_source = fit_base(flat, s, model, start)
    held = flat.index("held")
    w_held = flat.weight[held].numpy().astype(np.float64) if s.decide_weighted and flat.weight is not None else None
    # every path measures the refit noise with at least twin 0: on the core the reference's refit leaves free
    first_twin = Ahead(workers, lambda: twin_refit(base, flat, s, 0))
    ref = copy.deepcopy(base)
    refit(ref, flat, s)
    ss = Session(flat=flat, s=s, tools=tools, held=held, w_held=w_held,
                 scale="misfit-weighted" if w_held is not None else "unweighted", base=base, base_start=base_start,
                 ref=ref, e_ref_user=None, e_ref=None, sigma_r=float("nan"), twin_d=[], joint_ids=joint_ids,
                 budget=Budget(s.alpha, sum(1 for eff in s.effects for _ in joint_ids
                                            if flat.has_exo or not LIBRARY[eff].needs_exo)), workers=workers,
                 first_twin=first_twin)
    ss.e_ref_user, ss.e_ref = ss.errors(ref)
    return ss, base_source


def run(data, model=None, settings: Settings | None = None, trials_loaded=None, tools: Tools | None = None) -> dict:
    """The whole procedure; returns the result dict (JSON-ready parts plus objects for the report). `tools`: the
    learned path's fits and judgements (`session.Tools`; tests pass stubs)."""
    s, tools = settings or Settings(), tools or Tools()
    workers = Workers(s.workers)
    torch.manual_seed(s.seed)
    trials = trials_loaded if trials_loaded is not None else load_trials(data)
    flat = prepare(trials, max_delay=s.max_delay, seed=s.seed)
    if s.joints is not None and set(s.joints) - set(flat.joints):
        raise ValueError(f"unknown joint(s) {sorted(set(s.joints) - set(flat.joints))}; the data have {list(flat.joints)}")
    held = flat.index("held")
    log(s, f"{len(trials)} trials, {flat.q.shape[0]} samples ({len(flat.index('train'))} train, {len(held)} held out), "
           f"joints {flat.joints} {flat.joint_types}, exo={flat.has_exo}, insole={flat.has_insole}")
    joint_ids = s.joint_ids(flat)
    from . import physics_path
    start = new_base(flat, s) if model is None else None      # made here: the fit started ahead needs it too
    ahead = []

    def parametric():
        from . import physics
        p = physics.setup(flat, s.effects, joint_ids, alpha=s.alpha, cutoff_hz=s.cutoff_hz, max_delay=s.max_delay)
        log(s, f"parametric base fitted ({p.seconds:.1f} s)")
        if start is not None and workers.n > 1:     # the core the base fit leaves free
            ahead.append(physics_path.extended_ahead(p, flat, s, joint_ids, workers, lambda terms, init:
                                                     tools.fit_without(flat, s, start, terms, init)))
        return p

    step(s, "1/7 base and reference" + (" beside the parametric base" if s.physics_first else ""))
    with running(workers):      # which also stops, on leaving, whatever was started ahead and not taken
        # independent (numpy and torch, each on one thread): side by side where a second worker is free
        (ss, base_source), phys = workers.map([lambda: reference(flat, s, model, tools, workers, joint_ids, start),
                                               parametric if s.physics_first else lambda: None])
        return _after_reference(flat, s, trials, model, tools, workers, joint_ids, held, ss, base_source, phys,
                                ahead[0] if ahead else None)


def _after_reference(flat, s, trials, model, tools, workers, joint_ids, held, ss, base_source, phys, ahead) -> dict:
    """`run` from the gate on: which path decides each joint, rule 6, the learned path, physics first's report.
    `ahead`: physics first's extended model started beside the base fit (`physics_path.extended_ahead`)."""
    from . import compensate, physics_path
    raw = ss
    adequate = physics_first(flat, s, ss.ref, joint_ids, phys, tools.adequacy, ahead) if phys is not None else None
    # each joint's candidates live in its own equation (`ident.JointProblem`): physics first decides those of the
    # joints whose own gate passed, the learned path the others'. (A candidate whose columns touched several
    # joints' equations would go to physics first only if every joint it touches passed; none does today.)
    phys_joints = [j for j in joint_ids if adequate and adequate["paths"][flat.joints[j]] == "physics first"]
    learned_joints = [j for j in joint_ids if j not in phys_joints]
    if ahead is not None and learned_joints:     # the learned path needs both cores, and its report another model
        ahead.cancel()
    # rule 6 (the learned base's check) before the learned path's data are compensated: a term it sets aside must
    # not be taken out of them
    held_models = tools.learned_check(phys, raw.base, raw.ref, flat, s, phys_joints,
                                      physics_path.learned_residual(raw.ref, flat),
                                      lambda m: log(s, m)) if phys_joints else {}
    held_terms, held_init = physics_path.held_terms(phys, phys_joints) if phys_joints and learned_joints else ([], {})
    if held_terms:      # the learned path tests its joints with physics first's terms taken out of the data
        raw.first_twin.cancel()
        log(s, "the learned path's data: " + ", ".join(f"{e}:{flat.joints[j]}" for e, j in held_terms) +
               " removed at their physical sizes; its base and reference fitted again on them")
        ss, base_source = reference(compensate.data(flat, held_terms, held_init, s.max_delay), s, model, tools,
                                    workers, joint_ids)
    # the physics path decides nothing on the refit noise: one twin measures it for the report
    noise = refit_noise(ss.base, ss.flat, s, ss.e_ref, ss.errors,
                        max(int(s.n_twins), 1) if learned_joints else 1, ss.scale, workers, first=ss.first_twin)
    ss.sigma_r, ss.twin_d = noise["sigma"], noise.pop("twin_d")
    log(s, f"reference held-out MSE {ss.e_ref_user.mean():.4g} ({torque_unit(flat)})²; refit noise σ_r "
           f"{ss.sigma_r:.3g} ({ss.scale}, {len(noise['twin_differences'])} twin refits)")
    learned = None
    if learned_joints:      # the budget keeps m of the whole family: no path's thresholds loosen (`physics.select`)
        ss.joint_ids = learned_joints
        learned = learned_path(ss, trials, phys, adequate, base_source, noise)
        if held_terms:
            learned = compensate.results_on_raw(learned, flat, held_terms, held_init, s.max_delay)
    if not phys_joints:
        return learned
    limits = (learned["report"]["detection_limits"] if learned else
              all_limits(flat, s, raw.base_start, raw.ref, held, raw.w_held, ss.sigma_r, ss.budget.single()))
    return physics_path.report(flat, s, trials, raw.base, raw.ref, base_source, noise, phys, adequate, phys_joints,
                               held, limits, lambda m: log(s, m), held_models, learned=learned,
                               fit_without=None if raw.base_start is None else
                               lambda terms, init: (ahead and ahead.take(terms, init)) or
                               tools.fit_without(flat, s, raw.base_start, terms, init))


def learned_path(ss: Session, trials, phys, adequate, base_source: str, noise: dict) -> dict:
    """Steps 2-7 on the learned base (`session.Session` holds what they share)."""
    flat, s = ss.flat, ss.s
    ss.groups, ss.group_kind = sample_groups(flat, ss.held)
    ss.held_subject = flat.subjects_of(ss.held)
    ss.subjects = sorted({m["subject"] for m in flat.trial_meta})
    ss.cache = FitCache(flat, s, ss.base_start, ss.errors, (ss.e_ref_user, ss.e_ref), fit=ss.tools.fresh_fit,
                        confused=ss.tools.inertia_confused, scale=ss.scale, workers=ss.workers)
    starts = R.rollout_starts(flat, s.horizon, seed=s.seed)
    baseline, ro_base = metrics(ss.ref, flat, s, starts)
    baseline.update(source=base_source, noise_floor=noise)
    structure = R.residual_structure(ss.ref, flat, ss.held)
    step(s, "detection limits")
    limits = all_limits(flat, s, ss.base_start, ss.ref, ss.held, ss.w_held, ss.sigma_r, ss.budget.single())
    log(s, f"{ss.budget.m} candidates: a single-term test at {100 * ss.budget.single():.3g} % (family-wise "
           f"{100 * s.alpha:.3g} %, `settings.Budget`)")

    step(s, "2/7 candidates term by term")
    results = single.fit_candidates(ss)                         # 2. screen, warm refit, rules 1, 2, 4, 5; rescue
    step(s, "3/7 nulls of exo-driven terms")
    nulls.run_nulls(ss, results)                                # 3. rule 3 for exo-driven terms
    single.verdicts(results)                                    # 4. single-term verdicts
    nulls.outdone_by_a_doubted_rival(results, lambda eff, name: ss.fitted.get(
        (eff, flat.joints.index(name)), (None, None))[1], lambda a, b: ss.gain(a, b))
    step(s, "5/7 forward selection")
    sel = selection.forward(ss, results)                        # 5. forward selection (Holm)
    selection.without_terms(ss, results)                        # 6. payload
    step(s, "7/7 extended model")
    accepted, model, cis = extended.joint_fit(ss, results, sel.acc_init)     # 7. the extended model
    ext_model, ext_rep, ro_ext = None, None, None
    conf = extended.confirm_model(ss, accepted, model, sel.acc_init) if accepted else None
    if ss.optima_ahead is not None:     # step 7's looks are made: the comparison base started ahead is not wanted
        ss.optima_ahead.cancel()
    if conf is not None and conf["confirmed"]:
        ext_model = conf["model"]
        ext_rep, ro_ext = extended.describe(ss, accepted, conf, cis, sel.acc_init, starts, ro_base)
    extended.notes(ss, results, ext_model, limits)
    for e in results:
        if e["status"] in ("accepted", "ambiguous") and e["kind"] == "finding":
            log(s, e.summary())
    from . import physics_path
    if phys is not None:
        physics_path.attach(results, phys, flat)
    report = {"baseline": strip(baseline),
              "findings": [public(e) for e in results if e["status"] == "accepted"],
              "rejected": [public(e) for e in results if e["status"] != "accepted"],
              "extended": strip(ext_rep) if ext_rep else {"note": "nothing found: the base model is kept",
                                                          **strip(baseline)},
              "residuals": structure, "detection_limits": limits,
              "physics": physics_path.section(phys, flat, adequate) if phys is not None else None,
              "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in s.__dict__.items()},
              "data": dict(trials=len(trials), samples=int(flat.q.shape[0]), heldout=int(len(ss.held)),
                           torque_unit=torque_unit(flat), joints=list(flat.joints), joint_types=list(flat.joint_types),
                           has_exo=flat.has_exo, has_insole=flat.has_insole,
                           split="held-out time segments (1 in 4, ~2 s) within every trial")}
    return dict(report=report, flat=flat, base=ss.base, ref=ss.ref, ext_model=ext_model, ro_base=ro_base,
                ro_ext=ro_ext, results=results)
