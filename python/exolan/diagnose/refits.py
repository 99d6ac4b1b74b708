"""Fits and their caches: the warm refit, the fit from scratch (`fresh_fit`), the term-free fits at other seeds
(the noise between optima), the reference's refit with terms frozen, held-out errors, and `FitCache`, which makes
each of those fits once per run."""
from __future__ import annotations

import copy
import functools
import time
from dataclasses import replace

import numpy as np
import torch

from ..extensions import ExtendedModel
from . import residuals as R
from .export import extend
from .fit import sq_errors, train
from .flat import Flat
from .settings import Settings, heartbeat, log
from .workers import Workers


def held_errors(model, flat: Flat, held: torch.Tensor, w_held: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Per held-out sample: the user's squared torque error (mass-normalised, summed over joints) and the
    decision's, each joint's error weighted by its trial's fit weight (`fit.misfit_weights`; the same as the
    user's when `w_held` is None).

    Why the decisions weight as the fits do: the fits are weighted least squares, and a held-out criterion
    that matches their objective does not let the tasks the conservative model fits worst (unmeasured pelvis
    motion in calisthenics) dominate a gain's variance — nor lets a term that soaks up their misfit look
    like a gain. The weights come from the base model's training residuals only (measured:
    docs/DIAGNOSIS.md, "Measurements behind the code").
    """
    e = sq_errors(model, flat, held)
    return e.sum(1), (e * w_held).sum(1) if w_held is not None else e.sum(1)


def metrics(model, flat: Flat, s: Settings, starts) -> dict:
    held = flat.index("held")
    m = R.torque_metrics(model, flat, held, n_boot=s.n_boot // 2)
    ro = R.rollout_errors(model, flat, starts, s.horizon)
    m["rollout"] = R.summarise_rollouts(ro)
    m["rollout_curve"] = dict(q=ro["q"], qd=ro["qd"])
    m["energy"] = R.energy_audit(model, flat, held, n_boot=s.n_boot // 2)
    return m, ro


def terms_text(model) -> str:
    """"with viscous_damping:0, ..." for a progress line, or "of the base"."""
    eff = getattr(model, "effects", None)
    if not eff:
        return "of the base"
    return "with " + ", ".join(f"{e}:{j}" for e, js in eff.items() for j in js)


# effects that an inflated inertia can mimic: fitted without the acceleration term (`fresh_fit`)
INERTIA_CONFUSED = ("actuation_delay",)
# a fit from scratch is the longest fit and often the only one running (the extended model's): its steps in two
# pieces take a free core where there is one (`fit.train`; its bits do not depend on whether one was free)
FRESH_PIECES = 2


def base_fit(model, flat: Flat, s: Settings, what: str = "base fit", trainer=train):
    """The base's recipe from `model`'s present state, in place (its steps, rate, batch, seed, acceleration term):
    the base itself and every fit that must differ from it by its data alone (an injection's base, the extended
    model fitted without its terms)."""
    return trainer(model, flat, s.steps_base, lr=s.lr_base, batch=s.batch, seed=s.seed, w_acc=s.w_acc,
                   progress=heartbeat(s, what, s.steps_base))


def refit(model, flat: Flat, s: Settings, seed_offset: int = 1, trainer=train):
    """A warm-start refit with the shared schedule (steps, rates, batch, Polyak averaging, acceleration term)."""
    return trainer(model, flat, s.steps_refit, lr=s.lr_refit, lr_ext=s.lr_ext, batch=s.batch, seed=s.seed + seed_offset,
                 progress=heartbeat(s, "warm refit " + terms_text(model), s.steps_refit),
                 average=s.average, w_acc=s.w_acc)


def inertia_recipe(effects, confused: tuple = INERTIA_CONFUSED) -> bool:
    """Whether a fit from scratch of these terms takes the recipe of an inertia-confused term (`fresh_fit`)."""
    return any(eff in confused for eff, _ in effects)


def fresh_fit(flat: Flat, s: Settings, effects, init: dict, start: torch.nn.Module,
              confused: bool | None = None, trainer=train) -> ExtendedModel:
    """The base model with `effects` present from the first step, fitted from scratch: the reference's budget
    and history (its seed, the base's unweighted steps, then the weighted refit) plus the terms. `start` is the
    base before its fit: a fresh `make_base`, or a given run's pooled model as it was loaded (the adaptation of
    `run` is then redone with the terms present).

    Why from scratch: a warm start keeps what the base already absorbed of an effect (a conservative model
    with a free contact term mimics part of any dissipation or compliance along stereotyped motion), so a
    warm-started parameter is biased towards "no effect", and what it leaves over looks like a further term.
    Why the unweighted steps first: a model fitted weighted from the start fits the worst tasks less and loses
    on the unweighted held-out error for that reason alone (measured, hip Coulomb world).

    With a term that an inflated inertia can mimic (`INERTIA_CONFUSED`: the actuation delay) the terms are
    fitted without the acceleration term, and the inertia is then stabilised by one more refit with it, the
    terms frozen. The acceleration term holds H up (fit.train), and a held-up H takes part of a delay; without it
    H collapses at some states and rollouts diverge; the frictions are not confused with the inertia (measured:
    docs/DIAGNOSIS.md, "Measurements behind the code").

    The terms start at `init`, their warm estimates. A torque gain's fit from scratch is not identified by the
    data alone: along the exo torque's copy of the joint torque it trades against the scale of the base's
    dynamics, and the base absorbs part of the controller's own variation too, so the fit ends where its start
    sends it. Its warm estimate, started where the post-hoc screen's regression on the own variation points,
    comes out below the truth and the fit from scratch started there above it: the reported interval is widened
    by the spread between the two (`with_refit_spread`; measured: docs/DIAGNOSIS.md, "Measurements behind the code").

    `confused`: the recipe, where it must be another set's (default: that of `effects`, `inertia_recipe`). A fit
    from scratch is judged against one that differs from it by its terms alone: the same seed, minibatches and
    recipe. The recipe alone moves the held-out error (measured: docs/DIAGNOSIS.md, "Measurements behind the code").
    """
    m = ExtendedModel(copy.deepcopy(start), flat.n, list(effects), dt=flat.dt, max_delay=s.max_delay, init=dict(init),
                      coupled_damping=False)
    confused = inertia_recipe(effects) if confused is None else bool(confused)
    w_acc = 0.0 if confused else s.w_acc
    trainer = functools.partial(trainer, pieces=FRESH_PIECES)
    trainer(m, flat, s.steps_base, lr=s.lr_base, lr_ext=s.lr_ext, batch=s.batch, seed=s.seed, w_acc=w_acc,
            progress=heartbeat(s, "fit from scratch " + terms_text(m), s.steps_base),
            weighted=False)
    refit(m, flat, replace(s, w_acc=w_acc), trainer=trainer)
    if confused:
        refit_terms_frozen(m, flat, s, seed_offset=len(effects) + 1, trainer=trainer)
    return m


def other_seeds(s: Settings, n: int | None = None) -> list[Settings]:
    """The settings of n (default `Settings.n_optima`) other minibatch seeds, s + 1000 k for k = 1..n: the
    first `n_optima` are those of the optimum twins; the paired comparison (`run`'s `paired`) sets fits with
    terms beside term-free fits seed by seed on the first `n_paired`."""
    n = s.n_optima if n is None else n
    return [replace(s, seed=s.seed + 1000 * (k + 1)) for k in range(int(n))]     # n >= 1: Settings checks it


def optimum_twins(flat: Flat, s: Settings, start: torch.nn.Module, confused: bool,
                  seeds: list[Settings] | None = None, fit=None, workers: Workers | None = None) -> list[ExtendedModel]:
    """The term-free base fitted from scratch (`fresh_fit`, recipe `confused`) at `Settings.n_optima` other
    minibatch seeds (or at the settings `seeds`): the optima that a fit from scratch lands in by chance.

    A model with a term fitted from scratch is judged against the term-free base fitted with the same seed and
    recipe, but the term changes every gradient from the first step, so the two end in different optima: their
    difference carries, beside the term's gain, what another minibatch order alone would give. That noise is
    far above the twin refits' σ_r and lies on the tasks the base extrapolates worst (measured:
    docs/DIAGNOSIS.md, "Measurements behind the code"). Their differences to the
    base judged against are the `twins` of `confirm` for every comparison of a fit from scratch with it."""
    fit = fresh_fit if fit is None else fit
    return (workers or Workers()).map([lambda sk=sk: fit(flat, sk, (), {}, start, confused=confused)
                                       for sk in (seeds or other_seeds(s))])


def refit_terms_frozen(m: ExtendedModel, flat: Flat, s: Settings, seed_offset: int, trainer=train) -> None:
    """A warm refit of the base's networks with the physical terms held where they are (free again after)."""
    ext = m.ext_parameters()
    for p in ext:
        p.requires_grad_(False)
    try:
        refit(m, flat, s, seed_offset=seed_offset, trainer=trainer)
    finally:
        for p in ext:
            p.requires_grad_(True)


