"""glibc's malloc kept from handing a fit's freed host arrays back to the system and
mapping them again on the next fit.

A fit of 1e5 points makes dozens of NumPy temporaries of ~0.8 MB. Under glibc's default
(dynamic) thresholds the heap is trimmed as soon as more than twice the largest of them
lies free at its top, and arrays above the mmap threshold are mapped one by one: every
fit then faults its memory in afresh (a plane of 1e5 points: ~1,300 page faults a fit;
docs/engine.md, "Session 36").
"""

from __future__ import annotations

import ctypes
import os
import sys
import warnings

from ._cache import OFF_VALUES

#: mallopt's parameters (glibc's malloc.h).
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3
#: Memory kept past the heap's top when it shrinks (and added when it grows): a large
#: fit's temporaries stay mapped from one fit to the next.
TOP_PAD = 64 << 20
#: Allocations from this size up are mapped on their own; glibc's dynamic threshold
#: rises to this same ceiling (DEFAULT_MMAP_THRESHOLD_MAX on 64-bit), but only after a
#: first such array is freed, and setting the top pad alone would freeze it low.
MMAP_THRESHOLD = 32 << 20
#: Set to "0" (or "false", "no", "off", as ``JAXFIT_CACHE``) to leave the process's
#: malloc settings as they are; "1", "true", "yes", "on" or unset: set them.
ENVIRONMENT = "JAXFIT_MALLOC"
ON_VALUES = frozenset({"", "1", "true", "yes", "on"})

applied: bool | None = None  # (set once, by ``keep_freed_memory``)


def keep_freed_memory() -> bool:
    """Sets glibc's top pad (``TOP_PAD``) and mmap threshold (``MMAP_THRESHOLD``) for the
    process, once; returns whether both were set. Nothing is done outside glibc (macOS,
    Windows, musl), or with ``JAXFIT_MALLOC=0``; another value than those of
    ``ENVIRONMENT`` warns. The cost: up to ``TOP_PAD`` of freed
    memory per malloc arena stays with the process instead of going back to the system."""
    global applied
    if applied is not None:
        return applied
    applied = False
    value = os.environ.get(ENVIRONMENT, "").strip().lower()
    if value in OFF_VALUES:
        return applied
    if value not in ON_VALUES:
        warnings.warn(f"jaxfit: {ENVIRONMENT}={os.environ[ENVIRONMENT]!r} is not understood "
                      f"(0 to leave malloc as it is, 1 to set it); setting it",
                      RuntimeWarning, stacklevel=2)
    if not sys.platform.startswith("linux"):
        return applied
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return applied
    if not hasattr(libc, "gnu_get_libc_version"):  # (musl's mallopt ignores these)
        return applied
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    applied = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
        mallopt(M_TOP_PAD, TOP_PAD))
    return applied
