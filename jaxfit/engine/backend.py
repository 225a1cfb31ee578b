"""Where the engine meets the device: every ``jax.default_backend()`` switch, the CPU
compiler options, and how per-cloud arrays are spread over the local devices.

The same code runs on a CPU and a GPU; only the choices here differ (measurements of
each: docs/engine.md).
"""

from __future__ import annotations

import concurrent.futures
import functools
import os
import threading
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from .._cache import stored_jit


def cores() -> int:
    """The cores this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


#: LLVM modules a program's code generation is split into, compiled in parallel: one a
#: core (at least 2). XLA's default, 32, took longer and more CPU on 2 cores, at the same
#: run time (docs/engine.md, "Session 34").
CODEGEN_SPLIT = {"xla_cpu_parallel_codegen_split_count": max(2, cores())}
#: XLA's older loop emitters in place of its MLIR fusion emitters: the kernel and the
#: refinement compile in about 0.5-0.65 of the time and run as fast (docs/engine.md,
#: "Session 24"), and a first fit's time is mostly their compiles.
LOOP_EMITTERS = {"xla_cpu_use_fusion_emitters": False}
#: Per-function XLA CPU options for the scoring kernel (PERF.md), passed to ``jax.jit``
#: so users' ``XLA_FLAGS`` stay untouched; a jax that refuses one gets the defaults.
CPU_OPTIONS = {
    "xla_cpu_experimental_ynn_fusion_type": "",
    "xla_cpu_prefer_vector_width": 512,
    "xla_cpu_enable_fast_min_max": True,
    **LOOP_EMITTERS,
    **CODEGEN_SPLIT,
}
#: The kernel's options where its refinement compiles beside it (a fit with LO): code
#: generation not split over the cores, which the two compiles already keep busy. A
#: kernel compiled alone (``polish``, detect's candidates) keeps the split, which lets its
#: one compile use both cores (docs/engine.md, "Session 27").
BESIDE_OPTIONS = {**CPU_OPTIONS, "xla_cpu_parallel_codegen_split_count": 1}
#: The refinement's XLA CPU options.
REFINE_OPTIONS = {**LOOP_EMITTERS, **CODEGEN_SPLIT}
#: On the CPU the scoring kernel splits H hypotheses into this many independent loops
#: when each gets at least BLOCK_MIN of them: XLA's CPU runtime runs independent loops
#: side by side, but splits one loop's body over the cores only when it is large.
HYPOTHESIS_BLOCKS = 2
BLOCK_MIN = 256


def map_leading(fn, args, batch_size: int | None = None):
    """``jax.lax.map(fn, args, batch_size=batch_size)`` over the leading (C,) axis of the
    pytree ``args`` (None leaves pass through), without the loop where it would take one
    step: for C = 1 ``fn`` called on the one row, for C = batch_size its ``vmap``. A
    single fit's program then has no scan and no batching over clouds to trace, lower
    and compile, and a call of a few clouds no scan."""
    count = jax.tree.leaves(args)[0].shape[0]
    if count == 1:
        out = fn(jax.tree.map(lambda a: a[0], args))
        return jax.tree.map(lambda a: a[None], out)
    if count == batch_size:
        return jax.vmap(fn)(args)
    return jax.lax.map(fn, args, batch_size=batch_size)


def batched_like(tree, ref):
    """The arrays of ``tree`` unchanged in value, each made to depend on the array
    ``ref`` (a select between two copies of itself, which XLA removes), so that under
    ``vmap`` a loop carry built from constants is batched from the start wherever ref
    is. Why: a while_loop's batching rule traces its body again each time it finds
    another carry batched, and once more after, at every level of nesting."""
    same = jnp.ravel(ref)[0] == jnp.ravel(ref)[0]
    return jax.tree.map(lambda a: jnp.where(same, a, a), tree)


def on_cpu() -> bool:
    """Whether the engine runs on the CPU backend."""
    return jax.default_backend() == "cpu"


def hypothesis_blocks(hypotheses: int) -> int:
    """Independent scoring loops for H hypotheses (1 off the CPU)."""
    if not on_cpu() or hypotheses % HYPOTHESIS_BLOCKS:
        return 1
    return HYPOTHESIS_BLOCKS if hypotheses >= BLOCK_MIN * HYPOTHESIS_BLOCKS else 1


def jit_tuned(fn, static_argnames=(), options=None):
    """``stored_jit`` with the XLA CPU ``options`` (default CPU_OPTIONS) on the CPU, and
    without them where they are refused (one ``RuntimeWarning``, then the defaults for
    the rest of the process)."""
    plain = stored_jit(fn, static_argnames)
    if not on_cpu():
        return plain
    tuned = stored_jit(fn, static_argnames, CPU_OPTIONS if options is None else options)
    state = {"tuned": True}

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if state["tuned"]:
            try:
                return tuned(*args, **kwargs)
            except Exception as err:  # an unknown or changed XLA option
                if "option" not in str(err).lower():
                    raise
                state["tuned"] = False
                warnings.warn(f"jaxfit: XLA CPU options refused ({err}); using defaults",
                              RuntimeWarning, stacklevel=2)
        return plain(*args, **kwargs)

    return call


def slots(count: int, devices: int) -> int:
    """Rows of the per-cloud arrays for ``count`` clouds: a power of two (fewer
    compilations) and a multiple of the device count."""
    rows = max(1 << (count - 1).bit_length(), devices)
    return -(-rows // devices) * devices


def placer(devices):
    """How the host loop puts per-cloud arrays (clouds first) on the devices: split along
    the cloud axis over all local devices (GPUs, or CPU devices forced with
    ``--xla_force_host_platform_device_count``), so every jitted call runs on all of
    them; on one device, plain arrays (jit takes NumPy arrays on its fast path)."""
    if len(devices) == 1:
        return lambda array: array
    mesh = jax.sharding.Mesh(np.asarray(devices), ("clouds",))
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("clouds"))
    return lambda array: jax.device_put(array, sharding)


#: The thread pools of ``in_threads``, one per worker count, kept for the process: each
#: call starting threads of its own had them start with fresh malloc arenas, whose memory
#: glibc maps and faults in again (a 1000 x 500-point ``fit_batch`` took 4,000-12,000
#: page faults and ~30 % more time in its first ~8 calls; docs/engine.md, "Session 41").
_pools: dict[int, concurrent.futures.ThreadPoolExecutor] = {}
_pools_lock = threading.Lock()
_worker = threading.local()  # .busy: this thread is one of the pools'


def thread_pool(workers: int) -> concurrent.futures.ThreadPoolExecutor:
    """The process's pool of ``workers`` threads (made on first use; a forked child makes
    its own: the parent's threads do not exist there)."""
    with _pools_lock:
        pool = _pools.get(workers)
        if pool is None:
            pool = _pools[workers] = concurrent.futures.ThreadPoolExecutor(
                workers, thread_name_prefix="jaxfit", initializer=_mark_worker)
        return pool


