"""A term that moves the coordinates the whole base acts in: a backlash of width w puts the limb at q + (w/2) s
(s the side of the gap, `exo_signals.gap_side`), so every base column changes with w. A column beside a fixed
base cannot size it: the base's coefficients move to absorb it (a knee backlash of 0.04 rad came out 0.016 that
way, docs/DIAGNOSIS.md, "Backlash"). So it is sized by variable projection with a design that changes with the
width: the base refitted at every w.

The design X(u), u = w/2, is its Taylor polynomial of second order in u (central differences at a step h below
every width searched): every base column is smooth in the angle and linear in q̇ and q̈, so the remainder is of
order u² relative to the shift itself (1 % at u = 0.1 rad). Interpolated through the largest width instead, it
was 13 % off at the widths a gear or a strap's play has. With the Gram blocks of [X0, X1, X2] on the weighted
training rows made once per weighting, the profiled SSE at any u is a solve of the size of the base (`Profile`),
not a factorisation of the rows."""
from __future__ import annotations

import numpy as np
from scipy import linalg

CHUNK = 16384           # rows per block of the Gram products (no weighted copy of the design is kept)


def backlash_grid(sig, j, ctx):
    """Widths searched: up to a tenth of the joint's range of motion (a play, not a loose joint), down to a
    hundredth of that, log-spaced (`ident.JointProblem` refines between grid neighbours)."""
    q = sig.q[sig.train, j]
    q = q[np.isfinite(q)]
    hi = 0.1 * float(np.subtract(*np.quantile(q, [0.99, 0.01]))) if len(q) else 0.0
    return list(np.geomspace(hi / 100, hi, 14)) if hi > 0 else [0.0, 1.0]


def backlash_col(sig, j, nu, ctx):
    """Where the base cannot be refitted in moved coordinates (the learned base's residual, a constant base): the
    backlash linearised at the parametric base's final fit, ν ∂τ̂/∂w (`ctx['shift_D']`, filtered already)."""
    return nu * ctx["shift_D"][j]


class ShiftBasis:
    """X(u) = X0 + u X1 + u² X2 for joint j's coordinate shift u s (filtered as the base: `Signals.lp`)."""

    def __init__(self, sig, j: int, X0: np.ndarray, h: float, columns):
        """`columns(q, qd, qdd, sig)` -> (raw base columns, names): `ident.base_columns`; h the differences' step."""
        def at(u):
            q, qd, qdd = sig.q.copy(), sig.qd.copy(), sig.qdd.copy()
            q[:, j] += u * sig.side[:, j]
            qd[:, j] += u * sig.side_d[:, j]
            qdd[:, j] += u * sig.side_dd[:, j]
            return sig.lp(columns(q, qd, qdd, sig)[0])
        Xp, Xm = at(h), at(-h)
        self.X0 = X0
        self.X1 = np.nan_to_num((Xp - Xm) / (2 * h))
        self.X2 = np.nan_to_num((Xp + Xm - 2 * X0) / (2 * h * h))
        self._gram: np.ndarray | None = None

    def at(self, u: float) -> np.ndarray:
        return self.X0 + u * self.X1 + (u * u) * self.X2

    def derivative(self, u: float, theta: np.ndarray) -> np.ndarray:
        """∂(X(u) θ)/∂u: the prediction's change with the shift at fixed base coefficients (its linearisation)."""
        return (self.X1 + (2 * u) * self.X2) @ theta

    def _chunks(self, train: np.ndarray):
        """(rows of a block, its training rows) over the design, CHUNK rows at a time: no weighted copy is kept."""
        for a in range(0, len(train), CHUNK):
            m = train[a:a + CHUNK]
            if m.any():
                yield slice(a, a + CHUNK), m

    def _blocks(self, train: np.ndarray, w: np.ndarray, V: np.ndarray) -> np.ndarray:
        """(3, p, k) Xaᵀ W V over the training rows, a = 0, 1, 2."""
        XV = np.zeros((3, self.X0.shape[1], V.shape[1]))
        for sl, m in self._chunks(train):
            Vw = V[sl][m] * w[sl][m][:, None]
            for k, X in enumerate((self.X0, self.X1, self.X2)):
                XV[k] += X[sl][m].T @ Vw
        return XV

    def gram(self, train: np.ndarray, w: np.ndarray) -> np.ndarray:
        """(3, 3, p, p) Xaᵀ W Xb on the training rows; made once per weighting (`forget` when it changes)."""
        if self._gram is None:
            p = self.X0.shape[1]
            G = np.zeros((3, 3, p, p))
            for sl, m in self._chunks(train):
                ww = np.sqrt(w[sl][m])[:, None]
                Xs = [X[sl][m] * ww for X in (self.X0, self.X1, self.X2)]
                for i in range(3):
                    for k in range(i, 3):
                        G[i, k] += Xs[i].T @ Xs[k]
            for i in range(3):
                for k in range(i):
                    G[i, k] = G[k, i].T
            self._gram = G
        return self._gram

    def forget(self) -> None:
        self._gram = None

    def profile(self, train: np.ndarray, w: np.ndarray, z: np.ndarray, C: np.ndarray) -> "Profile":
        """The weighted training SSE of z on [X(u), C] as a function of u (`Profile`); z (N,), C (N, k) on all rows."""
        V = np.concatenate([z[:, None], C], 1)
        XV = self._blocks(train, w, V)
        wt = w[train]
        Vt = V[train]
        VV = Vt.T @ (Vt * wt[:, None])
        return Profile(self.gram(train, w), XV, VV)


class Profile:
    """SSE(u) = zᵀWz − bᵀ A⁺ b of the normal equations of [X(u), C], A and b polynomials in u from Gram blocks.
    Solved after scaling every column to unit diagonal, with a pseudo-inverse that drops directions below 1e-12 of
    the largest (columns with no rows, or dependent ones, as the base's rank-revealing QR drops them)."""

    def __init__(self, G: np.ndarray, XV: np.ndarray, VV: np.ndarray):
        self.G, self.XV, self.VV = G, XV, VV

    def __call__(self, u: float) -> float:
        c = np.array([1.0, u, u * u])
        Axx = np.einsum("a,b,abpq->pq", c, c, self.G)
        XV = np.einsum("a,apk->pk", c, self.XV)         # [Xᵀ W z, Xᵀ W C]
        A = np.block([[Axx, XV[:, 1:]], [XV[:, 1:].T, self.VV[1:, 1:]]])
        b = np.concatenate([XV[:, 0], self.VV[1:, 0]])
        d = np.sqrt(np.clip(np.diag(A), 0.0, None))
        keep = d > 0
        s = 1.0 / d[keep]
        ev, V = linalg.eigh(A[np.ix_(keep, keep)] * s[:, None] * s[None, :])
        big = ev > ev[-1] * 1e-12
        proj = V[:, big].T @ (b[keep] * s)
        return float(self.VV[0, 0] - np.sum(proj * proj / ev[big]))
