"""Context encoders: the whole-sequence TCN pass equals a fresh 63-step window per sample; causality;
training chunks that start before the trial reproduce the whole-trial z exactly."""
import torch

from exolan.encoder import LSTMEncoder, TCNEncoder, tcn_window_z
from exolan.models import build_model


def _randomise(module):
    # default init gives many dead ReLUs; larger random biases exercise every path
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn_like(p) * 0.5)


def test_tcn_receptive_field_is_63():
    assert TCNEncoder(7).receptive_field == 63


def test_sequence_pass_equals_per_sample_window_pass():
    torch.manual_seed(0)
    enc = TCNEncoder(7).double()
    _randomise(enc)
    x = torch.randn(150, 7, dtype=torch.float64)
    z_seq = enc(x.unsqueeze(0))[0]
    z_win = tcn_window_z(enc, x)
    assert z_seq.abs().max() > 0.1
    torch.testing.assert_close(z_seq, z_win, rtol=0, atol=1e-12)


def test_tcn_is_causal_with_exact_receptive_field():
    torch.manual_seed(1)
    enc = TCNEncoder(3).double()
    _randomise(enc)
    x = torch.randn(1, 200, 3, dtype=torch.float64)
    z = enc(x)
    x2 = x.clone()
    x2[0, 120] += 1.0
    dz = (enc(x2) - z).abs().amax(-1)[0]
    assert torch.all(dz[:120] == 0)                 # nothing before the change moves
    assert dz[120:183].min() > 0                    # the change is seen for 63 steps ...
    assert torch.all(dz[183:] == 0)                 # ... and not after


def test_chunk_with_prestart_mask_equals_trial_start():
    """A training chunk beginning 62 samples before the trial start (masked) gives the trial's z."""
    torch.manual_seed(2)
    enc = TCNEncoder(4).double()
    _randomise(enc)
    x = torch.randn(1, 80, 4, dtype=torch.float64)
    chunk = torch.cat([torch.randn(1, 62, 4, dtype=torch.float64) * 9, x], dim=1)   # garbage before start
    keep = torch.cat([torch.zeros(1, 62, dtype=torch.bool), torch.ones(1, 80, dtype=torch.bool)], dim=1)
    torch.testing.assert_close(enc(chunk, keep)[:, 62:], enc(x), rtol=0, atol=1e-12)
    # and a chunk starting inside the trial, with 62 warm-up samples, matches beyond its warm-up
    torch.testing.assert_close(enc(x[:, 10:])[:, 62:], enc(x)[:, 72:], rtol=0, atol=1e-12)


def test_lstm_chunk_with_prestart_positions_starts_from_zero_state_at_trial_start():
    torch.manual_seed(3)
    enc = LSTMEncoder(5).double()
    x = torch.randn(1, 40, 5, dtype=torch.float64)
    z = enc(x)
    assert z.shape == (1, 40, 16)
    # rows with 0, 7 and 62 garbage samples before the trial start, all 40 + 62 long
    rows, keeps = [], []
    for s in (0, 7, 62):
        garbage = torch.randn(1, s, 5, dtype=torch.float64) * 5
        tail = torch.randn(1, 62 - s, 5, dtype=torch.float64)
        rows.append(torch.cat([garbage, x, tail], dim=1))
        keeps.append(torch.cat([torch.zeros(s, dtype=torch.bool), torch.ones(40, dtype=torch.bool),
                                torch.zeros(62 - s, dtype=torch.bool)]).unsqueeze(0))
    zc = enc(torch.cat(rows), torch.cat(keeps))
    for i, s in enumerate((0, 7, 62)):
        torch.testing.assert_close(zc[i, s:s + 40], z[0], rtol=0, atol=1e-12)


def test_model_context_normalises_and_zeroes_nonfinite():
    m = build_model("exolan", context_channels=["a", "b"], hidden=8).double()
    m.norm.set_stats([1.0, 2.0], [2.0, 0.0])        # zero std is replaced by 1
    x = torch.tensor([[[3.0, float("nan")], [1.0, 4.0]]], dtype=torch.float64)
    torch.testing.assert_close(m.norm(x), torch.tensor([[[1.0, 0.0], [0.0, 2.0]]], dtype=torch.float64))