def around_estimates(base, fresh: ExtendedModel, flat: Flat, s: Settings, effects, trainer=train) -> ExtendedModel:
    """The reference's own refit with the terms held at the joint fit's estimates (`fresh`, fitted from
    scratch): the base as fitted, the terms frozen there, the reference's refit schedule and minibatch order
    (seed offset 1). It differs from the reference by the terms alone, so rule 1's paired comparison with the
    reference carries only the refit noise σ_r of rule 2.

    The second way an extended model can confirm its terms (step 7 of `run`), when the fit from scratch does
    not: a base fitted from scratch lands in another optimum than the reference's, and the held-out error of the
    task it extrapolates worst varies between such fits far beyond a term's gain; the same noise works the other way
    too (a fit from scratch can confirm where this model does not). Not the reference refitted once more: an
    unconverged reference's own twins gain by one more refit alone (measured: docs/DIAGNOSIS.md, "Measurements
    behind the code").
    """
    m = extend(base, flat, list(effects), init=fresh.subject_init(), max_delay=s.max_delay)
    with torch.no_grad():       # every term's parameter is the joint fit's
        for p, q in zip(m.ext_parameters(), fresh.ext_parameters(), strict=True):
            p.copy_(q)
    refit_terms_frozen(m, flat, s, seed_offset=1, trainer=trainer)
    return m


