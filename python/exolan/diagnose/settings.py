"""The diagnosis' settings (one frozen record), its significance budget and its progress lines."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

from .candidates import FITTED
from .workers import stop_or_go


def default_workers() -> int:
    """Threads for independent fits: `EXOLAN_FIT_WORKERS`, else the cores, at most 4 (torch's kernels release
    the GIL, the Python between them does not: beyond a few threads they wait on each other)."""
    env = os.environ.get("EXOLAN_FIT_WORKERS", "")
    return max(1, int(env)) if env.strip() else max(1, min(4, os.cpu_count() or 1))


@dataclass(frozen=True)
class Settings:
    steps_base: int = 3000      # base model fit (minibatch Adam steps)
    steps_refit: int = 400      # every warm-start refit (reference, candidates, nulls, extended)
    lr_base: float = 2e-2
    lr_refit: float = 3e-3
    lr_ext: float = 3e-2
    batch: int = 4096
    hidden: int = 64
    z_dim: int = 4
    n_boot: int = 1000
    n_twins: int = 3            # reference refits with other minibatch orders: the refit noise σ_r
    n_optima: int = 2           # term-free fits from scratch at other seeds: the noise between optima
    n_paired: int = 4           # the paired second look: fits at this many other seeds too, K = 1 + n_paired
    rescue: bool = True         # second looks from scratch paired over seeds (`secondlook.second_look`)
    # a friction whose warm refit failed rule 1 or 2 refitted from scratch on the learned path (`single.rescue`):
    # off by default since physics first sizes absorbed dissipation where the parametric base is adequate; where
    # it is not, the rescue cost 20 of 27 min on a 4-user world and found nothing (docs/DIAGNOSIS.md, "Time")
    rescue_frictions: bool = False
    average: bool = True        # refits end on their Polyak-averaged weights (fit.train): 4x less refit noise
    w_acc: float = 0.1          # weight of the acceleration error H⁻¹(τ − τ̂) in every fit (fit.train)
    horizon: int = 20
    seed: int = 0
    effects: tuple = FITTED     # which candidate effects to fit (all by default)
    joints: tuple | None = None  # restrict to these joint names (None: all)
    max_delay: float = 0.1
    weighted: bool = True       # refits weight each trial and joint by the base's inverse misfit (fit.misfit_weights)
    weights_explained: bool = True  # the weights' misfit: the base's less what every candidate column explains (`weights`)
    decide_weighted: bool = True  # decisions on the held-out error with the fits' weights (reported gains unweighted)
    pelvis_tilt: bool = False   # base term: the pelvis tilts with the other hip (base.py docstring)
    pelvis_surge: bool = True   # base term: the pelvis's fore-aft acceleration from both insoles (base.PelvisSurge)
    lim_cop: bool = True        # base: the insole mapping's lever arms see the centre of pressure, B(q, x_cop, z)
    adapt_model: bool = True    # a given model (`--model`): fit it at its pooled context first (base.PooledContext)
    inject_gain: bool = False   # the gain's detection limit also by injection and recovery (refits; only when asked)
    inject_delay: bool = False  # the same for the actuation delay's (off: a delay already in the data confounds it)
    physics_first: bool = True  # size every candidate against a parametric rigid-body base first (`physics`)
    alpha: float = 0.05         # THE family-wise level of every accept decision, both paths (`Budget`)
    cutoff_hz: float = 25.0     # zero-phase low-pass of q and τ for the parametric identification (`ident`)
    verbose: bool = True
    workers: int = field(default_factory=default_workers)  # fits side by side (`workers`; same bits)

    def __post_init__(self):
        # the noise between optima needs a twin, and a paired comparison a second seed to measure its spread
        if int(self.workers) < 1:
            raise ValueError(f"Settings.workers must be at least 1, got {self.workers}")
        for name in ("n_optima", "n_paired"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"Settings.{name} must be at least 1, got {getattr(self, name)}")

    def joint_ids(self, flat) -> list[int]:
        """The indices of the joints these settings diagnose (`joints`; all where None)."""
        return [j for j, nm in enumerate(flat.joints) if self.joints is None or nm in self.joints]


@dataclass(frozen=True)
class Budget:
    """One significance budget for the learned path's accept decisions (docs/DIAGNOSIS.md, "One budget").

    `alpha` is the family-wise level over the `m` candidates the data can test. A candidate's single-term test
    (rules 1 and 2) runs at Bonferroni's α/m; forward selection's test of a further term, after r accepted ones,
    at Holm's α/(m − r). A decision that may pass by one of several looks at the data (a warm refit, then fits
    from scratch; two fits from scratch judged two ways) splits its level evenly among them (Bonferroni within
    the decision), so a second look is part of the same test, not a new one. Tests a term must pass *as well*
    (nulls, rule 5, the extended model's confirmation) can only remove terms and spend nothing; the extended
    model's confirmation runs at α, split over its looks. Levels are two-sided, as the intervals are."""
    alpha: float
    m: int

    def single(self, looks: int = 1) -> float:
        return self.alpha / max(self.m, 1) / looks

    def further(self, accepted: int, looks: int = 1) -> float:
        return self.alpha / max(self.m - accepted, 1) / looks

    def confirmation(self, looks: int) -> float:
        return self.alpha / looks


_LAST_LINE = [time.time()]     # when the last progress line was printed (`log`, `heartbeat`)
_STEP = [""]                    # the step the run is on, named in every heartbeat (`step`)
HEARTBEAT_S = 25.0              # a line at least this often while a fit runs (the user sees it is alive)


def log(s: Settings, msg: str):
    if s.verbose:
        _LAST_LINE[0] = time.time()
        print(f"[diagnose {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def step(s: Settings, name: str) -> None:
    """Enter a step of the procedure: a line now, and its name in every heartbeat until the next."""
    _STEP[0] = name
    log(s, f"== {name}")


def heartbeat(s: Settings, what: str, steps: int):
    """A `fit.train` progress callback: a line saying which step of the procedure, which fit (its terms: the
    candidate) and which optimiser step, when none was printed for a while."""
    def tick(i: int, loss: float) -> None:
        stop_or_go()        # a fit started ahead whose result is no longer wanted (`workers.Ahead`)
        if s.verbose and time.time() - _LAST_LINE[0] >= HEARTBEAT_S:
            where = f"[{_STEP[0]}] " if _STEP[0] else ""
            log(s, f"... {where}{what}: step {i + 1}/{steps}, loss {loss:.4g}")
    return tick
