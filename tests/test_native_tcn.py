"""The native TCN encoder (rust/tcn.rs through exolan.native_tcn) against torch's autograd: z, the gradient of x
and of every parameter, float64 to 1e-12 and float32 to 1e-5 (relative to each tensor's largest value), with
pre-start masks, a 1x1 and an identity residual, sequences shorter than the receptive field and longer than a
chunk; no tape without gradients; the same bits at any thread count; the switch."""
import pytest
import torch

from exolan import native_tcn
from exolan.encoder import TCNEncoder

pytestmark = pytest.mark.skipif(not native_tcn.enabled(), reason="the native module has no tcn_forward")
BOTH = (torch.float32, torch.float64)
_encode = native_tcn.encode


def _encoder(C: int, dtype, seed: int = 0, **kw) -> TCNEncoder:
    torch.manual_seed(seed)
    enc = TCNEncoder(C, **kw).to(dtype)
    with torch.no_grad():  # default init leaves many ReLUs dead; larger random values exercise every path
        for p in enc.parameters():
            p.copy_(torch.randn_like(p) * 0.5)
    return enc


def _inputs(B: int, T: int, C: int, dtype, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(B, T, C, generator=g, dtype=dtype)
    keep = torch.ones(B, T, dtype=torch.bool)
    for b in range(B):  # 0, 5, 62, ... positions before the trial start, a whole row of them at b = 3
        keep[b, : (0, 5, 62, T)[b % 4]] = False
    return x, keep


def _run(monkeypatch, enc, x, keep, gz, native: bool):
    """z, dx and every parameter's gradient, through the kernel or through torch's path."""
    calls = []
    with monkeypatch.context() as m:
        m.setattr(native_tcn, "DTYPES", BOTH if native else ())
        m.setattr(native_tcn, "encode", lambda *a: calls.append(1) or _encode(*a))
        x = x.clone().requires_grad_(True)
        enc.zero_grad()
        z = enc(x, keep)
        z.backward(gz)
    assert len(calls) == int(native)
    return [z.detach(), x.grad] + [p.grad.clone() for p in enc.parameters()]


def _rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-30))


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
@pytest.mark.parametrize("C", [7, 16])
@pytest.mark.parametrize("B,T", [(1, 5), (3, 70), (4, 517), (32, 318)])
def test_matches_torch_autograd(monkeypatch, dtype, tol, C, B, T):
    enc = _encoder(C, dtype)
    x, keep = _inputs(B, T, C, dtype)
    gz = torch.randn(B, T, enc.z_dim, generator=torch.Generator().manual_seed(2), dtype=dtype)
    got = _run(monkeypatch, enc, x, keep, gz, native=True)
    want = _run(monkeypatch, enc, x, keep, gz, native=False)
    names = ["z", "dx"] + [n for n, _ in enc.named_parameters()]
    assert len(got) == len(want) == 2 + 20 + (2 if C != 16 else 0)
    assert want[0].abs().max() > 0.1 and want[1].abs().max() > 0
    for name, g, w in zip(names, got, want):
        assert g.shape == w.shape and g.dtype == w.dtype, name
        assert _rel_err(g, w) < tol, f"{name}: relative error {_rel_err(g, w):.2e}"
    # the gradient of x is zero before the trial start (the input is multiplied by keep)
    assert torch.all(got[1][~keep] == 0)


def test_without_keep_and_other_shapes(monkeypatch):
    """keep None, kernel 3, 3 levels, hidden 5 (padded to the lane count) and parameters that need no gradient."""
    enc = _encoder(4, torch.float64, hidden=5, levels=3, kernel=3)
    enc.tcn[1].conv2.weight.requires_grad_(False)
    x = torch.randn(2, 40, 4, dtype=torch.float64)
    gz = torch.randn(2, 40, 5, dtype=torch.float64)
    calls = []
    with monkeypatch.context() as m:
        m.setattr(native_tcn, "DTYPES", BOTH)
        m.setattr(native_tcn, "encode", lambda *a: calls.append(1) or _encode(*a))
        xg = x.clone().requires_grad_(True)
        z = enc(xg)
        z.backward(gz)
    got = [z.detach(), xg.grad] + [p.grad for p in enc.parameters() if p.requires_grad]
    assert calls and enc.tcn[1].conv2.weight.grad is None
    enc.zero_grad()
    xt = x.clone().requires_grad_(True)
    zt = enc(xt)
    zt.backward(gz)
    want = [zt.detach(), xt.grad] + [p.grad for p in enc.parameters() if p.requires_grad]
    for g, w in zip(got, want):
        assert _rel_err(g, w) < 1e-12


def test_no_tape_without_gradients_and_same_bits_at_any_thread_count():
    enc = _encoder(7, torch.float32)
    x, keep = _inputs(9, 300, 7, torch.float32)
    params = native_tcn._params(enc)
    arrays = [p.detach().numpy() for p in params]
    z = torch.empty(9, 300, 16)
    k = keep.to(torch.float32)
    assert native_tcn._native.tcn_forward(7, 16, 5, 2, arrays, x.numpy(), k.numpy(), z.numpy(), False, 1) is None
    assert native_tcn._native.tcn_forward(7, 16, 5, 2, arrays, x.numpy(), k.numpy(), z.numpy(), True, 1).batch == 9
    with torch.no_grad():
        assert torch.equal(enc(x, keep), z)
    threads = torch.get_num_threads()
    results = []
    try:
        for n in (1, 2, 3):
            torch.set_num_threads(n)
            enc.zero_grad()
            xg = x.clone().requires_grad_(True)
            zz = enc(xg, keep)
            zz.backward(torch.ones_like(zz))
            results.append([zz.detach(), xg.grad] + [p.grad.clone() for p in enc.parameters()])
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(results[0][0], z)
    for r in results[1:]:
        assert all(torch.equal(a, b) for a, b in zip(r, results[0]))


def test_switch_and_fallbacks(monkeypatch):
    enc = _encoder(7, torch.float32)
    x = torch.randn(2, 10, 7)
    assert native_tcn.usable(enc, x)
    assert not native_tcn.usable(enc.double(), x.double())       # float64: torch's path unless the tests ask
    monkeypatch.setenv("EXOLAN_NATIVE_TERMS", "0")
    assert not native_tcn.usable(enc.float(), x)
