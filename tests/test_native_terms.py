"""The native training kernel (rust/grad via exolan.native_terms) against torch's autograd of the same
Lagrangian: outputs and every gradient (q, q̇, z, each weight), float64 to round-off and float32 to its
precision; when it is used and when not; the same bits at any thread count."""
import os

import pytest
import torch

from exolan import native_terms
from exolan.delan import Lagrangian

pytestmark = pytest.mark.skipif(not native_terms.enabled(), reason="the native module is not built")

CASES = [(("revolute", "revolute"), 16), (("prismatic",), 0), (("revolute", "prismatic", "revolute"), 4),
         (("revolute",), 3)]


def _terms_and_grads(lag, q, qd, z, weights, native: bool):
    old = os.environ.get("EXOLAN_NATIVE_TERMS")
    os.environ["EXOLAN_NATIVE_TERMS"] = "1" if native else "0"
    try:
        outs = lag.factor_terms(q, qd, z)
        loss = sum((o * w).sum() for o, w in zip(outs, weights))
        inputs = [q, qd, z] + list(lag.parameters())
        grads = torch.autograd.grad(loss, inputs, allow_unused=True)
    finally:
        if old is None:
            del os.environ["EXOLAN_NATIVE_TERMS"]
        else:
            os.environ["EXOLAN_NATIVE_TERMS"] = old
    return [o.detach() for o in outs], [g if g is not None else torch.zeros_like(x) for g, x in zip(grads, inputs)]


@pytest.mark.parametrize("joint_types,dz", CASES)
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_kernel_matches_autograd(joint_types, dz, dtype, tol, monkeypatch):
    monkeypatch.setattr(native_terms, "DTYPES", (torch.float32, torch.float64))
    torch.manual_seed(len(joint_types) + dz)
    lag = Lagrangian(joint_types, dz, hidden=24, softplus_offset=1e-2, v_scale=2.5).to(dtype)
    N, n = 300, len(joint_types)                                 # not a multiple of the kernel's tile
    q = (2 * torch.randn(N, n, dtype=dtype)).requires_grad_()
    qd = torch.randn(N, n, dtype=dtype).requires_grad_()
    z = torch.randn(N, dz, dtype=dtype).requires_grad_()
    weights = [torch.randn(N, n, n, dtype=dtype), torch.randn(N, n, n, dtype=dtype), torch.randn(N, n, dtype=dtype),
               torch.randn(N, n, dtype=dtype)]
    ref_out, ref_grad = _terms_and_grads(lag, q, qd, z, weights, native=False)
    out, grad = _terms_and_grads(lag, q, qd, z, weights, native=True)
    for name, a, b in zip(["L", "H", "c", "g"], out, ref_out):
        assert (a - b).abs().max() <= tol * b.abs().max(), name
    names = ["q", "qd", "z"] + [k for k, _ in lag.named_parameters()]
    for name, a, b in zip(names, grad, ref_grad):
        if b.numel() == 0:
            continue                                             # z of a model without a context
        assert (a - b).abs().max() <= tol * max(float(b.abs().max()), 1e-3), name


def test_used_for_float32_on_the_cpu_only():
    lag = Lagrangian(("revolute", "revolute"), 4)
    q = torch.zeros(5, 2)
    assert native_terms.usable(lag, q)
    assert not native_terms.usable(lag.double(), q.double())       # float64: torch's path, the oracle
    assert not native_terms.usable(Lagrangian(("revolute",) * 4, 4), torch.zeros(5, 4))   # more joints than the kernel
    with pytest.MonkeyPatch.context() as m:
        m.setenv("EXOLAN_NATIVE_TERMS", "0")
        assert not native_terms.usable(lag, q)


def test_thread_count_does_not_change_a_bit():
    torch.manual_seed(0)
    lag = Lagrangian(("revolute", "revolute"), 16)
    N = 2000
    q, qd, z = torch.randn(N, 2, requires_grad=True), torch.randn(N, 2, requires_grad=True), torch.randn(N, 16)
    results = []
    old = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            L, H, c, g = lag.factor_terms(q, qd, z)
            grads = torch.autograd.grad((c ** 2).sum() + (H ** 2).sum() + g.sum(), [q, qd] + list(lag.parameters()),
                                        allow_unused=True)
            results.append([t for t in (L, H, c, g, *grads) if t is not None])
    finally:
        torch.set_num_threads(old)
    assert all(torch.equal(a, b) for a, b in zip(*results))


def test_unused_potential_bias_gets_no_gradient_as_in_torch():
    """V's output bias does not reach g = ∂V/∂q: None, so that Adam's weight decay leaves it alone as before."""
    lag = Lagrangian(("revolute", "revolute"), 2)
    q = torch.randn(40, 2)
    _, _, _, g = lag.factor_terms(q, torch.randn(40, 2), torch.randn(40, 2))
    g.sum().backward()
    assert lag.V[-1].bias.grad is None and lag.V[-1].weight.grad is not None
