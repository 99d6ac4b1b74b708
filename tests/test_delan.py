"""The analytic forward-mode DeLaN terms against an autograd oracle (torch.func), float64.

The oracle builds the Lagrangian ℒ(q, q̇) = ½ q̇ᵀ H(q) q̇ − V(q) from the raw layer weights, independently of
exolan.delan's Jacobian code, and gets τ from the Euler-Lagrange equation
τ = ∂²ℒ/∂q̇² q̈ + ∂²ℒ/∂q̇∂q q̇ − ∂ℒ/∂q with torch.func.
"""

import pytest
import torch
from torch.func import grad, hessian, jacfwd, jacrev, vmap

from exolan import delan
from exolan.models import build_model



@pytest.fixture(autouse=True)
def float64_default():
    """float64 inside this module's tests only (a module-level switch would leak into other test files)."""
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)


def _oracle_net(layers, x):
    h = x
    for lin in list(layers)[:-1]:
        h = torch.tanh(h @ lin.weight.T + lin.bias)
    last = list(layers)[-1]
    return h @ last.weight.T + last.bias


def _phi(q, joint_types):
    rev = [j for j, t in enumerate(joint_types) if t == "revolute"]
    pri = [j for j, t in enumerate(joint_types) if t == "prismatic"]
    parts = []
    if rev:
        parts += [torch.cos(q[rev]), torch.sin(q[rev])]
    if pri:
        parts.append(q[pri])
    return torch.cat(parts)


def _oracle_H(lag, joint_types, q, z):
    n = len(joint_types)
    u = _oracle_net(lag.L, torch.cat([_phi(q, joint_types), z]))
    Lm = torch.zeros(n, n, dtype=q.dtype)
    Lm = Lm + torch.diag(torch.nn.functional.softplus(u[:n]) + lag.softplus_offset)
    k = n
    for i in range(1, n):
        for j in range(i):
            Lm = Lm + u[k] * torch.nn.functional.one_hot(torch.tensor(i), n).to(q.dtype)[:, None] \
                * torch.nn.functional.one_hot(torch.tensor(j), n).to(q.dtype)[None, :]
            k += 1
    return Lm @ Lm.T


def _oracle_V(lag, joint_types, q, z):
    return lag.v_scale * _oracle_net(lag.V, torch.cat([_phi(q, joint_types), z]))[0]


def _oracle(lag, joint_types, q, qd, qdd, z):
    def lagrangian(q_, qd_):
        return 0.5 * qd_ @ _oracle_H(lag, joint_types, q_, z) @ qd_ - _oracle_V(lag, joint_types, q_, z)
    M = hessian(lagrangian, argnums=1)(q, qd)                                   # ∂²ℒ/∂q̇²
    Mqd_q = jacrev(jacrev(lagrangian, argnums=1), argnums=0)(q, qd)            # ∂²ℒ/∂q̇∂q
    dLdq = grad(lagrangian, argnums=0)(q, qd)
    g = grad(lambda q_: _oracle_V(lag, joint_types, q_, z))(q)
    c = Mqd_q @ qd - dLdq - g                                                   # −∂ℒ/∂q = −∂T/∂q + g
    tau = M @ qdd + c + g
    return M, c, g, tau


CASES = [
    (("revolute", "revolute"), 0),
    (("revolute", "revolute"), 3),
    (("prismatic",), 2),
    (("prismatic", "revolute", "prismatic"), 4),
    (("revolute", "prismatic", "revolute", "revolute"), 0),
]


