"""exolan: physics-consistent, context-aware learned dynamics of the human-exoskeleton leg.

The learning side (torch) lives in this package; the fast engine is the Rust extension
``exolan._native``.
"""
import os as _os
from importlib.metadata import PackageNotFoundError, version as _dist_version

# OpenMP threads that spin while they wait collapse torch's multi-threaded speed on a shared machine (measured: a
# training step 3.1x slower at 2 threads beside other work, docs/TRAINING.md); read once, when torch loads.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

try:
    __version__ = _dist_version("exolan")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"

try:
    from . import _native
    native_version = _native.__version__
except ImportError:  # the extension is not built; `exolan doctor` says so
    _native = None
    native_version = None

from .engine import Engine, fast_rollout  # numpy + the extension only (no torch)

__all__ = ["__version__", "native_version", "Engine", "fast_rollout"]
