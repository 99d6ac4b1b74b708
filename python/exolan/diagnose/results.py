"""Result objects: a candidate's verdict and evidence (`Verdict`) in place of a string-keyed dict.

Every field a candidate can carry is declared here, once; a field never set is absent from `to_json()` (the
report's schema is unchanged). The mapping interface (`v["status"]`, `v.get(...)`, `"status" in v`, `update`)
remains for the report writer and the physics-first path, which read entries by name; an unknown name raises.
Fields the report does not show (the working state of the decision) are marked `public=False`.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

from ..runio import jsonable

_UNSET = object()


def _f(public: bool = True):
    return field(default=_UNSET, metadata=dict(public=public))


@dataclass(eq=False)
class Verdict:
    # what is tested
    effect: object = _f()
    joint: object = _f()
    subjects: object = _f()
    unit: object = _f()
    kind: object = _f()
    # the verdict
    status: object = _f()
    reason: object = _f()
    note: object = _f()
    # the estimate
    estimate: object = _f()
    ci: object = _f()
    vs: object = _f()
    identifiable: object = _f()
    estimate_by_subject: object = _f()
    estimate_warm_start: object = _f()
    ci_warm_start: object = _f()
    warm_start: object = _f()
    estimate_single_term: object = _f()
    ci_single_term: object = _f()
    ci_identification: object = _f()
    ci_method: object = _f()
    ci_learned: object = _f()      # the learned path's own interval where the parametric base's disagrees
    size_limit: object = _f()      # a rejected linear term: the size from which these data would show it
    # the evidence
    screen: object = _f()
    heldout_gain: object = _f()
    heldout_gain_ci: object = _f()
    relative_gain: object = _f()
    relative_gain_ci: object = _f()
    decision_gain: object = _f()
    subject_gains: object = _f()
    task_invariance: object = _f()
    null_gain: object = _f()
    nulls: object = _f()
    rivals: object = _f()
    conditional_gain: object = _f()
    subject_form: object = _f()
    subject_form_not_taken: object = _f()
    from_scratch: object = _f()
    warm_fit: object = _f()
    parametric: object = _f()
    cross_check: object = _f()
    # the decision's working state (not in the report)
    block: object = _f(public=False)
    fit_seconds: object = _f(public=False)
    passes_gain: object = _f(public=False)
    passes_floor: object = _f(public=False)
    passes_invariance: object = _f(public=False)
    passes_null: object = _f(public=False)
    passes: object = _f(public=False)
    level: object = _f(public=False)        # the level its single-term test ran at (`settings.Budget`)
    pci: object = _f(public=False)          # θ's estimate and HAC interval of the fit that stands for it
    rank: object = _f(public=False)         # forward selection's order: its (conditional) decision gain
    rescued: object = _f(public=False)      # fitted from scratch by the second look (`selection.rescue`)
    form: object = _f(public=False)         # the subject form taken (`subjects.take_form`)

    # -- the mapping interface -----------------------------------------------------------------------------
    def _check(self, key: str) -> None:
        if key not in _NAMES:
            raise KeyError(f"a Verdict has no field {key!r}")

    def __getitem__(self, key: str):
        self._check(key)
        v = getattr(self, key)
        if v is _UNSET:
            raise KeyError(key)
        return v

    def __setitem__(self, key: str, value) -> None:
        self._check(key)
        setattr(self, key, value)

    def __contains__(self, key: str) -> bool:
        return key in _NAMES and getattr(self, key) is not _UNSET

    def get(self, key: str, default=None):
        return self[key] if key in self else default

    def setdefault(self, key: str, default=None):
        if key not in self:
            self[key] = default
        return self[key]

    def update(self, **kw) -> None:
        for k, v in kw.items():
            self[k] = v

    def pop(self, key: str, default=None):
        v = self.get(key, default)
        if key in self:
            setattr(self, key, _UNSET)
        return v

    # -- what the report shows -----------------------------------------------------------------------------
    def to_json(self) -> dict:
        return {f.name: jsonable(getattr(self, f.name)) for f in fields(self)
                if f.metadata["public"] and getattr(self, f.name) is not _UNSET}

    def summary(self) -> str:
        """One line: effect, joint, verdict, estimate with its interval, and why."""
        est = self.get("estimate")
        ci = self.get("ci")
        size = "" if est is None else f" {est:.4g}" + ("" if not ci else f" [{ci[0]:.3g}, {ci[1]:.3g}]")
        return f"{self.effect} {self.joint}: {self.get('status', 'undecided')}{size}" + (
            f" ({self.reason})" if self.get("reason") else "")

    def add_note(self, text: str) -> None:
        """Append `text` to the note ("; " between notes)."""
        self.note = f"{self.note}; {text}" if self.get("note") else text


_NAMES = frozenset(f.name for f in fields(Verdict))


def public(e) -> dict:
    """What the report shows of a verdict (or of a plain dict from elsewhere)."""
    return e.to_json() if isinstance(e, Verdict) else {k: jsonable(v) for k, v in e.items()}


def strip(m: dict | None) -> dict:
    return {} if m is None else jsonable(dict(m))
