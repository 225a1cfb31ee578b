"""Pauses of Python's cyclic garbage collector while jaxfit makes many long-lived objects
at once (a program's tracing and lowering), shared by every thread."""

from __future__ import annotations

import contextlib
import gc
import threading

_pause = {"holders": 0, "was_enabled": False}
_lock = threading.Lock()


@contextlib.contextmanager
def paused():
    """Within it, the cyclic collector does not run; it is back as it was before once the
    last such block, in any thread, has ended (a collector the user turned off stays
    off). Why: objects that survive set off full collections of every object the process
    holds, with the GIL held: 0.03-0.05 s of a cold first fit's ~1 s (docs/engine.md,
    "Session 26"). The cycles made meanwhile are collected after."""
    with _lock:
        if _pause["holders"] == 0:
            _pause["was_enabled"] = gc.isenabled()
            gc.disable()
        _pause["holders"] += 1
    try:
        yield
    finally:
        with _lock:
            _pause["holders"] -= 1
            if _pause["holders"] == 0 and _pause["was_enabled"]:
                gc.enable()
