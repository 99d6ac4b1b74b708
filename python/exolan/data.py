"""The dataset reader: layout 1 (exoskeleton, the simulated world and the published EPIC files) and
layout 2 (any N-joint recording), see ../shared/DATA_LAYOUT.md and docs/DESIGN.md section 1.

Python API::

    ds = load(path)                 # Dataset (list-like of Trial); layout detected
    split = paper_split(ds)         # Split(train, test_seen, test_unseen), each a Dataset
    x = context_features(trial)     # (T, C) encoder input, names: context_channels(trial)
    flat = stack(ds.trials)         # flat arrays + subject/task/trial indices

Conventions:
  * Layout 1: each recording gives two trials (sides l, r). Flexion is positive for both joints on
    both sides and CoP z is lateral for both feet, so both legs are samples of one model with no
    sign change ("mirroring" is a relabelling of the columns). A side without any valid sample
    (e.g. a leg that was not measured) is left out and listed in ``Dataset.skipped``.
  * Degrees -> radians; tau = moment x mass_kg + recorded exoskeleton torque (N m).
  * qdd = Savitzky-Golay derivative of the recorded velocities (as the paper):
    ``scipy.signal.savgol_filter(qd, window_length=savgol_window(dt), polyorder=SAVGOL_ORDER=3,
    deriv=1, delta=dt)``, applied to each contiguous finite stretch separately (stretches
    shorter than the window stay NaN): a cubic fit over SAVGOL_SECONDS = 55 ms (11 samples at
    200 Hz, the paper's window; the odd sample count nearest to 55 ms at other rates, at least 5),
    which passes gait content (< 15 Hz) and suppresses the noise that a plain difference would
    amplify. The window is fixed in time, not in samples: an 11-sample window on a 1 kHz bench
    recording is 11 ms, and a 14-bit encoder's quantisation then puts 16 % of q̈'s RMS into its
    error (0.6 % at 200 Hz; measured on a sum of sines, 0.2-3 Hz), an error in the regressor
    of the inertia that biases it.
  * Layout 2 without velocity columns: qd = the same Savitzky-Golay filter, derivative of q.
  * NaN stays NaN; ``valid`` marks samples where q, qd, qdd, tau and f_v are all finite.
  * Cache: the parsed dataset is pickled into the user's cache folder (`cache_dir`: ``$EXOLAN_CACHE_DIR``,
    else ``$XDG_CACHE_HOME/exolan`` or ``~/.cache/exolan`` on Linux), never into the data folder (which
    may be read-only, shared or under version control), keyed by a hash of the reader version, its
    settings and the content of every file read.
"""
from __future__ import annotations

import hashlib
import os
import pickle
import sys
from pathlib import Path

from .runio import atomic_write
from .recording import SAVGOL_ORDER, SAVGOL_SECONDS
from .layout1 import _layout1_files, _load_layout1
from .layout2 import read_layout2
from .dataset import DataError, Dataset
# the reader's API, importable from here as before the split (this module is its front door)
from .dataset import COP_FORCE_THRESHOLD, PAPER_TRAIN_TASKS, DataWarning, Split, Trial  # noqa: F401
from .dataset import context_channels, context_features, paper_split, stack, task_group  # noqa: F401
from .recording import GAP_FACTOR, SLOW_SAMPLE_TIME, finite_runs, savgol_derivative, savgol_window  # noqa: F401
from .layout1 import JOINTS, SIDES, read_subjects, read_trial_dir  # noqa: F401

READER_VERSION = "2"


# --------------------------------------------------------------------------------------------
# cache and the public loader

def cache_dir() -> Path:
    """The reader's cache folder: $EXOLAN_CACHE_DIR, else the platform's per-user cache folder
    ($XDG_CACHE_HOME/exolan or ~/.cache/exolan on Linux, ~/Library/Caches/exolan on macOS,
    %LOCALAPPDATA%/exolan/Cache on Windows). The data folder itself never receives a file."""
    env = os.environ.get("EXOLAN_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    if sys.platform == "win32" and os.environ.get("LOCALAPPDATA"):
        return Path(os.environ["LOCALAPPDATA"]) / "exolan" / "Cache"
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches" / "exolan"
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    # the XDG spec: a relative path in the variable is invalid and is ignored
    return (Path(xdg) if os.path.isabs(xdg) else Path.home() / ".cache") / "exolan"


def _input_files(path: Path) -> tuple[int, Path, list]:
    """(layout, root, files) of what load(path) reads."""
    if path.is_file():
        if path.suffix == ".csv":
            if not path.with_suffix(".json").exists():
                raise DataError(f"{path.with_suffix('.json')}: missing file (layout 2 needs <name>.json)")
            return 2, path.parent, [path, path.with_suffix(".json")]
        if path.name == "subjects.csv":
            path = path.parent
        else:
            raise DataError(f"{path}: not a dataset (expected a layout-1 root or a layout-2 <name>.csv)")
    if not path.exists():
        raise DataError(f"{path}: no such file or directory")
    if (path / "subjects.csv").exists():
        files = [path / "subjects.csv"]
        for _, td in _layout1_files(path):
            files += [td / "Exo.csv", td / "Joint_Moments_Filt.csv"]
        return 1, path, files
    pairs = sorted(p for p in path.glob("*.csv") if p.with_suffix(".json").exists())
    if pairs:
        return 2, path, [f for p in pairs for f in (p, p.with_suffix(".json"))]
    if _layout1_files(path):
        raise DataError(f"{path / 'subjects.csv'}: missing file (layout 1 needs subject masses)")
    raise DataError(f"{path}: no dataset found (layout 1: subjects.csv + <SUBJECT>/<trial>/Exo.csv; "
                    f"layout 2: <name>.csv + <name>.json)")


def load(path, cache: bool = True) -> Dataset:
    """Read a dataset (layout detected); repeated loads of unchanged files come from the cache."""
    path = Path(path).expanduser().resolve()
    layout, root, files = _input_files(path)
    contents = {}
    h = hashlib.blake2b(digest_size=20)
    h.update(f"exolan-reader {READER_VERSION} layout {layout} sg {SAVGOL_SECONDS} s {SAVGOL_ORDER}".encode())
    for f in files:
        try:
            b = f.read_bytes()
        except OSError as exc:
            raise DataError(f"{f}: cannot read ({exc})") from exc
        contents[f] = b
        h.update(str(f.relative_to(root)).encode() + b"\0" + hashlib.blake2b(b, digest_size=20).digest())
    key = h.hexdigest()
    cdir = cache_dir() if cache else None
    cfile = cdir / f"dataset-{key}.pkl" if cdir else None
    if cfile is not None and cfile.exists():
        try:
            with open(cfile, "rb") as fh:
                ds = pickle.load(fh)
            ds.root = str(path if layout == 1 else root)
            return ds
        except Exception:  # a corrupt cache entry is rebuilt, never trusted
            pass
    if layout == 1:
        ds = _load_layout1(root, contents)
    else:
        trials = []
        for f in files[::2]:
            trials.append(read_layout2(f, contents[f], contents[f.with_suffix(".json")]))
        ds = Dataset(trials, str(root), 2, {t.subject: 1.0 for t in trials}, {}, [])
    if cfile is not None:
        try:
            atomic_write(cfile, pickle.dumps(ds, protocol=5))
        except OSError:
            pass  # no writable cache: loading still works
    return ds


def real_data_path() -> Path:
    """The real recordings (../shared/real relative to the repository, or $EXOLAN_REAL_DATA)."""
    env = os.environ.get("EXOLAN_REAL_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2].parent / "shared" / "real"
