"""Type stub of the Rust engine's binding (rust/python.rs). Arrays are float64 numpy arrays, C-contiguous for
the batch methods; `tests/test_native_stub.py` checks this file against the built module."""

from os import PathLike

import numpy as np
import numpy.typing as npt

_F64 = npt.NDArray[np.float64]

__version__: str
FORMAT_VERSION: str

def sum(xs: _F64) -> float:
    """Sum of a contiguous 1-D array, read without copying (a build test of the binding)."""

def scale_in_place(xs: _F64, k: float) -> int:
    """Multiply a contiguous 1-D array by k in place; returns the address of the data it used."""

_Arr = npt.NDArray[np.float32] | npt.NDArray[np.float64]

def terms_forward(
    joint_types: list[str],
    dz: int,
    softplus_offset: float,
    v_scale: float,
    l_weights: list[_Arr],
    v_weights: list[_Arr],
    q: _Arr,
    qd: _Arr,
    z: _Arr,
    l_out: _Arr,
    h_out: _Arr,
    c_out: _Arr,
    g_out: _Arr,
    keep: bool,
    threads: int,
) -> TermsCall | None:
    """The training kernel (rust/grad): L, H (N, n, n), c, g (N, n) written into the given arrays from q, qd (N, n),
    z (N, dz) and the inertia and potential networks' [W, b, ...] (float32 or float64, all alike); with `keep`, the
    call to take the reverse pass from (python/exolan/native_terms.py)."""

class TermsCall:
    def backward(
        self, dl: _Arr, dh: _Arr, dc: _Arr, dg: _Arr, dq: _Arr, dqd: _Arr, dz: _Arr, threads: int
    ) -> tuple[list[tuple[_Arr, _Arr]], list[tuple[_Arr, _Arr]]]:
        """Gradients of q, qd, z written into dq, dqd, dz from those of L, H, c, g; returns the weight gradients
        [(dW, db), ...] of the inertia and the potential network."""
    @property
    def samples(self) -> int:
        """Samples of the forward pass."""

def mlp_forward(weights: list[_Arr], x: _Arr, y: _Arr, keep: bool, threads: int) -> MlpCall | None:
    """The plain tanh MLP's training kernel (rust/grad/mlp.rs): y (N, d_out) written from x (N, d_in) through
    [W₀, b₀, ...] (float32 or float64, all alike); with `keep`, the call to take the reverse pass from
    (python/exolan/native_mlp.py)."""

class MlpCall:
    def backward(self, dy: _Arr, dx: _Arr | None, threads: int) -> list[tuple[_Arr, _Arr]]:
        """The weight gradients [(dW, db), ...] from dy (N, d_out); dx (N, d_in) written where given."""

def tcn_forward(
    c_in: int,
    hidden: int,
    levels: int,
    kernel: int,
    weights: list[_Arr],
    x: _Arr,
    keep: _Arr,
    z: _Arr,
    tape: bool,
    threads: int,
) -> TcnCall | None:
    """The TCN encoder's training kernel (rust/tcn.rs): z (B, T, hidden) written into `z` from x (B, T, c_in) and
    keep (B, T) (float32 or float64, all alike), the convs' [W, b, ...] in block order (conv1, conv2, res where
    present); with `tape`, the call to take the reverse pass from (python/exolan/native_tcn.py)."""

class TcnCall:
    def backward(self, dz: _Arr, dx: _Arr | None, threads: int) -> list[tuple[_Arr, _Arr]]:
        """The convs' weight gradients [(dW, db), ...] from dz (B, T, hidden); dx (B, T, c_in) written where given."""
    @property
    def batch(self) -> int:
        """Sequences of the forward pass."""

class Engine:
    """A loaded model; batch methods take arrays with the leading dimension N or B in place."""

    def __new__(cls, path: str | PathLike[str]) -> Engine: ...
    @staticmethod
    def from_bytes(data: bytes) -> Engine: ...
    @property
    def n(self) -> int: ...
    @property
    def z_dim(self) -> int: ...
    @property
    def context_dim(self) -> int: ...
    @property
    def method(self) -> str: ...
    @property
    def lim(self) -> bool: ...
    @property
    def encoder(self) -> str: ...
    @property
    def joint_names(self) -> list[str]: ...
    @property
    def joint_types(self) -> list[str]: ...
    @property
    def context_channels(self) -> list[str]: ...
    @property
    def dt(self) -> float: ...
    @property
    def extensions(self) -> list[str]: ...
    @property
    def metadata(self) -> dict[str, str]: ...
    @property
    def simd(self) -> str: ...
    def inverse_dynamics(
        self,
        q: _F64,
        qd: _F64,
        qdd: _F64,
        z: _F64 | None = None,
        f_v: _F64 | None = None,
        tau_e: _F64 | None = None,
        tau_app: _F64 | None = None,
        tau_app_d: _F64 | None = None,
        tau_app_dd: _F64 | None = None,
    ) -> _F64:
        """τ, flat (N·n,), from q, qd, qdd (N, n), z (N, dz), f_v (N,), exo torques (N, n)."""
    def forward_dynamics(
        self,
        q: _F64,
        qd: _F64,
        tau: _F64,
        z: _F64 | None = None,
        f_v: _F64 | None = None,
        tau_e: _F64 | None = None,
        tau_app: _F64 | None = None,
    ) -> _F64:
        """q̈, flat (N·n,)."""
    def inverse_dynamics_one(
        self, q: _F64, qd: _F64, qdd: _F64, z: _F64 | None = None, f_v: float | _F64 | None = None,
        precision: str = "f64",
    ) -> _F64:
        """One sample ((n,) or (1, n)) with the GIL held; TypeError for anything else. precision "f64"
        or "f32" (float32 pass, no extension terms; ValueError for anything else)."""
    def forward_dynamics_one(
        self, q: _F64, qd: _F64, tau: _F64, z: _F64 | None = None, f_v: float | _F64 | None = None,
        precision: str = "f64",
    ) -> _F64:
        """One sample, as inverse_dynamics_one."""
    def terms(self, q: _F64, qd: _F64, z: _F64 | None = None) -> _F64:
        """[H, c, g, B] per sample, flat (N·(n·n + 3n),)."""
    def rollout(
        self,
        q0: _F64,
        qd0: _F64,
        tau: _F64,
        dt: float,
        z: _F64 | None = None,
        f_v: _F64 | None = None,
        tau_e: _F64 | None = None,
        threads: int | None = None,
        precision: str = "f64",
    ) -> tuple[_F64, _F64]:
        """q and qd, each flat (B·(T+1)·n,), from q0, qd0 (B, n), tau (B, T, n), z (B, dz) or (B, T, dz);
        precision "f64" (bit-exact) or "f32" (float32 lanes)."""
    def encode(self, x: _F64) -> _F64:
        """z, flat (B·T·dz,), streamed from zero state over x (B, T, C)."""
    def time_hot(self, op: str, per_batch: int = 200, batches: int = 100) -> float:
        """Seconds per call of a hot path timed inside Rust (minimum over batches)."""
    def applied_exo(self, tau_e: _F64, dt: float) -> _F64:
        """τ_e(t − d), flat (T·n,), for a recorded (T, n) sequence with the model's delay."""
