"""Python face of the Rust engine (`exolan._native`): `Engine` and `fast_rollout`.

    eng = Engine("model.safetensors")
    tau = eng.inverse_dynamics(q, qd, qdd, z, f_v)          # (..., n)
    qdd = eng.forward_dynamics(q, qd, tau, z, f_v)          # (..., n)
    H, c, g, B = eng.terms(q, qd, z)                        # (..., n, n), (..., n) x 3
    q, qd = eng.rollout(q0, qd0, tau, dt, z=z, f_v=f_v)     # (B, T+1, n) or (T+1, n)
    z = eng.encode(x)                                       # (T, C) -> (T, dz), streaming from zero state
    q, qd = fast_rollout("model.safetensors", q0, qd0, tau, dt, z=z, f_v=f_v)

numpy in, numpy out (float64); leading dimensions are free for the per-sample calls; z of shape (dz,) and
a scalar f_v broadcast. The work runs in Rust with the GIL released; bad shapes or non-finite inputs raise
ValueError with the engine's message, a singular inertia or a diverging rollout ArithmeticError.
This module imports numpy and the native extension only (no torch).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np


def _native():
    from . import _native as nat

    if nat is None:
        raise ImportError("exolan._native is not built: run `maturin develop --release`")
    return nat


class EngineTerms(NamedTuple):
    H: np.ndarray  # (..., n, n)
    c: np.ndarray  # (..., n)
    g: np.ndarray  # (..., n)
    B: np.ndarray  # (..., n) LIM lever arms (zeros without LIM)


def _f64(x, name):
    try:
        a = np.asarray(x, dtype=np.float64)
        # (np.ascontiguousarray would turn a 0-d array into 1-d)
        return a if a.flags.c_contiguous else np.ascontiguousarray(a)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be convertible to a float64 array ({exc})") from None


class Engine:
    """A model loaded by the Rust engine. `model`: a weight-file path, its bytes, or an Engine."""

    def __init__(self, model):
        nat = _native()
        if isinstance(model, Engine):
            self._e = model._e
        elif isinstance(model, nat.Engine):
            self._e = model
        elif isinstance(model, (bytes, bytearray, memoryview)):
            self._e = nat.Engine.from_bytes(bytes(model))
        else:
            self._e = nat.Engine(os.fspath(model))
        self.path = None if isinstance(model, (bytes, bytearray, memoryview)) else getattr(model, "path", model)

    # -- description -------------------------------------------------------------------------------
    n = property(lambda self: self._e.n)
    z_dim = property(lambda self: self._e.z_dim)
    context_dim = property(lambda self: self._e.context_dim)
    method = property(lambda self: self._e.method)
    lim = property(lambda self: self._e.lim)
    encoder = property(lambda self: self._e.encoder)
    joint_names = property(lambda self: list(self._e.joint_names))
    joint_types = property(lambda self: list(self._e.joint_types))
    context_channels = property(lambda self: list(self._e.context_channels))
    dt = property(lambda self: self._e.dt)
    extensions = property(lambda self: list(self._e.extensions))
    metadata = property(lambda self: dict(self._e.metadata))
    simd = property(lambda self: self._e.simd)

    def __repr__(self):
        return (f"Engine(method={self.method!r}, lim={self.lim}, encoder={self.encoder!r}, n={self.n}, "
                f"z_dim={self.z_dim}, extensions={self.extensions})")

    # -- shape helpers -----------------------------------------------------------------------------
    def _flat(self, x, name, lead=None):
        a = _f64(x, name)
        n = self.n
        if a.ndim == 0 or a.shape[-1] != n:
            raise ValueError(f"bad input shape: {name} has shape {a.shape}, expected (..., {n})")
        if lead is not None and a.shape[:-1] != lead:
            a = np.broadcast_to(a, lead + (n,))
        return np.ascontiguousarray(a.reshape(-1, n)), a.shape[:-1]

    def _z(self, z, lead):
        dz = self.z_dim
        if z is None:
            if dz:
                raise ValueError(f"this model ({self.method}) needs a context z of dimension {dz}")
            return None
        a = _f64(z, "z")
        if a.ndim == 0 or a.shape[-1] != dz:
            raise ValueError(f"bad input shape: z has shape {a.shape}, expected (..., {dz})")
        try:
            a = np.broadcast_to(a, lead + (dz,))
        except ValueError:
            raise ValueError(f"bad input shape: z has shape {a.shape}, not broadcastable to {lead + (dz,)}") from None
        return np.ascontiguousarray(a.reshape(-1, dz))

    def _fv(self, f_v, lead):
        if f_v is None:
            if self.lim:
                raise ValueError("a model with LIM needs the insole force f_v")
            return None
        a = _f64(f_v, "f_v")
        try:
            a = np.broadcast_to(a, lead)
        except ValueError:
            raise ValueError(f"bad input shape: f_v has shape {a.shape}, expected {lead}") from None
        return np.ascontiguousarray(a.reshape(-1))

    def _opt(self, x, name, lead):
        return None if x is None else self._flat(x, name, lead)[0]

    # -- dynamics ----------------------------------------------------------------------------------
    def inverse_dynamics(self, q, qd, qdd, z=None, f_v=None, tau_e=None, tau_app=None, tau_app_d=None,
                         tau_app_dd=None, precision="f64") -> np.ndarray:
        """τ = H q̈ + c + g − B f_v (+ extension terms): the predicted recorded total torque, (..., n).

        tau_e: recorded exo torque (..., n) for the extension terms; tau_app = τ_e(t − d) (see
        `applied_exo`), tau_app_d/_dd its time derivatives (strap compliance). `precision="f32"`: one
        sample (n,) computed in float32 (float64 in and out; models without extension terms)."""
        if tau_e is None and tau_app is None and tau_app_d is None and tau_app_dd is None:
            try:  # one plain float64 sample: the native fast path (TypeError: anything else; ValueError: precision)
                return self._e.inverse_dynamics_one(q, qd, qdd, z, f_v, precision)
            except TypeError:
                _only_f64(precision, "q, qd, qdd")
        else:
            _only_f64(precision, None)
        qf, lead = self._flat(q, "q")
        args = (qf, self._flat(qd, "qd", lead)[0], self._flat(qdd, "qdd", lead)[0], self._z(z, lead),
                self._fv(f_v, lead), self._opt(tau_e, "tau_e", lead), self._opt(tau_app, "tau_app", lead),
                self._opt(tau_app_d, "tau_app_d", lead), self._opt(tau_app_dd, "tau_app_dd", lead))
        return self._e.inverse_dynamics(*args).reshape(lead + (self.n,))

    def forward_dynamics(self, q, qd, tau, z=None, f_v=None, tau_e=None, tau_app=None, precision="f64") -> np.ndarray:
        """q̈ = H⁻¹(τ + B f_v − c − g − extension terms), (..., n); `precision` as `inverse_dynamics`."""
        if tau_e is None and tau_app is None:
            try:
                return self._e.forward_dynamics_one(q, qd, tau, z, f_v, precision)
            except TypeError:
                _only_f64(precision, "q, qd, tau")
        else:
            _only_f64(precision, None)
        qf, lead = self._flat(q, "q")
        args = (qf, self._flat(qd, "qd", lead)[0], self._flat(tau, "tau", lead)[0], self._z(z, lead),
                self._fv(f_v, lead), self._opt(tau_e, "tau_e", lead), self._opt(tau_app, "tau_app", lead))
        return self._e.forward_dynamics(*args).reshape(lead + (self.n,))

    def terms(self, q, qd, z=None) -> EngineTerms:
        """H (..., n, n), c, g, B (..., n) of the base model at (q, q̇)."""
        qf, lead = self._flat(q, "q")
        n = self.n
        flat = self._e.terms(qf, self._flat(qd, "qd", lead)[0], self._z(z, lead)).reshape(-1, n * n + 3 * n)
        H = flat[:, :n * n].reshape(lead + (n, n))
        c, g, B = (flat[:, n * n + k * n:n * n + (k + 1) * n].reshape(lead + (n,)) for k in range(3))
        return EngineTerms(H, c, g, B)

    def rollout(self, q0, qd0, tau, dt=None, z=None, f_v=None, tau_e=None, threads=None, precision="f64"):
        """Semi-implicit Euler over T = tau.shape[-2] steps (DESIGN.md section 5).

        Unbatched: q0, qd0 (n,), tau (T, n), z (dz,) or (T, dz), f_v (T,), tau_e (T, n) -> q, qd (T+1, n).
        Batched: q0, qd0 (B, n), tau (B, T, n), z (B, dz), (B, T, dz) or (dz,), f_v (B, T) -> (B, T+1, n).
        Index 0 is the initial state. dt defaults to the model's (metadata `dt`). A batch is spread over
        `threads` threads (default: one per core, the engine's own pool); the result is bit-identical
        for every thread count. `precision="f32"` computes in float32, 16 rollouts per SIMD register
        (inputs and outputs stay float64; agrees with "f64" to ~1e-6 relative over 20 steps on random
        models; models without extension terms only; docs/ENGINE.md); unbatched, or B = 1, it runs the
        float32 single-sample pass with the state integrated in float64."""
        n, dz = self.n, self.z_dim
        q0 = _f64(q0, "q0")
        batched = q0.ndim == 2
        if q0.ndim not in (1, 2):
            raise ValueError(f"bad input shape: q0 has shape {q0.shape}, expected (n,) or (B, n)")
        if not batched:
            q0 = q0[None]
        B = q0.shape[0]
        add = (lambda a: a[None]) if not batched else (lambda a: a)
        qd0 = add(_f64(qd0, "qd0"))
        tau = add(_f64(tau, "tau"))
        if tau.ndim != 3:
            raise ValueError(f"bad input shape: tau has shape {tau.shape}, expected {'(B, T, n)' if batched else '(T, n)'}")
        T = tau.shape[1]
        if dt is None:
            dt = self.dt
            if not dt:
                raise ValueError("dt not given and the weight file has none")
        zz = None
        if z is not None:
            zz = _f64(z, "z")
            if zz.ndim == 1:
                zz = np.broadcast_to(zz, (B, zz.shape[0]))
            elif not batched:
                zz = zz[None]
            zz = np.ascontiguousarray(zz)
        elif dz:
            raise ValueError(f"this model ({self.method}) needs a context z of dimension {dz}")
        fv = None
        if f_v is not None:
            fv = _f64(f_v, "f_v")
            fv = np.ascontiguousarray(fv if batched else fv[None])
        te = None if tau_e is None else np.ascontiguousarray(add(_f64(tau_e, "tau_e")))
        q, qd = self._e.rollout(np.ascontiguousarray(q0), np.ascontiguousarray(qd0), np.ascontiguousarray(tau),
                                float(dt), zz, fv, te, threads, precision)
        shape = (B, T + 1, n) if batched else (T + 1, n)
        return q.reshape(shape), qd.reshape(shape)

    def encode(self, x) -> np.ndarray:
        """Raw context features (T, C) or (B, T, C) -> z (T, dz) or (B, T, dz), streamed sample by sample
        from zero state (a trial start), exactly as a controller runs it."""
        a = _f64(x, "x")
        if a.ndim == 2:
            return self._e.encode(a[None]).reshape(a.shape[0], self.z_dim)
        if a.ndim != 3:
            raise ValueError(f"bad input shape: x has shape {a.shape}, expected (T, C) or (B, T, C)")
        return self._e.encode(a).reshape(a.shape[0], a.shape[1], self.z_dim)

    def time_hot(self, op: str, per_batch: int = 200, batches: int = 100) -> float:
        """Native seconds per call of a hot path timed inside Rust ("inverse", "forward", "rollout_step",
        "encode_step"): the minimum over batches, for benchmarks on a shared machine."""
        return self._e.time_hot(op, per_batch, batches)

    def applied_exo(self, tau_e, dt=None) -> np.ndarray:
        """τ_e(t − d) for a recorded sequence (T, n) with the model's delay (τ_e itself without one)."""
        dt = self.dt if dt is None else dt
        a = _f64(tau_e, "tau_e")
        return self._e.applied_exo(a, float(dt)).reshape(a.shape)


_CACHE: dict = {}


def _engine(model) -> Engine:
    if isinstance(model, Engine):
        return model
    p = Path(os.fspath(model)).resolve()
    st = p.stat()
    key = (str(p), st.st_mtime_ns, st.st_size)
    eng = _CACHE.get(key)
    if eng is None:
        eng = _CACHE[key] = Engine(p)
    return eng


def _only_f64(precision, args) -> None:
    """The batch path (several samples, or exo torques) runs float64 only: ValueError for anything else."""
    if precision == "f64":
        return
    if precision != "f32":
        raise ValueError(f'precision must be "f64" or "f32", got {precision!r}')
    if args is None:
        raise ValueError('precision="f32" does not take exo torques (models with extension terms need "f64")')
    raise ValueError(f'precision="f32" takes one plain sample: {args} of shape (n,), z (dz,), f_v a number')


def fast_rollout(model, q0, qd0, tau, dt=None, z=None, f_v=None, tau_e=None, threads=None, precision="f64"):
    """Rollouts with the Rust engine. `model`: weight-file path (loaded once and cached) or Engine.
    Shapes as `Engine.rollout`: (n,)/(T, n) unbatched or (B, n)/(B, T, n) batched; returns (q, qd).
    `precision`: "f64" (bit-exact with torch float64) or "f32" (faster batches, see `Engine.rollout`)."""
    return _engine(model).rollout(q0, qd0, tau, dt, z=z, f_v=f_v, tau_e=tau_e, threads=threads,
                                  precision=precision)


# -- `exolan rollout MODEL --data DIR` --------------------------------------------------------------

def rollout_errors(eng: Engine, trials, horizon: int = 20, stride: int = 5) -> dict:
    """Open-loop rollouts of `horizon` steps from every `stride`-th start whose window is valid, z from
    the streaming encoder over the whole trial; per-joint RMSE of q and q̇ at the horizon."""
    from .data import context_features

    n = eng.n
    sq = np.zeros(n)
    sqd = np.zeros(n)
    count = 0
    for t in trials:
        T = len(t.q)
        if T <= horizon:
            continue
        ok = np.lib.stride_tricks.sliding_window_view(np.asarray(t.valid, bool), horizon + 1).all(axis=1)
        starts = np.nonzero(ok)[0][::stride]
        if len(starts) == 0:
            continue
        z = eng.encode(context_features(t)) if eng.z_dim else None
        steps = starts[:, None] + np.arange(horizon + 1)[None]
        win = lambda a: a[steps]
        q, qd = eng.rollout(t.q[starts], t.qd[starts], win(t.tau)[:, :horizon], t.dt,
                            z=None if z is None else win(z)[:, :horizon],
                            f_v=win(t.f_v)[:, :horizon] if eng.lim else None,
                            tau_e=win(t.tau_e)[:, :horizon] if eng.extensions else None)
        sq += ((q[:, horizon] - t.q[starts + horizon]) ** 2).sum(0)
        sqd += ((qd[:, horizon] - t.qd[starts + horizon]) ** 2).sum(0)
        count += len(starts)
    if count == 0:
        return {"rollouts": 0}
    return {"rollouts": int(count), "horizon": int(horizon),
            "q_rmse": dict(zip(eng.joint_names, np.sqrt(sq / count).tolist())),
            "qd_rmse": dict(zip(eng.joint_names, np.sqrt(sqd / count).tolist()))}


def cli_rollout(args) -> int:
    import json
    import time

    from . import data as _data

    eng = Engine(args.model)
    ds = _data.load(args.data)
    trials = list(ds)
    t0 = time.perf_counter()
    res = rollout_errors(eng, trials, horizon=args.horizon)
    res["seconds"] = time.perf_counter() - t0
    res["model"] = str(args.model)
    res["data"] = str(args.data)
    text = json.dumps(res, indent=2)
    print(text)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text + "\n")
    return 0