def _mark_worker():
    _worker.busy = True


def _in_a_pool() -> bool:
    """Whether this thread is one of the pools' (then their calls run in it)."""
    return getattr(_worker, "busy", False)


def _forget_pools():
    """In a forked child: no pools (their threads stayed in the parent) and a fresh lock
    (the parent's may have been held by another thread at the fork)."""
    global _pools_lock
    _pools.clear()
    _pools_lock = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pools)


def submitted(fn) -> concurrent.futures.Future:
    """fn() started in a thread of ``thread_pool(1)``, to be read by ``.result()``; run
    here and now where this thread is one of the pools' (as ``in_threads``)."""
    if not _in_a_pool():
        return thread_pool(1).submit(fn)
    future = concurrent.futures.Future()
    try:
        future.set_result(fn())
    except Exception as err:  # (raised by .result(), as from a thread)
        future.set_exception(err)
    return future


def in_threads(fn, items, workers: int, ordered: bool = True):
    """(item, fn(item)) for each of items, in their order (or, not ``ordered``, as the
    calls finish), ``workers`` calls at a time in the threads of ``thread_pool`` (JAX's
    calls and XLA's compiler release the GIL); the caller may stop early: the calls not
    yet started are dropped, and those running are waited for. Called from one of the
    pools' threads, the calls run in it, one after another (a pool's thread waiting on
    its own pool could wait for ever)."""
    if _in_a_pool():
        yield from ((item, fn(item)) for item in items)
        return
    pool = thread_pool(workers)
    pending = [pool.submit(fn, item) for item in items]
    of = dict(zip(pending, items, strict=True))
    try:
        for future in (pending if ordered else concurrent.futures.as_completed(pending)):
            yield of[future], future.result()
    finally:
        for future in pending:
            future.cancel()
        concurrent.futures.wait(pending)
