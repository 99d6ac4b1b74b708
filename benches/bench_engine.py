"""The Rust engine against torch, measured in the same run on the same model (ExoLaN: hip + knee, DeLaN 2x64,
LIM 2x16, TCN 5x16; random init, float64 unless stated).

    python benches/bench_engine.py [--threads 2] [--batch 256] [--horizon 20] [--json out.json]

Single sample: the Rust engine's own cost (timed inside Rust, `Engine.time_hot`), the same call through the
Python binding, and torch eager (`model.inverse` etc. on one sample, no_grad). Batched: open-loop rollouts of
B x T steps, Rust (`threads` threads; float64, and float32 with `precision="f32"`) vs torch batched (exolan.rollout.rollout, the analytic forward-mode
derivative path, torch.set_num_threads(threads)). Every figure is the minimum over repeats (the machine may be
shared; the minimum is the least disturbed run), and the script prints the ratios.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "python"))

from exolan.engine import Engine  # noqa: E402
from exolan.export import export  # noqa: E402
from exolan.models import build_model  # noqa: E402
from exolan.rollout import rollout as torch_rollout  # noqa: E402

CHANNELS = ["q_hip", "q_knee", "qd_hip", "qd_knee", "f_v", "cop_x", "cop_z"]


def best_of(f, repeats: int, per: int) -> float:
    """Seconds per call: minimum over `repeats` batches of `per` calls."""
    f()
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        for _ in range(per):
            f()
        best = min(best, (time.perf_counter() - t) / per)
    return best


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--horizon", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    model = build_model("exolan", lim=True, context_channels=CHANNELS, joint_names=("hip", "knee")).double().eval()
    tmp = Path(tempfile.mkdtemp())
    eng = Engine(export(model, tmp / "bench.safetensors", {"dt": 0.005}))
    rng = np.random.default_rng(0)
    q, qd, qdd = (rng.normal(size=(1, 2)) for _ in range(3))
    z = rng.normal(size=(1, 16)) * 0.5
    fv = np.array([300.0])
    T = torch.as_tensor
    tq, tqd, tqdd, tz, tfv = T(q), T(qd), T(qdd), T(z), T(fv)
    R = a.repeats
    res: dict = {"threads": a.threads, "batch": a.batch, "horizon": a.horizon, "simd": eng.simd,
                 "torch": torch.__version__, "cpu_count": os.cpu_count(), "load_avg": os.getloadavg()}

    # --- single sample ------------------------------------------------------------------------
    single = {}
    single["inverse"] = dict(
        rust_native=eng.time_hot("inverse", 200, 100),
        rust_python=best_of(lambda: eng.inverse_dynamics(q, qd, qdd, z, fv), R, 200),
    )
    single["forward"] = dict(
        rust_native=eng.time_hot("forward", 200, 100),
        rust_python=best_of(lambda: eng.forward_dynamics(q, qd, qdd, z, fv), R, 200),
    )
    single["rollout_step"] = dict(rust_native=eng.time_hot("rollout_step", 1, 100))
    # the opt-in float32 single-sample path (precision="f32")
    single32 = dict(inverse=eng.time_hot("inverse_f32", 200, 100), forward=eng.time_hot("forward_f32", 200, 100),
                    rollout_step=eng.time_hot("rollout_step_f32", 1, 100),
                    inverse_python=best_of(lambda: eng.inverse_dynamics(q[0], qd[0], qdd[0], z[0], fv[0],
                                                                        precision="f32"), R, 200))
    single["encode_step"] = dict(rust_native=eng.time_hot("encode_step", 200, 100))
    with torch.no_grad():
        single["inverse"]["torch_eager"] = best_of(lambda: model.inverse(tq, tqd, tqdd, tz, tfv), R, 20)
        single["forward"]["torch_eager"] = best_of(lambda: model.forward_dynamics(tq, tqd, tqdd, tz, tfv), R, 20)

        def torch_step():
            a_ = model.forward_dynamics(tq, tqd, tqdd, tz, tfv)
            v = tqd + 0.005 * a_
            return tq + 0.005 * v, v

        single["rollout_step"]["torch_eager"] = best_of(torch_step, R, 20)
        # torch has no streaming encoder: z_t needs a pass over the receptive field (63 samples)
        xw = T(rng.normal(size=(1, 63, 7)))
        single["encode_step"]["torch_eager"] = best_of(lambda: model.context(xw)[:, -1], R, 10)
    res["single"] = single
    res["single_f32"] = single32

    # --- batched rollouts ---------------------------------------------------------------------
    B, H = a.batch, a.horizon
    q0, qd0 = rng.normal(size=(B, 2)) * 0.5, rng.normal(size=(B, 2))
    tau = rng.normal(size=(B, H, 2)) * 5
    zs = rng.normal(size=(B, H, 16)) * 0.5
    fvs = rng.uniform(0, 600, size=(B, H))
    rust_b = best_of(lambda: eng.rollout(q0, qd0, tau, 0.005, z=zs, f_v=fvs, threads=a.threads), R, 1)
    rust_b32 = best_of(lambda: eng.rollout(q0, qd0, tau, 0.005, z=zs, f_v=fvs, threads=a.threads, precision="f32"),
                       R, 1)
    args64 = [T(x) for x in (q0, qd0, tau)] + [0.005, T(zs), T(fvs)]
    with torch.no_grad():
        torch_b64 = best_of(lambda: torch_rollout(model, *args64), R, 1)
        m32 = build_model("exolan", lim=True, context_channels=CHANNELS, joint_names=("hip", "knee")).eval()
        m32.load_state_dict({k: v.float() for k, v in model.state_dict().items()})
        args32 = [T(x).float() for x in (q0, qd0, tau)] + [0.005, T(zs).float(), T(fvs).float()]
        torch_b32 = best_of(lambda: torch_rollout(m32, *args32), R, 1)
    steps = B * H
    res["batched"] = dict(rust_s=rust_b, rust_f32_s=rust_b32, torch64_s=torch_b64, torch32_s=torch_b32,
                          rust_steps_per_s=steps / rust_b, rust_f32_steps_per_s=steps / rust_b32,
                          torch64_steps_per_s=steps / torch_b64, torch32_steps_per_s=steps / torch_b32)

    # --- report ---------------------------------------------------------------------------------
    us = lambda s: f"{s * 1e6:10.2f} µs"
    print(f"exolan engine benchmark  (simd {eng.simd}, threads {a.threads}, torch {torch.__version__}, "
          f"load avg {res['load_avg'][0]:.1f} on {os.cpu_count()} cpus)")
    print(f"{'single sample':<16}{'Rust native':>14}{'Rust via Py':>14}{'torch eager':>14}{'eager/native':>14}")
    for k, v in single.items():
        py = us(v["rust_python"]) if "rust_python" in v else " " * 13 + "-"
        print(f"{k:<16}{us(v['rust_native'])}  {py}  {us(v['torch_eager'])}  {v['torch_eager'] / v['rust_native']:10.0f}x")
    b = res["batched"]
    print(f"batched rollouts B={B} x T={H}: Rust {b['rust_steps_per_s'] / 1e6:.3f} M steps/s, "
          f"torch float64 {b['torch64_steps_per_s'] / 1e6:.3f} M steps/s, torch float32 "
          f"{b['torch32_steps_per_s'] / 1e6:.3f} M steps/s  ->  Rust/torch64 {b['torch64_s'] / b['rust_s']:.1f}x, "
          f"Rust/torch32 {b['torch32_s'] / b['rust_s']:.1f}x")
    print(f"batched rollouts, Rust precision=\"f32\": {b['rust_f32_steps_per_s'] / 1e6:.3f} M steps/s  ->  "
          f"Rust f32/torch32 {b['torch32_s'] / b['rust_f32_s']:.1f}x, Rust f32/Rust f64 {b['rust_s'] / b['rust_f32_s']:.1f}x")
    print("single sample, precision=\"f32\", Rust native: " + ", ".join(
        f"{k} {v * 1e6:.2f} µs" for k, v in single32.items() if k != "inverse_python")
        + f"; inverse via Python {single32['inverse_python'] * 1e6:.2f} µs")
    inv, py1 = single["inverse"]["rust_native"], single["inverse"]["rust_python"]
    print(f"issue #39 targets: inverse native {inv * 1e6:.2f} µs (≤ 1.5), via Python {py1 * 1e6:.2f} µs (≤ 5), "
          f"batched Rust/torch32 {b['torch32_s'] / b['rust_s']:.1f}x (f64), "
          f"{b['torch32_s'] / b['rust_f32_s']:.1f}x (f32) (≥ 5)")
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=2) + "\n")
    return res


if __name__ == "__main__":
    main()
