"""Big arrays kept in the process between uses: glibc's allocator told not to hand them back to the kernel.

A step on a large print allocates and frees arrays of hundreds of megabytes many times (the bunny's 10M waypoints:
20M material points, their sort orders, the scan's chunks). glibc serves every allocation above 32 MB with a fresh
``mmap`` and unmaps it on free, so each new array is faulted in page by page again: a third of the motion step's
time on the bunny was the kernel's (23 of 79 s). With ``mmap`` off for the heap and its top never trimmed, freed
arrays are reused by the next ones: the motion step 73 -> 62 s, its kernel time 23 -> 11 s, the peak memory 6 %
higher (5.7 -> 6.0 GB). The scan's threads keep arenas of their own (one arena for all: 69 s, the threads wait on
its lock). Between steps the freed memory goes back to the kernel (``release_freed_memory``, after every pipeline
step): kept for the whole run, the bunny's command held 11 GB at its peak, against 7.2 GB before.
"""
from __future__ import annotations

import ctypes
import os
from typing import Any

#: mallopt's parameters (malloc.h)
M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4
#: glibc's own settings of the same things in the environment: a user's choice stands
USER_SETTINGS = ("MALLOC_MMAP_MAX_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_",
                 "MALLOC_ARENA_MAX")


def _glibc(name: str) -> Any:
    """The C library's function ``name`` (None where it has none: musl, macOS, Windows)."""
    try:
        return getattr(ctypes.CDLL(None), name)
    except (OSError, AttributeError):
        return None


def keep_freed_memory() -> bool:
    """Large allocations from the heap and freed memory kept for reuse (glibc only; nothing where a ``MALLOC_*``
    setting of the user's is in the environment or ``NEURALSLICER_KEEP_FREED_MEMORY=0``); whether it was applied."""
    if os.environ.get("NEURALSLICER_KEEP_FREED_MEMORY", "1") == "0" or any(k in os.environ for k in USER_SETTINGS):
        return False
    mallopt = _glibc("mallopt")
    if mallopt is None:
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # -1: the heap's top is never trimmed (mallopt(3))
    return bool(mallopt(M_MMAP_MAX, 0) and mallopt(M_TRIM_THRESHOLD, -1))


def release_freed_memory() -> bool:
    """Hand the memory freed so far back to the kernel (glibc's ``malloc_trim``): between steps, so that a step reuses
    its own arrays and the next one starts from what is still held; whether anything was released."""
    trim = _glibc("malloc_trim")
    if trim is None:
        return False
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return bool(trim(0))