@pytest.mark.parametrize("joint_types,dz", CASES)
def test_terms_match_autograd_oracle(joint_types, dz):
    torch.manual_seed(len(joint_types) * 10 + dz)
    n = len(joint_types)
    lag = delan.Lagrangian(joint_types, z_dim=dz, hidden=16, softplus_offset=0.05, v_scale=3.0).double()
    B = 7
    q, qd, qdd = torch.randn(B, n) * 1.5, torch.randn(B, n) * 2.0, torch.randn(B, n) * 5.0
    z = torch.randn(B, dz)
    H, c, g = lag.terms(q, qd, z)
    tau = delan.inverse_dynamics(lag, q, qd, qdd, z)
    qdd_fd = delan.forward_dynamics(lag, q, qd, tau, z)
    M_o, c_o, g_o, tau_o = vmap(lambda a, b, d, e: _oracle(lag, joint_types, a, b, d, e))(q, qd, qdd, z)
    torch.testing.assert_close(H, M_o, rtol=0, atol=1e-10)
    torch.testing.assert_close(c, c_o, rtol=0, atol=1e-10)
    torch.testing.assert_close(g, g_o, rtol=0, atol=1e-10)
    torch.testing.assert_close(lag.gravity(q, z), g_o, rtol=0, atol=1e-10)   # g alone, without the inertia network
    torch.testing.assert_close(tau, tau_o, rtol=0, atol=1e-10)
    # forward dynamics inverts inverse dynamics
    torch.testing.assert_close(qdd_fd, qdd, rtol=0, atol=1e-10)
    # the oracle's forward dynamics: q̈ = H⁻¹ (τ − c − g)
    qdd_o = torch.linalg.solve(M_o, (tau_o - c_o - g_o).unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(qdd_fd, qdd_o, rtol=0, atol=1e-10)


def test_jacobians_match_jacfwd():
    """The carried layer Jacobian equals torch.func.jacfwd of the plain network."""
    torch.manual_seed(1)
    jt = ("revolute", "prismatic")
    lag = delan.Lagrangian(jt, z_dim=2, hidden=8).double()
    q, z = torch.randn(5, 2), torch.randn(5, 2)
    x, dphi = lag._inputs(q, z)
    _, dv = delan.mlp_forward_jac(lag.V, x, dphi)
    ref = vmap(jacfwd(lambda q_, z_: _oracle_net(lag.V, torch.cat([_phi(q_, jt), z_]))))(q, z)
    torch.testing.assert_close(dv, ref, rtol=0, atol=1e-12)


def test_inertia_is_positive_definite_and_leading_dims_free():
    torch.manual_seed(2)
    lag = delan.Lagrangian(("revolute", "revolute"), z_dim=1, hidden=8, softplus_offset=0.1).double()
    q, qd, z = torch.randn(3, 4, 2), torch.randn(3, 4, 2), torch.randn(3, 4, 1)
    H, c, g = lag.terms(q, qd, z)
    assert H.shape == (3, 4, 2, 2) and c.shape == (3, 4, 2) and g.shape == (3, 4, 2)
    assert torch.all(torch.linalg.eigvalsh(H) >= 0.1 ** 2 - 1e-12)
    flat = lag.terms(q.reshape(-1, 2), qd.reshape(-1, 2), z.reshape(-1, 1))
    torch.testing.assert_close(H.reshape(-1, 2, 2), flat.H, rtol=0, atol=0)


def test_energy_balance_power():
    """dE/dt = q̇ᵀ τ for the conservative model: checks c's sign convention with an independent identity
    (Ḣ − 2C skew-symmetry in disguise), via a finite difference of the energy along the exact flow."""
    torch.manual_seed(3)
    lag = delan.Lagrangian(("revolute", "revolute"), z_dim=0, hidden=16, softplus_offset=0.2).double()
    q, qd, tau = torch.randn(1, 2), torch.randn(1, 2), torch.randn(1, 2)
    qdd = delan.forward_dynamics(lag, q, qd, tau)
    h = 1e-6
    def E(a, b):
        T, V = delan.energy(lag, a, b)
        return T + V
    dE = (E(q + h * qd + 0.5 * h * h * qdd, qd + h * qdd) - E(q - h * qd + 0.5 * h * h * qdd, qd - h * qdd)) / (2 * h)
    torch.testing.assert_close(dE, (qd * tau).sum(-1), rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("method", ["exolan", "delan-lstm", "delan"])
@pytest.mark.parametrize("lim", [True, False])
def test_model_inverse_forward_consistent_with_lim(method, lim):
    torch.manual_seed(4)
    m = build_model(method, lim=lim, context_channels=["a", "b", "c"], z_dim=4, hidden=8, lim_hidden=4,
                    lim_scale=0.05).double()
    q, qd, qdd = torch.randn(6, 2), torch.randn(6, 2), torch.randn(6, 2)
    z = m.context(torch.randn(2, 3, 3)).reshape(6, -1)
    f_v = torch.rand(6) * 800
    tau = m.inverse(q, qd, qdd, z, f_v)
    H, c, g = m.terms(q, qd, z)
    Bfv = m.contact(q, z, f_v)
    torch.testing.assert_close(tau, (H @ qdd[..., None])[..., 0] + c + g - Bfv, rtol=0, atol=1e-12)
    torch.testing.assert_close(m.forward_dynamics(q, qd, tau, z, f_v), qdd, rtol=0, atol=1e-9)
    assert (Bfv.abs().sum() > 0) == lim


@pytest.mark.parametrize("n", [1, 2, 3])
def test_solve_inertia_matches_a_dense_solve_with_its_gradient(n):
    """The closed forms (1 and 2 joints) and the Cholesky path agree with `torch.linalg.solve`, values and
    gradients, over a batch of SPD inertias."""
    g = torch.Generator().manual_seed(n)
    A = torch.randn(64, n, n, generator=g)
    H = (A @ A.transpose(1, 2) + 0.1 * torch.eye(n)).requires_grad_()
    r = torch.randn(64, n, generator=g, requires_grad=True)
    x = delan.solve_inertia(H, r)
    ref = torch.linalg.solve(H, r.unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(x, ref, rtol=1e-9, atol=1e-10)
    w = torch.randn(64, n, generator=g)
    gH, gr = torch.autograd.grad((x * w).sum(), (H, r))
    rH, rr = torch.autograd.grad((ref * w).sum(), (H, r))
    # H is symmetric (L Lᵀ): only its gradient along symmetric perturbations is defined alike by every solver
    E = torch.randn(64, n, n, generator=g)
    E = E + E.transpose(1, 2)
    torch.testing.assert_close((gH * E).sum((1, 2)), (rH * E).sum((1, 2)), rtol=1e-8, atol=1e-9)
    torch.testing.assert_close(gr, rr, rtol=1e-8, atol=1e-9)
