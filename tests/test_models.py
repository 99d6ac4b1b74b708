"""The 16 methods by name: one interface, the exact state_dict names and shapes of DESIGN.md section 3."""
import pytest
import torch

from exolan.models import METHODS, build_model

CH = ["q_hip", "q_knee", "qd_hip", "qd_knee", "f_v", "cop_x", "cop_z"]


def _expected(method, lim, C=7, n=2, dz=16):
    enc = {"exolan": "tcn", "delan-lstm": "lstm", "mlp-tcn": "tcn", "mlp-lstm": "lstm", "tcn": "tcn",
           "lstm": "lstm"}.get(method, "none")
    core = "delan" if method in ("exolan", "delan-lstm", "delan") else ("linear" if method in ("tcn", "lstm") else "mlp")
    dz = dz if enc != "none" else 0
    d_in = 2 * n + dz
    e = {}
    if enc != "none":
        e["norm.ctx_mean"] = (C,)
        e["norm.ctx_std"] = (C,)
    if enc == "tcn":
        for i in range(5):
            cin = C if i == 0 else 16
            e[f"encoder.tcn.{i}.conv1.weight"] = (16, cin, 2)
            e[f"encoder.tcn.{i}.conv1.bias"] = (16,)
            e[f"encoder.tcn.{i}.conv2.weight"] = (16, 16, 2)
            e[f"encoder.tcn.{i}.conv2.bias"] = (16,)
        e["encoder.tcn.0.res.weight"] = (16, C, 1)
        e["encoder.tcn.0.res.bias"] = (16,)
    if enc == "lstm":
        for k in range(5):
            cin = C if k == 0 else 16
            e[f"encoder.lstm.weight_ih_l{k}"] = (64, cin)
            e[f"encoder.lstm.weight_hh_l{k}"] = (64, 16)
            e[f"encoder.lstm.bias_ih_l{k}"] = (64,)
            e[f"encoder.lstm.bias_hh_l{k}"] = (64,)
    if core == "delan":
        for net, out in (("L", n * (n + 1) // 2), ("V", 1)):
            e[f"delan.{net}.0.weight"] = (64, d_in)
            e[f"delan.{net}.0.bias"] = (64,)
            e[f"delan.{net}.1.weight"] = (64, 64)
            e[f"delan.{net}.1.bias"] = (64,)
            e[f"delan.{net}.2.weight"] = (out, 64)
            e[f"delan.{net}.2.bias"] = (out,)
    elif core == "mlp":
        e["head.0.weight"] = (96, 3 * n + dz)
        e["head.0.bias"] = (96,)
        e["head.1.weight"] = (96, 96)
        e["head.1.bias"] = (96,)
        e["head.2.weight"] = (n, 96)
        e["head.2.bias"] = (n,)
    else:
        e["head.0.weight"] = (n, 3 * n + dz)
        e["head.0.bias"] = (n,)
    if lim:
        e["lim.0.weight"] = (16, d_in)
        e["lim.0.bias"] = (16,)
        e["lim.1.weight"] = (16, 16)
        e["lim.1.bias"] = (16,)
        e["lim.2.weight"] = (n, 16)
        e["lim.2.bias"] = (n,)
    return e


@pytest.mark.parametrize("lim", [True, False])
@pytest.mark.parametrize("method", METHODS)
def test_state_dict_names_and_shapes(method, lim):
    m = build_model(method, lim=lim, context_channels=CH)
    got = {k: tuple(v.shape) for k, v in m.state_dict().items()}
    assert got == _expected(method, lim)


@pytest.mark.parametrize("lim", [True, False])
@pytest.mark.parametrize("method", METHODS)
def test_interface_float32_and_float64(method, lim):
    torch.manual_seed(0)
    for dtype in (torch.float32, torch.float64):
        m = build_model(method, lim=lim, context_channels=CH).to(dtype)
        x = torch.randn(2, 70, 7, dtype=dtype)
        z = m.context(x)
        assert z.shape == (2, 70, 0 if method in ("mlp", "delan") else 16)
        q, qd, qdd = (torch.randn(2, 70, 2, dtype=dtype) for _ in range(3))
        f_v = torch.rand(2, 70, dtype=dtype) * 500
        tau = m.inverse(q, qd, qdd, z, f_v)
        assert tau.shape == (2, 70, 2) and tau.dtype == dtype and torch.isfinite(tau).all()
        if m.is_lagrangian:
            assert m.forward_dynamics(q, qd, tau, z, f_v).shape == (2, 70, 2)
            assert m.terms(q, qd, z).H.shape == (2, 70, 2, 2)
        else:
            with pytest.raises(TypeError):
                m.forward_dynamics(q, qd, tau, z, f_v)


def test_unknown_method_and_option_raise():
    with pytest.raises(ValueError):
        build_model("delan-gru")
    with pytest.raises(TypeError):
        build_model("exolan", context_channels=CH, hiden=64)


def test_delan_tcn_alias_and_rebuild_from_spec():
    m = build_model("delan-tcn", lim=True, context_channels=CH, v_scale=12.0, lim_scale=0.07)
    assert m.method == "exolan"
    m2 = build_model(**m.spec())
    m2.load_state_dict(m.state_dict())
    assert m2.delan.v_scale == 12.0 and m2.lim.lim_scale == 0.07
