"""Export a trained model to the Rust engine's weight file (DESIGN.md section 3).

    exolan export RUN --out model.safetensors
    export(model_or_run, path, meta=None)

Every tensor is written in float64 (little-endian) under its torch state_dict name; the metadata carries
what the engine needs to rebuild the physics (format version, method, joints, encoder, scales, dt) plus
free-form `train_*` provenance. An `ExtendedModel` (exolan.extensions) exports its base model's weights
plus the `ext.*` tensors of its active terms (DESIGN.md section 4).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

FORMAT = "exolan-weights"
FORMAT_VERSION = "1"
DELAN_METHODS = ("exolan", "delan-tcn", "delan-lstm", "delan")


def _split_extended(model):
    """(base ExoModel, ext tensors dict, coulomb_eps or None)."""
    if hasattr(model, "ext_tensors") and hasattr(model, "base"):
        return model.base, model.ext_tensors(), float(getattr(model, "coulomb_eps", 0.01))
    return model, {}, None


def _metadata(model, extra: dict) -> dict:
    cfg = dict(getattr(model, "config", {}))
    m = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "method": model.method,
        "lim": "true" if model.use_lim else "false",
        "joint_names": json.dumps(list(model.joint_names)),
        "joint_types": json.dumps(list(model.joint_types)),
        "encoder": model.encoder_kind,
        "z_dim": str(int(model.z_dim)),
        "context_channels": json.dumps(list(model.context_channels)),
        "tcn_levels": str(int(cfg.get("tcn_levels", 5))),
        "tcn_kernel": str(int(cfg.get("tcn_kernel", 2))),
        "lstm_layers": str(int(cfg.get("lstm_layers", 5))),
        "hidden": str(int(cfg.get("hidden", 64))),
        "lim_hidden": str(int(cfg.get("lim_hidden", 16))),
        "activation": "tanh",
        # repr of a Python float is the shortest string that reads back to the same double
        "softplus_offset": repr(float(model.delan.softplus_offset)),
        "v_scale": repr(float(model.delan.v_scale)),
        "lim_scale": repr(float(model.lim.lim_scale if model.lim is not None else cfg.get("lim_scale", 0.1))),
        "coulomb_eps": repr(0.01),
    }
    for k, v in extra.items():
        m[str(k)] = v if isinstance(v, str) else json.dumps(v, default=str)
    return m


def state_tensors(model) -> dict[str, np.ndarray]:
    """The model's weights as contiguous float64 arrays under their state_dict names."""
    return {k: np.ascontiguousarray(v.detach().cpu().to(dtype=__import__("torch").float64).numpy())
            for k, v in model.state_dict().items()}


def export(model_or_run, path, meta: dict | None = None) -> Path:
    """Write `model_or_run` (an ExoModel, an ExtendedModel, or a run directory) to `path`.

    `meta`: extra metadata (e.g. {"dt": 0.005, "train_data": "..."}); values that are not strings are
    JSON-encoded. A run directory contributes dt and `train_*` provenance itself.
    Returns the path. Raises ValueError for methods the engine cannot run (the black-box heads).
    """
    from safetensors.numpy import save_file

    extra: dict = {}
    model = model_or_run
    if isinstance(model_or_run, (str, Path)):
        from .train import load_run

        model, run_meta = load_run(model_or_run)
        extra["dt"] = repr(float(run_meta["dt"]))
        extra["train_run"] = str(Path(model_or_run).resolve())
        for k, v in (run_meta.get("config") or {}).items():
            if isinstance(v, (str, int, float, bool)) or v is None:
                extra[f"train_{k}"] = str(v)
        extra["train_epoch"] = str(run_meta.get("epoch"))
    extra.update(meta or {})
    base, ext, eps = _split_extended(model)
    if getattr(base, "delan", None) is None:
        raise ValueError(f"method {getattr(base, 'method', '?')!r} is a black box: the Rust engine runs the "
                         f"DeLaN-based methods {', '.join(DELAN_METHODS)}")
    tensors = state_tensors(base)
    for k, v in ext.items():
        if not k.startswith("ext."):
            raise ValueError(f"extension tensor {k!r} must be named ext.*")
        tensors[k] = np.ascontiguousarray(np.asarray(v, dtype=np.float64))
    md = _metadata(base, extra)
    if eps is not None:
        md["coulomb_eps"] = repr(eps)
    if "dt" in md and not isinstance(md["dt"], str):
        md["dt"] = repr(float(md["dt"]))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata=md)
    tmp.replace(path)
    return path


def cli_export(args) -> int:
    out = export(args.run, args.out)
    # load it back through the engine: an export that the engine rejects is a failed export
    from .engine import Engine

    eng = Engine(out)
    print(f"exported {args.run} -> {out} (method {eng.method}, lim {eng.lim}, encoder {eng.encoder}, "
          f"joints {eng.joint_names}, extensions {eng.extensions or 'none'})")
    return 0
