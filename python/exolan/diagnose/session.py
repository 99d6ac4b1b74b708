"""One run's learned path: what every step reads (the data, the reference and its noise, the fits' cache, the
significance budget) in one object, and the fitting and judging functions it calls (`Tools`), which a test
replaces by passing stubs (`run(..., tools=Tools(...))`) instead of patching module names."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from . import compensate, inference, nulls, physics_path, refits, rules, secondlook, subjects
from .candidates import LIBRARY
from .flat import Flat
from .settings import Budget, Settings, log
from .workers import Ahead, Workers


@dataclass
class Tools:
    """The fits and judgements the learned path makes, and the gate that routes each joint to a path; defaults are
    the real ones."""
    fresh_fit: Callable = refits.fresh_fit              # a set of terms fitted from scratch
    around_estimates: Callable = refits.around_estimates  # the reference refitted with the terms frozen
    gain: Callable = rules.paired_gain                  # the paired held-out gain and its bootstrap
    above_noise: Callable = rules.above_noise           # rule 2
    user_improves: Callable = rules.user_improves       # rule 1's second condition
    user_grows_beyond_noise: Callable = rules.user_grows_beyond_noise  # the same for fits from scratch
    invariance: Callable = rules.invariance_rule        # rule 5
    confirm: Callable = rules.confirm                   # a fit from scratch or the extended model vs. its base
    paired_confirm: Callable = secondlook.paired_confirm  # the second look's comparison
    term_share: Callable = rules.term_share             # a term's own share of its fit vs. the refit floor
    param_ci: Callable = inference.param_ci             # θ and its HAC interval
    subject_form: Callable = subjects.subject_form      # a subject form proposed from the training rows
    inertia_confused: tuple = refits.INERTIA_CONFUSED   # terms fitted from scratch without the acceleration term
    adequacy: Callable = physics_path.adequacy          # the gate per joint: which path decides each joint's terms
    learned_check: Callable = physics_path.checked      # rule 6 on physics first's terms, until nothing changes
    fit_without: Callable = compensate.fitted_without   # physics first's extended model: fitted without its terms
    nulls_on_top: Callable = nulls.on_top               # rule 3 for an exo-driven term tested on top of others


@dataclass
class Session:
    flat: Flat
    s: Settings
    tools: Tools
    held: torch.Tensor
    w_held: np.ndarray | None
    scale: str                      # "misfit-weighted" or "unweighted": the decisions' held-out errors
    base: torch.nn.Module
    base_start: torch.nn.Module | None   # the base before its fit (None: a model judged as given, warm fits only)
    ref: torch.nn.Module
    e_ref_user: np.ndarray
    e_ref: np.ndarray
    sigma_r: float                  # the refit noise (rule 2)
    twin_d: list                    # the twin refits' per-sample differences to the reference
    budget: Budget
    joint_ids: list
    groups: np.ndarray = None
    group_kind: str = "none"
    held_subject: np.ndarray = None
    subjects: list = field(default_factory=list)
    cache: refits.FitCache = None
    fitted: dict = field(default_factory=dict)      # (effect, j) -> (model that stands for it, decision errors)
    warm_fits: dict = field(default_factory=dict)   # sorted terms -> the reference refitted warm with them
    workers: Workers = field(default_factory=Workers)  # independent fits side by side (one per candidate, per seed)
    first_twin: Ahead | None = None  # twin 0 of the refit noise, started beside the reference's refit (`procedure`)
    optima_ahead: Ahead | None = None  # step 7's from-scratch comparison base, started in selection (`selection`)

    @property
    def n_candidates(self) -> int:
        return self.budget.m

    @property
    def from_scratch(self) -> bool:
        """Whether fits from scratch are possible (a base trained or adapted here)."""
        return self.base_start is not None

    def log(self, msg: str) -> None:
        log(self.s, msg)

    def errors(self, m, f: Flat | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(user, decision) held-out errors of model m (`refits.held_errors`)."""
        return refits.held_errors(m, self.flat if f is None else f, self.held, self.w_held)

    def gain(self, e_before, e_after, alpha: float = 0.05) -> dict:
        return self.tools.gain(e_before, e_after, self.s, alpha=alpha)

    def above_noise(self, g: dict, alpha: float = 0.05) -> bool:
        return self.tools.above_noise(g, self.sigma_r, alpha=alpha)

    def passes_at(self, g: dict, level: float) -> bool:
        """Rule 1's bound at `level`: the bootstrap's lower quantile of the paired gain above 0."""
        draws = g.get("draws")
        if draws is None:
            return bool(g["ci"][0] > 0)
        return bool(np.quantile(draws, level / 2) > 0)

    def invariance(self, d, fitted_model, effect: str, j: int, twins: list | None = None) -> dict:
        """Rule 5 for the held-out gain series d of (effect, joint j) as `fitted_model` carries it; its noise
        beside the sampling error: the twin refits' (a warm refit against the reference), or `twins`."""
        out = self.tools.invariance(
            d, self.groups, self.group_kind, self.s, neutral=LIBRARY[effect].theta_neutral,
            by_group=lambda masks: inference.param_by_group(fitted_model, self.flat, effect, j, self.held, masks),
            twins=self.twin_d if twins is None else twins, param_path=LIBRARY[effect].needs_exo,
            family=self.n_candidates, positive=LIBRARY[effect].positive)
        out["scale"] = self.scale        # the gains per group are the decision's
        return out

    def own_share(self, m, terms: tuple, e_with: np.ndarray) -> dict:
        """`rules.term_share` of the terms in the fit `m` (`e_with`: its held-out decision errors)."""
        return self.tools.term_share(self.errors(m.without(terms))[1], e_with, self.sigma_r, self.s)

    def confirm(self, e_before, e_after, alpha: float, twins: list | None = None, look: str = "") -> dict:
        return self.tools.confirm(e_before, e_after, self.groups, self.group_kind, self.s, alpha, twins=twins,
                                  look=look)

    def subject_gains(self, d: np.ndarray) -> dict:
        return rules.subject_gains(d, self.held_subject, self.s)

    def second_look(self, key: tuple, init: dict, first, first_errors: tuple, level: float, given: tuple = (),
                    given_errors: tuple | None = None) -> dict:
        return secondlook.second_look(self, key, init, first, first_errors, level, given, given_errors)
