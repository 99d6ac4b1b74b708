"""Process settings that decide torch's CPU speed, applied when exolan is imported (before torch loads).

- OpenMP's wait policy: threads that spin while they wait collapse torch's multi-threaded speed on a shared
  machine (a training step 3.1x slower at 2 threads beside other work, docs/TRAINING.md). Read once, when torch
  loads, so it is set as an environment default.
- glibc's allocator: by default it gives freed blocks of a few MB back to the system and the next step faults
  them in again, page by page; a training step at batch 8192 then takes 25 % longer in two runs of three
  (2.3x the page faults; docs/TRAINING.md, "The allocator"). `mallopt` keeps them: blocks up to 32 MiB come
  from the heap, and free memory at its top is returned only beyond 1 GiB.

Either setting is left alone where the user made one (OMP_WAIT_POLICY; any MALLOC_* variable or a malloc tunable
in GLIBC_TUNABLES); EXOLAN_MALLOPT=0 turns the second off.
"""
from __future__ import annotations

import ctypes
import os
import sys

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3          # glibc's <malloc.h> parameter numbers
MMAP_THRESHOLD = 32 << 20                              # glibc's largest allowed value on 64-bit systems
TRIM_THRESHOLD = 1 << 30
# both settings as environment variables, for a process started without exolan (benches/bench_train.py's old tree)
ENVIRONMENT = {"OMP_WAIT_POLICY": "PASSIVE", "MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD),
               "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD)}


def keep_freed_memory() -> bool:
    """Set glibc's mmap and trim thresholds (above); True where they were set, False where skipped."""
    if os.environ.get("EXOLAN_MALLOPT", "1") == "0" or not sys.platform.startswith("linux"):
        return False
    if any(k.startswith("MALLOC_") for k in os.environ) or "malloc" in os.environ.get("GLIBC_TUNABLES", ""):
        return False                                   # the user tuned glibc's allocator already
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt     # glibc only (musl has no such library name)
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1 and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1


def apply() -> dict:
    """Both settings; what was done (shown by `exolan doctor`)."""
    os.environ.setdefault("OMP_WAIT_POLICY", ENVIRONMENT["OMP_WAIT_POLICY"])
    return {"omp_wait_policy": os.environ["OMP_WAIT_POLICY"], "malloc_keeps_freed_memory": keep_freed_memory()}
