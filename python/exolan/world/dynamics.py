"""Rigid-body dynamics of one leg: a planar 2-link chain hanging from the hip.

Coordinates (all in the hip frame, x forward, y up): joint angles q = (q_hip, q_knee), flexion
positive for both. The thigh's absolute angle from the downward vertical is th1 = q_hip (forward
positive), the shank's is th2 = q_hip - q_knee. u(th) = (sin th, -cos th) points along a link,
u'(th) = (cos th, sin th) is its forward normal.

The equations are derived in absolute angles (where the mass matrix has the textbook form) and
mapped to joint angles by th = T q with the constant T = [[1, 0], [1, -1]]:
H_q = T^T H_th T, c_q = T^T c_th, g_q = T^T g_th, and joint torques are the generalised forces
conjugate to q (virtual work tau . dq).

The hip moves with the pelvis; in the hip frame its acceleration a_p appears as an effective
gravity g_eff = (0, -9.81) - a_p acting on every segment (d'Alembert). All functions are
vectorised over a leading time axis.
"""
from __future__ import annotations

import numpy as np

from .anthropometry import G, LegParams

GRAVITY = np.array([0.0, -G])


def _u(th):
    return np.stack([np.sin(th), -np.cos(th)], axis=-1)


def _un(th):
    return np.stack([np.cos(th), np.sin(th)], axis=-1)


def mass_matrix(p: LegParams, q: np.ndarray) -> np.ndarray:
    """H(q), shape (..., 2, 2)."""
    q = np.asarray(q, float)
    th1, th2 = q[..., 0], q[..., 0] - q[..., 1]
    a = p.I1 + p.m1 * p.c1 ** 2 + p.m2 * p.l1 ** 2
    b = p.m2 * p.l1 * p.r2 * np.cos(th1 - th2 - p.beta2)
    c = p.I2 + p.m2 * p.r2 ** 2
    H = np.empty(q.shape[:-1] + (2, 2))
    H[..., 0, 0] = a + 2 * b + c
    H[..., 0, 1] = H[..., 1, 0] = -(b + c)
    H[..., 1, 1] = c
    return H


def coriolis(p: LegParams, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
    """c(q, qd): Coriolis and centrifugal torques, shape (..., 2)."""
    th1, th2 = q[..., 0], q[..., 0] - q[..., 1]
    th1d, th2d = qd[..., 0], qd[..., 0] - qd[..., 1]
    k = p.m2 * p.l1 * p.r2 * np.sin(th1 - th2 - p.beta2)
    c1, c2 = k * th2d ** 2, -k * th1d ** 2
    return np.stack([c1 + c2, -c2], axis=-1)


def gravity(p: LegParams, q: np.ndarray, g_eff: np.ndarray | None = None) -> np.ndarray:
    """g(q) = dV/dq under the (effective) gravity vector g_eff (..., 2); default plain gravity."""
    th1, th2 = q[..., 0], q[..., 0] - q[..., 1]
    ge = GRAVITY if g_eff is None else np.asarray(g_eff, float)
    g1 = -(p.m1 * p.c1 + p.m2 * p.l1) * np.sum(ge * _un(th1), axis=-1)
    g2 = -p.m2 * p.r2 * np.sum(ge * _un(th2 + p.beta2), axis=-1)
    return np.stack([g1 + g2, -g2], axis=-1)


def points(p: LegParams, q: np.ndarray) -> dict:
    """Knee and ankle positions relative to the hip, (..., 2) each."""
    th1, th2 = q[..., 0], q[..., 0] - q[..., 1]
    knee = p.l1 * _u(th1)
    ankle = knee + p.l2 * _u(th2)
    return {"knee": knee, "ankle": ankle}


def cop_point(p: LegParams, q: np.ndarray, cop_x: np.ndarray) -> np.ndarray:
    """World position (hip frame) of the CoP for a foot flat on the ground: the sole lies
    ``ankle_height`` below the ankle, the heel ``heel_to_ankle`` behind it, and the CoP ``cop_x``
    forward of the heel."""
    ankle = points(p, q)["ankle"]
    return np.stack([ankle[..., 0] - p.heel_to_ankle + cop_x, ankle[..., 1] - p.ankle_height], axis=-1)


def contact_torque(p: LegParams, q: np.ndarray, point: np.ndarray, f: np.ndarray) -> np.ndarray:
    """tau_c = J^T f for a force f (..., 2) acting at ``point`` (hip frame), the point taken as
    fixed on the shank-foot body at this instant. J^T f reduces to moments: about the hip for the
    hip (the whole leg rotates with q_hip) and minus the moment about the knee for the knee
    (q_knee rotates the shank backward)."""
    knee = points(p, q)["knee"]
    r_h = point
    r_k = point - knee
    m_h = r_h[..., 0] * f[..., 1] - r_h[..., 1] * f[..., 0]
    m_k = r_k[..., 0] * f[..., 1] - r_k[..., 1] * f[..., 0]
    return np.stack([m_h, -m_k], axis=-1)


def contact_jacobian(p: LegParams, q: np.ndarray, point: np.ndarray) -> np.ndarray:
    """J (..., 2, 2): d(point)/dq for the point fixed on the shank-foot body (for tests)."""
    knee = points(p, q)["knee"]
    rh, rk = point, point - knee
    J = np.empty(np.shape(point)[:-1] + (2, 2))
    # velocity of a point on body 2: th1d z x (knee) + th2d z x (p - knee); th2d = q1d - q2d
    J[..., 0, 0] = -rh[..., 1]
    J[..., 1, 0] = rh[..., 0]
    J[..., 0, 1] = rk[..., 1]
    J[..., 1, 1] = -rk[..., 0]
    return J


def inverse_dynamics(p: LegParams, q, qd, qdd, g_eff=None, f=None, point=None) -> np.ndarray:
    """Total actuated torque tau = H qdd + c + g - J^T f (what the joints must supply)."""
    q, qd, qdd = (np.asarray(a, float) for a in (q, qd, qdd))
    tau = np.einsum("...ij,...j->...i", mass_matrix(p, q), qdd) + coriolis(p, q, qd) + gravity(p, q, g_eff)
    if f is not None:
        tau = tau - contact_torque(p, q, point, f)
    return tau


def forward_dynamics(p: LegParams, q, qd, tau, g_eff=None) -> np.ndarray:
    """qdd = H^-1 (tau - c - g) (no contact)."""
    rhs = tau - coriolis(p, q, qd) - gravity(p, q, g_eff)
    return np.linalg.solve(mass_matrix(p, q), rhs[..., None])[..., 0]


def energy(p: LegParams, q, qd) -> np.ndarray:
    """Kinetic + potential energy under plain gravity, hip fixed (for the conservation check)."""
    T = 0.5 * np.einsum("...i,...ij,...j->...", qd, mass_matrix(p, q), qd)
    th1, th2 = q[..., 0], q[..., 0] - q[..., 1]
    y1 = -p.c1 * np.cos(th1)
    y2 = -p.l1 * np.cos(th1) - p.r2 * np.cos(th2 + p.beta2)
    return T + G * (p.m1 * y1 + p.m2 * y2)
