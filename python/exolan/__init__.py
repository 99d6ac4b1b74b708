"""exolan: physics-consistent, context-aware learned dynamics of the human-exoskeleton leg.

The learning side (torch) lives in this package; the fast engine is the Rust extension
``exolan._native``.
"""
from importlib.metadata import PackageNotFoundError, version as _dist_version

from . import runtime as _runtime

RUNTIME = _runtime.apply()  # before torch loads: OpenMP's wait policy and glibc's allocator (runtime.py)

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