class FitCache:
    """Every fit from scratch of one run, each made once: a set of terms with a recipe (`fresh`), the term-free
    base at other seeds and the noise between optima it measures (`optima`, `free_at_seeds`), a set at the
    second look's other seeds (`at_seeds`), and the second looks already made (`paired`).

    `fit` is the fit from scratch (`fresh_fit`, or a test's stub); `errors(model)` the (user, decision) held-out
    errors; `ref_errors` the reference's, which is the term-free fit of the reference's own recipe."""

    def __init__(self, flat: Flat, s: Settings, start, errors, ref_errors: tuple, fit=None,
                 confused: tuple = INERTIA_CONFUSED, scale: str = "", workers: Workers | None = None):
        self.flat, self.s, self.start, self.errors, self.ref_errors = flat, s, start, errors, ref_errors
        self.workers = workers or Workers()
        self.fit = fresh_fit if fit is None else fit
        self.confused, self.scale = confused, scale
        self.fresh_fits: dict = {}      # (terms, recipe) -> model
        self.optimum: dict = {}         # recipe -> (user, decision errors, twins, the twins' own errors)
        self.seed_fits: dict = {}       # (terms, recipe) -> models at the second look's other seeds
        self.paired: dict = {}          # terms -> their second look against the term-free base

    def recipe(self, effects) -> bool:
        return inertia_recipe(effects, self.confused)

    def fresh(self, key: tuple, init: dict, recipe: tuple | None = None) -> ExtendedModel:
        """The terms `key` fitted from scratch (once) with the recipe of the terms `recipe` (default: `key`'s
        own): a model and the one it is judged against share the recipe and differ by their terms alone."""
        conf = self.recipe(key if recipe is None else recipe)
        return self.workers.once(self.fresh_fits, (key, conf),
                                 lambda: self.fit(self.flat, self.s, key, init, self.start, confused=conf))

    def put(self, key: tuple, model: ExtendedModel) -> None:
        """A fit from scratch of `key` with its own recipe made elsewhere (a subject form's), kept for reuse."""
        self.fresh_fits[(key, self.recipe(key))] = model

    def optima(self, key: tuple) -> tuple[np.ndarray, np.ndarray, list]:
        """What a fit from scratch of the terms `key` is judged against: the term-free base fitted from scratch
        with the same recipe (the reference itself, or a base fitted with the delay's recipe), its (user,
        decision) held-out errors, and the noise between optima: the per-sample held-out differences between
        that base and the same fitted at `Settings.n_optima` other minibatch seeds (`optimum_twins`)."""
        conf = self.recipe(key)
        return self.workers.once(self.optimum, conf, lambda: self._optima(key, conf))[:3]

    def user_noise(self, key: tuple) -> float:
        """The noise between optima on the user's (unweighted) scale: the RMS of the mean held-out differences
        of the user's errors between the term-free base judged against and its twins (`optima`)."""
        self.optima(key)
        u_0, _, _, others = self.optimum[self.recipe(key)]
        return float(np.sqrt(np.mean([np.mean(u_0 - u_k) ** 2 for u_k, _ in others[:self.s.n_optima]])))

    def _optima(self, key: tuple, conf: bool) -> tuple:
        t1 = time.time()
        # the base judged against (the reference itself, or fitted with the delay's recipe) beside its twins
        base, twins_m = self.workers.map([
            (lambda: self.fresh((), {}, recipe=key)) if conf else (lambda: None),
            lambda: optimum_twins(self.flat, self.s, self.start, conf, fit=self.fit, workers=self.workers)])
        u_0, e_0 = self.errors(base) if conf else self.ref_errors
        others = [self.errors(m) for m in twins_m]
        twins = [e_0 - e_k for _, e_k in others]
        log(self.s, "noise between optima: the term-free base fitted from scratch at other minibatch seeds"
                    f"{' (the delay recipe)' if conf else ''} differs from the one judged against by "
                    + ", ".join(f"{d.mean():.3g}" for d in twins)
                    + f" ({self.scale}, mean held-out difference; {time.time() - t1:.0f} s)")
        return u_0, e_0, twins, others

    def free_at_seeds(self, key: tuple, seeds: list[Settings]) -> list[tuple]:
        """The term-free base's (user, decision) errors at `seeds` (the optimum twins' first, fitted further
        where the second look asks for more seeds, once per recipe), in the order of `other_seeds`."""
        self.optima(key)
        conf = self.recipe(key)
        with self.workers.hold(("term-free fits", conf)):     # grown in place: a second caller finds it grown
            return self._grow(conf, seeds)

    def _grow(self, conf: bool, seeds: list[Settings]) -> list[tuple]:
        others = self.optimum[conf][3]
        if len(others) < len(seeds):
            t1, n_more = time.time(), len(seeds) - len(others)
            others += [self.errors(m) for m in optimum_twins(self.flat, self.s, self.start, conf,
                                                             seeds[len(others):], fit=self.fit, workers=self.workers)]
            log(self.s, f"the term-free base fitted from scratch at {n_more} more seeds for the paired "
                        f"comparison ({time.time() - t1:.0f} s)")
        return others[:len(seeds)]

    def at_seeds(self, key: tuple, init: dict, conf: bool) -> list:
        """The terms `key` fitted from scratch with the recipe `conf` at the second look's other seeds
        (`other_seeds(s, s.n_paired)`, in that order), once."""
        def make():
            t1 = time.time()
            fits = self.workers.map([lambda sk=sk: self.fit(self.flat, sk, key, init, self.start, confused=conf)
                                     for sk in other_seeds(self.s, self.s.n_paired)])
            log(self.s, f"{[f'{a}:{self.flat.joints[b]}' for a, b in key]} fitted from scratch at "
                        f"{self.s.n_paired} more seeds for the paired comparison ({time.time() - t1:.0f} s)")
            return fits
        return self.workers.once(self.seed_fits, (key, conf), make)
