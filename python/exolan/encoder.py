"""Context encoders: z_t from the history of q, q̇, insole force and centre of pressure (causal).

Both encoders run over a whole sequence at once (one causal pass gives z at every step), which is how
training and evaluation use them; `tcn_window_z` re-runs the TCN on a 63-step window per sample and exists
only to prove that both give the same z.

On the CPU in float32 `TCNEncoder.forward` runs on the native training kernel (native_tcn.py, rust/tcn.rs),
which computes what the torch code below computes.

Input normalisation (`Normalizer`, state_dict `norm.ctx_mean`, `norm.ctx_std`): (x − mean)/std, then
non-finite → 0 (the training mean), as in DESIGN.md section 2.
"""
from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

from . import native_tcn


class Normalizer(nn.Module):
    def __init__(self, channels: int):
        super().__init__()
        self.register_buffer("ctx_mean", torch.zeros(channels))
        self.register_buffer("ctx_std", torch.ones(channels))

    def set_stats(self, mean, std) -> None:
        mean = torch.as_tensor(mean, dtype=self.ctx_mean.dtype)
        std = torch.as_tensor(std, dtype=self.ctx_std.dtype)
        self.ctx_mean.copy_(mean)
        # a constant channel (e.g. f_v of a layout without insoles) must not divide by zero
        self.ctx_std.copy_(torch.where(std > 1e-8, std, torch.ones_like(std)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = (x - self.ctx_mean) / self.ctx_std
        return torch.where(torch.isfinite(y), y, torch.zeros_like(y))


class TCNBlock(nn.Module):
    """h = relu(conv1(x)); h = relu(conv2(h)); y = relu(h + res(x)); causal, dilation d, kernel k."""

    def __init__(self, c_in: int, c_out: int, kernel: int, dilation: int):
        super().__init__()
        self.pad = (kernel - 1) * dilation
        self.conv1 = nn.Conv1d(c_in, c_out, kernel, dilation=dilation)
        self.conv2 = nn.Conv1d(c_out, c_out, kernel, dilation=dilation)
        # identity residual where the channel counts agree (no `res` weights then, DESIGN.md section 3)
        self.res = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else None

    def forward(self, x: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
        """x (B, C, T). `keep` (B, 1, T) is 0 at positions before the trial start: every tensor that a
        dilated conv reads is zeroed there, so a chunk with pre-start positions computes exactly what the
        whole-trial pass computes with its causal zero padding."""
        h = F.relu(self.conv1(F.pad(x, (self.pad, 0))))
        if keep is not None:
            h = h * keep
        h = F.relu(self.conv2(F.pad(h, (self.pad, 0))))
        y = F.relu(h + (x if self.res is None else self.res(x)))
        if keep is not None:
            y = y * keep
        return y


class TCNEncoder(nn.Module):
    def __init__(self, channels: int, hidden: int = 16, levels: int = 5, kernel: int = 2):
        super().__init__()
        self.kernel, self.levels = kernel, levels
        self.tcn = nn.ModuleList(
            TCNBlock(channels if i == 0 else hidden, hidden, kernel, 2 ** i) for i in range(levels))
        self.z_dim = hidden

    @property
    def receptive_field(self) -> int:
        return 1 + 2 * (self.kernel - 1) * sum(2 ** i for i in range(self.levels))

    def forward(self, x: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
        """x (B, T, C) normalised -> z (B, T, hidden). keep (B, T) bool/float: 0 before the trial start."""
        if native_tcn.usable(self, x):
            return native_tcn.encode(self, x, keep)
        h = x.transpose(1, 2)
        k = None
        if keep is not None:
            k = keep.to(h.dtype).unsqueeze(1)
            h = h * k
        for block in self.tcn:
            h = block(h, k)
        return h.transpose(1, 2)


class LSTMEncoder(nn.Module):
    def __init__(self, channels: int, hidden: int = 16, layers: int = 5):
        super().__init__()
        self.lstm = nn.LSTM(channels, hidden, num_layers=layers, batch_first=True)
        self.z_dim = hidden

    def forward(self, x: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
        """x (B, T, C) -> z (B, T, hidden), zero initial state at the trial start.

        `keep` (B, T) marks positions inside the trial. A row whose first s positions lie before the trial
        start is rotated left by s, so that the LSTM starts from zero state exactly at the trial start (as
        the whole-trial pass and the Rust streaming encoder do), and its output rotated back; the pre-start
        positions then hold values that no loss reads. A chunk that starts inside a trial begins from zero
        state after its warm-up samples: the LSTM's memory is unbounded, so that part is a truncation.
        """
        if keep is None:
            z, _ = self.lstm(x)
            return z
        B, T, _ = x.shape
        pre = (~keep.bool()).to(torch.long).cumprod(dim=1).sum(dim=1)          # leading pre-start positions
        if not bool(pre.any()):
            z, _ = self.lstm(x)
            return z
        ar = torch.arange(T, device=x.device)
        fwd = (ar.unsqueeze(0) + pre.unsqueeze(1)) % T                          # (B, T)
        xr = torch.gather(x, 1, fwd.unsqueeze(-1).expand_as(x))
        zr, _ = self.lstm(xr)
        back = (ar.unsqueeze(0) - pre.unsqueeze(1)) % T
        return torch.gather(zr, 1, back.unsqueeze(-1).expand(B, T, zr.shape[-1]))


def tcn_window_z(encoder: TCNEncoder, x: torch.Tensor) -> torch.Tensor:
    """Reference: z_t from a fresh pass over the window x[t−R+1 .. t] (zero left padding before the
    trial start), one window per step. x (T, C) normalised -> (T, hidden). Slow by design."""
    R = encoder.receptive_field
    T, C = x.shape
    padded = torch.cat([x.new_zeros(R - 1, C), x], dim=0)
    windows = padded.unfold(0, R, 1).transpose(1, 2)        # (T, R, C)
    keep = torch.ones(T, R, dtype=torch.bool)
    for t in range(min(T, R - 1)):
        keep[t, : R - 1 - t] = False                        # positions before the trial start
    return encoder(windows, keep)[:, -1, :]
