"""One home for writing run directories: atomic files and JSON.

Every file is written to a temporary name in its destination folder and renamed into place (os.replace is
atomic on POSIX), so an interrupted run never leaves a half-written file behind. `jsonable` turns numpy
values and non-finite floats into plain JSON (NaN -> null, ±inf -> "inf" / "-inf"), so that every file
exolan writes is strict JSON that any reader accepts.
"""
from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _umask()


def atomic_write(path: str | os.PathLike, data: bytes | str) -> None:
    """Write `data` to `path` through a temporary file in the same folder, then rename it into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_UMASK)   # mkstemp makes 0600; results are shared files, like open() makes
        with os.fdopen(fd, "wb") as fh:
            fh.write(data.encode() if isinstance(data, str) else data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def atomic_torch_save(path: str | os.PathLike, obj: Any) -> None:
    """torch.save through a temporary file (a checkpoint is never half-written)."""
    import io

    import torch

    buf = io.BytesIO()
    torch.save(obj, buf)
    atomic_write(path, buf.getvalue())


def jsonable(x: Any) -> Any:
    """Plain JSON values: numpy scalars and arrays, tuples, Paths; NaN -> None, ±inf -> "inf" / "-inf"."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating, float)):
        f = float(x)
        if math.isfinite(f):
            return f
        return None if math.isnan(f) else ("inf" if f > 0 else "-inf")
    if isinstance(x, os.PathLike):
        return os.fspath(x)
    return x


def dumps(obj: Any, indent: int | None = 2) -> str:
    """Strict JSON text of `obj` (through `jsonable`), newline-terminated."""
    return json.dumps(jsonable(obj), indent=indent, allow_nan=False) + "\n"


def write_json(path: str | os.PathLike, obj: Any, indent: int | None = 2) -> None:
    atomic_write(path, dumps(obj, indent))


def write_jsonl(path: str | os.PathLike, rows: list) -> None:
    atomic_write(path, "".join(json.dumps(jsonable(r), allow_nan=False) + "\n" for r in rows))


CHECKPOINT = "checkpoint.pt"


def load_run(run_dir: str | os.PathLike, device: str = "cpu"):
    """A training run directory's model (eval mode, on `device`) and its meta dict (config, spec, norm, run,
    metrics, epoch, dt). The model classes are imported here, not at module level: writing JSON needs no torch."""
    import torch

    from .models import build_model

    rd = Path(run_dir)
    spec = json.loads((rd / "model.json").read_text())
    model = build_model(**spec)
    ck = torch.load(rd / CHECKPOINT, map_location="cpu", weights_only=False)
    model.load_state_dict(ck["model"])
    model.to(device).eval()
    meta = dict(config=json.loads((rd / "config.json").read_text()), spec=spec,
                norm=json.loads((rd / "norm.json").read_text()),
                run=json.loads((rd / "run.json").read_text()) if (rd / "run.json").exists() else {},
                metrics=ck["metrics"], epoch=ck["epoch"])
    meta["dt"] = meta["norm"]["dt"]
    return model, meta
