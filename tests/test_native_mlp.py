"""The native MLP kernel (rust/grad/mlp.rs via exolan.native_mlp) against torch's autograd of the same tanh MLP:
output and every gradient, float64 to round-off and float32 to its precision; the same bits at any thread count."""
import pytest
import torch

from exolan import native, native_mlp
from exolan.delan import mlp, mlp_forward
from exolan.lim import LIM

pytestmark = pytest.mark.skipif(not native.enabled("mlp_forward"), reason="the native module is not built")


def _run(layers, x, w, on: bool, monkeypatch):
    monkeypatch.setenv("EXOLAN_NATIVE_TERMS", "1" if on else "0")
    y = mlp_forward(layers, x)
    inputs = [x] + list(layers.parameters())
    return y.detach(), torch.autograd.grad((y * w).sum(), inputs)


@pytest.mark.parametrize("d_in,hidden,d_out", [(22, 96, 2), (20, 16, 2), (5, 7, 9), (3, 33, 1)])
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_kernel_matches_autograd(d_in, hidden, d_out, dtype, tol, monkeypatch):
    monkeypatch.setattr(native_mlp, "DTYPES", (torch.float32, torch.float64))
    torch.manual_seed(d_in + hidden)
    layers = mlp(d_in, hidden, d_out).to(dtype)
    x = torch.randn(7, 43, d_in, dtype=dtype, requires_grad=True)        # leading dims; not a multiple of a tile
    w = torch.randn(7, 43, d_out, dtype=dtype)
    y0, g0 = _run(layers, x, w, False, monkeypatch)
    y1, g1 = _run(layers, x, w, True, monkeypatch)
    assert (y1 - y0).abs().max() <= tol * y0.abs().max()
    for a, b in zip(g1, g0):
        assert (a - b).abs().max() <= tol * max(float(b.abs().max()), 1e-3)


def test_used_where_it_applies():
    x = torch.zeros(4, 20)
    assert native_mlp.usable(mlp(20, 16, 2), x)
    assert not native_mlp.usable(torch.nn.ModuleList([torch.nn.Linear(20, 2)]), x)   # no hidden layer: one product
    assert not native_mlp.usable(mlp(20, 16, 2).double(), x.double())
    assert native_mlp.usable(LIM(("revolute", "revolute"), 16), x)


def test_thread_count_does_not_change_a_bit():
    torch.manual_seed(0)
    layers = mlp(22, 96, 2)
    x = torch.randn(3000, 22, requires_grad=True)
    outs = []
    for threads in (1, 2):
        with native.cpu_threads(threads):
            y = mlp_forward(layers, x)
            outs.append([y] + list(torch.autograd.grad((y ** 2).sum(), [x] + list(layers.parameters()))))
    assert all(torch.equal(a, b) for a, b in zip(*outs))
