"""The host loop: batches of hypotheses for all clouds of a call in lockstep, each cloud
with its own best model and stopping state (optimistix's one loop for every solver:
init, then step -> refine -> terminate per batch). The clouds of a call are first split
into groups of similar point buckets (``call_groups``), one padded loop each.
"""

from __future__ import annotations

import threading

import jax
import numpy as np

from .. import _checks
from .._cache import after_export
from ..shapes import Model
from .backend import cores, in_threads, on_cpu, placer, slots
from .cloud import Cloud, bucket_size
from .kernel import batch_best_many, refine_many
from .keys import THREEFRY, cloud_keys, keys_at, seed_cloud_keys, seed_keys_at
from .options import Bounds, FitOptions
from .refine import lo_rows
from .stopping import Status

#: Clouds of different point buckets share one padded loop while its padded points
#: (slots x bucket) stay within SHARE_FACTOR times those of one loop per bucket, or
#: within SHARE_POINTS (docs/engine.md, "Grouping clouds by bucket").
SHARE_FACTOR = 2
SHARE_POINTS = 1 << 16
#: Whether a group's first refinement is compiled in a thread while the kernel compiles
#: (XLA's compilation releases the GIL; docs/engine.md, "Compile cost").
COMPILE_AHEAD = True

#: On the CPU (one device) a group of many clouds is searched in parts of at most
#: PART_CLOUDS clouds (and at least PART_LEAST, where it is cut to give every core one),
#: one part per core at once in threads: for clouds of a few hundred points XLA's CPU
#: runtime keeps a second core busy only part of a call (the refinement of 1000 such
#: clouds ran faster on one core than on two), while independent calls run side by side,
#: and the caller turns finished parts into results meanwhile (docs/engine.md,
#: "Session 23").
PART_CLOUDS = 256
PART_LEAST = 128

_ahead: set = set()  # the refinement calls compiled ahead in this process


def refine_ahead(cls: type[Model], options: FitOptions, arrays: dict, rows: int, dtype,
                 gated: bool, put=lambda a: a):
    """A thread (not started) that calls ``refine_many`` once on hypotheses of the
    kernel's output shapes (zeros, costs +inf) with the group's per-slot ``arrays``, so
    that its program is traced and compiled while the main thread compiles the kernel;
    None when refinement is off or a call of this signature was already made in this
    process (then it is compiled, or being compiled, already). Start it once the
    kernel's program is traced and lowered (``_cache.after_export``: the two tracings
    would share the GIL, and a cold first fit waits on the kernel's), and join it before
    the first real refinement: that call then finds the program ready."""
    if not (options.refine and COMPILE_AHEAD):
        return None
    slots_count, size = arrays["points"].shape[:2]
    signature = (cls, slots_count, size, np.dtype(dtype).name, rows, gated, options.refiner,
                 options.scorer, len(jax.local_devices()))
    if signature in _ahead:
        return None
    _ahead.add(signature)
    # Device arrays as the kernel returns them: a NumPy argument keys another stored
    # program, and an array committed to a device (or not) another jitted executable.
    # The kernel's outputs are committed exactly when its keys are (a stored program's
    # outputs are, and so are the keys it makes). (device_put, not jnp.zeros, which
    # compiles a program of its own.)
    device = jax.local_devices()[0] if getattr(arrays["keys"], "committed", False) else None
    theta = put(jax.device_put(np.zeros((slots_count, cls.lo_starts, cls.num_params), dtype),
                               device))
    cost = put(jax.device_put(np.full((slots_count, cls.lo_starts), np.inf, dtype), device))

    def compile_refinement():
        try:
            refine_many(cls, theta, cost, arrays["points"], arrays["n"],
                        arrays["threshold"], arrays["bounds"],
                        arrays["normals"] if gated else None, rows, options.refiner,
                        options.scorer)
        except Exception:  # (the real call raises it, in the caller's thread)
            _ahead.discard(signature)

    return threading.Thread(target=compile_refinement, name="jaxfit-refine-ahead",
                            daemon=True)


def call_groups(sizes, devices: int = 1) -> list[list[int]]:
    """The clouds (indices into ``sizes``, each cloud's point count) of each padded loop,
    in their order of the call, groups by increasing bucket.

    The clouds are sorted by ``bucket_size``, one group per bucket; going up the buckets,
    the next is merged into the last group while the merged loop's padded points
    ``slots(count, devices) * bucket`` stay within ``SHARE_FACTOR`` times the sum of its
    buckets' own loops, or within ``SHARE_POINTS``. Memory is then bounded by what the
    clouds need (tiny clouds are never padded to a big one's bucket), and clouds of
    similar sizes still share one loop (one host loop, one compiled shape)."""
    by_bucket: dict[int, list[int]] = {}
    for i, n in enumerate(sizes):
        by_bucket.setdefault(bucket_size(n), []).append(i)
    groups: list[tuple[list[int], int]] = []  # (clouds, padded points of separate loops)
    for bucket in sorted(by_bucket):
        clouds = by_bucket[bucket]
        alone = slots(len(clouds), devices) * bucket
        if groups:
            merged, separate = groups[-1][0] + clouds, groups[-1][1] + alone
            if slots(len(merged), devices) * bucket <= max(SHARE_FACTOR * separate,
                                                           SHARE_POINTS):
                groups[-1] = (merged, separate)
                continue
        groups.append((clouds, alone))
    return [sorted(clouds) for clouds, _ in groups]


def subset_rows(mask: np.ndarray, multiple: int = 1):
    """The rows a batched call runs on for the slots where mask (S,) holds: None (all S
    slots) or those slots, padded by repeating the first, to the smallest of S / 16,
    S / 256, ... (a multiple of ``multiple``, the device count) that holds them. A few
    hard clouds among many easy ones then do not keep every cloud's kernel and
    refinement running, and at most a few more sizes compile."""
    live = np.flatnonzero(mask)
    size = len(mask)
    while (size >> 4) >= max(len(live), 1) and (size >> 4) % multiple == 0:
        size >>= 4
    if size == len(mask):
        return None
    return np.concatenate([live, np.full(size - len(live), live[0])])


def _keys(key, seed, which, count: int, rows_count: int, slots_of=None):
    """The (rows_count,) keys of the slots, or with ``slots_of`` (S,) those of its slots:
    fold_in(key, index in the call) for each cloud, and padding slots fold_in(key, slot)
    when the clouds are the call's first ones (one cached dispatch), else the first
    cloud's key. A subset is made as the whole is, never by indexing the keys: a JAX key
    array indexed on the host is a chain of eager operations, each compiled in every
    process (~0.15 s of a first ``fit_batch`` whose hard clouds go on) and ~8 ms a call
    after (docs/engine.md, "Session 41")."""
    impl = jax.config.jax_default_prng_impl
    first = which is None or list(which) == list(range(count))
    if first and slots_of is None:
        return (cloud_keys(key, rows_count) if seed is None
                else seed_cloud_keys(seed, impl, rows_count))
    indices = list(range(rows_count)) if first else \
        [int(i) for i in which] + [int(which[0])] * (rows_count - count)
    if slots_of is not None:
        indices = [indices[s] for s in np.asarray(slots_of).tolist()]
    if seed is not None and impl == THREEFRY:
        return seed_keys_at(seed, tuple(indices))
    return keys_at(key if seed is None else _checks.prng_key(seed), indices)


def parts(sizes, groups, cores: int = 1) -> list[tuple[list[int], int, int | None]]:
    """(clouds, bucket, slots) of each ``search_group`` of a call whose clouds have
    ``sizes`` points and form ``groups`` (``call_groups``; clouds as indices into sizes):
    each group padded to its largest cloud's bucket, and cut into near-equal runs of at
    most PART_CLOUDS clouds, or into ``cores`` runs of at least PART_LEAST where it has
    that many; the runs of a group padded to its bucket and to one slot count (one
    program), so that a cloud's result does not depend on the cut. slots None: the
    group's own (it is not cut). ``cores`` 0: no group is cut."""
    out = []
    for group in groups:
        bucket = bucket_size(max(sizes[i] for i in group))
        pieces = 0 if not cores else max(-(-len(group) // PART_CLOUDS),
                                         min(cores, len(group) // PART_LEAST))
        if pieces <= 1:
            out.append((group, bucket, None))
            continue
        rows = slots(-(-len(group) // pieces), 1)
        out.extend((run.tolist(), bucket, rows)
                   for run in np.array_split(np.asarray(group), pieces))
    return out


def searches(cls: type[Model], options: FitOptions, clouds: list[Cloud], key, seed,
             which=None, start: bool = False, separate: bool = False):
    """The search of the prepared clouds with the checked ``options``, one
    ``search_group`` per part of ``parts``: returns ``run(lowered=None)``, a
    generator of (part, (theta, drawn, status)) for each part, in the parts' order or,
    where they run in threads, as they finish: the part's clouds
    (indices into ``clouds``), the best theta (C, P) of each (NaN where none was valid;
    with ``options.polish`` the best batch's ``cls.lo_starts`` best (C, S, P), NaN where
    invalid, for ``refine.host_lo`` to refine each), hypotheses drawn (C,) and the Status
    (C,) of each. ``key`` is the call's JAX key, or None with the int ``seed`` it stands
    for; ``which``: each cloud's index in the call (its key is fold_in(key, index);
    default 0, 1, ...). ``lowered``: the options with a lower ``max_hypotheses``
    (``lower``; the first batch does not depend on them). With ``separate``, every cloud
    is a group of its own, padded as the largest cloud (``fit_batch``'s ``separate``).

    Where a group was cut (on the CPU, one device), the parts run one per core at once
    in threads, and the next ones go on while the caller works on the one it was given
    (the first to finish: a part whose hard clouds take more batches holds up no other);
    else one after another in the caller's thread, and with ``start`` each part's first
    batch is dispatched now (``Search``), before ``run`` is called.
    """
    which = list(range(len(clouds))) if which is None else list(which)
    devices = len(jax.local_devices())
    sizes = [c.points.shape[0] for c in clouds]
    groups = [[i] for i in range(len(clouds))] if separate else call_groups(sizes, devices)
    count = cores() if devices == 1 and on_cpu() else 0  # (a GPU takes a group whole)
    todo = parts(sizes, groups, count)
    cut = len(todo) > len(groups)
    reach = max(sizes) if separate else None

    def arguments(part, lowered):
        clouds_of, bucket, rows = part
        return (cls, lowered, [clouds[j] for j in clouds_of], key, seed,
                [which[j] for j in clouds_of], bucket if reach is None else None, rows, reach)

    started = [Search(*arguments(part, options)) for part in todo] if start and not cut \
        else None

    def run(lowered: FitOptions | None = None):
        lowered = options if lowered is None else lowered
        if cut:
            yield from ((part[0], found) for part, found in in_threads(
                lambda part: search_group(*arguments(part, lowered)), todo,
                min(len(todo), count), ordered=False))
            return
        for k, part in enumerate(todo):
            yield part[0], (started[k].result(lowered) if started is not None
                            else search_group(*arguments(part, lowered)))

    return run


def lower(options: FitOptions, cls: type[Model], max_hypotheses: int) -> FitOptions:
    """The checked ``options`` with ``max_hypotheses`` instead of their own."""
    return FitOptions.build(options, max_hypotheses=max_hypotheses).check(cls)


class Search:
    """One ``search_group`` in two steps: made, it dispatches the first batch (its
    kernel, and with LO its first refinement) and returns; ``result`` reads them and runs
    the rest. A caller can so dispatch several searches' first batches at once and
    finish them in turn, the device running the later ones while the host works on the
    earlier (``detect``'s shapes of a round)."""

    def __init__(self, *args):
        self._steps = _search_steps(*args)
        self._found = None
        try:
            next(self._steps)
        except StopIteration as stop:  # (no batch to run)
            self._found = stop.value

    def result(self, lowered: FitOptions | None = None):
        """``search_group``'s (theta, drawn, status); ``lowered``: the search's options
        with fewer ``max_hypotheses`` (``lower``; the first batch does not depend on
        them), made once by the caller for all of a call's searches."""
        if self._found is None:
            try:
                self._steps.send(lowered)
            except StopIteration as stop:
                self._found = stop.value
            else:  # pragma: no cover - _search_steps yields once
                raise RuntimeError("a search yields once")
        return self._found


def search_group(cls: type[Model], options: FitOptions, clouds: list[Cloud], key, seed,
                 which=None, size: int | None = None, rows: int | None = None,
                 reach: int | None = None):
    """The search of clouds that share one loop (as ``searches`` gives it for a part),
    padded to ``size`` points (a bucket; default the largest cloud's) and ``rows``
    slots (default ``backend.slots`` of the clouds); with ``reach``, padded (bucket and
    LO's rows) as if the largest cloud had that many points."""
    return Search(cls, options, clouds, key, seed, which, size, rows, reach).result()


def _search_steps(cls: type[Model], options: FitOptions, clouds: list[Cloud], key, seed,
                  which=None, size: int | None = None, rows: int | None = None,
                  reach: int | None = None):
    """``search_group`` as a generator for ``Search``: it yields once, after dispatching
    the first batch, and takes options with a lower ``max_hypotheses`` (or None) there; it
    returns the search's (theta, drawn, status)."""
    est = cls.estimator(options.estimator)
    count = len(clouds)
    devices = jax.local_devices()
    rows_count = slots(count, len(devices)) if rows is None else rows
    n_max = max([c.points.shape[0] for c in clouds] + [reach or 0])
    size = bucket_size(n_max) if size is None else size
    dtype = jax.dtypes.canonicalize_dtype(np.float64)  # float32 unless x64 is on
    order = list(range(count)) + [0] * (rows_count - count)  # padding slots repeat cloud 0
    put = placer(devices)
    built = [cloud.kernel_rows() for cloud in clouds]  # padding slots reuse cloud 0's
    gated = clouds[0].gated  # one normal_angle for all clouds of a call
    host = {  # per-slot arrays, clouds first
        "points": stacked([unit for unit, _, _ in built], rows_count, dtype, size),
        "normals": (stacked([nrm for _, nrm, _ in built], rows_count, dtype, size)
                    if est.uses_normals or gated else None),
        "n": np.asarray([clouds[i].points.shape[0] for i in order], np.int32),
        "n_sample": np.asarray([built[i][2] for i in order], np.int32),
        "keys": _keys(key, seed, which, count, rows_count),
        "threshold": np.asarray([clouds[i].threshold / clouds[i].scale for i in order], dtype),
        "bounds": unit_bounds([clouds[i] for i in order], dtype),
    }
    every = host if len(devices) == 1 else jax.tree.map(put, host)
    ahead = refine_ahead(cls, options, every, lo_rows(n_max), dtype, gated, put)

    def on(slots_of):
        """The per-slot arrays for the rows ``slots_of`` (None: every slot), placed."""
        if slots_of is None:
            return every
        rows = jax.tree.map(lambda a: put(a[slots_of]),
                            {name: a for name, a in host.items() if name != "keys"})
        return {**rows, "keys": put(_keys(key, seed, which, count, rows_count, slots_of))}

    def lo(theta, cost, arrays):  # LO of the kernel's best (theta, cost) on those slots
        return refine_many(cls, theta, cost, arrays["points"], arrays["n"],
                           arrays["threshold"], arrays["bounds"],
                           arrays["normals"] if gated else None, lo_rows(n_max),
                           options.refiner, options.scorer)

    starts = (cls.lo_starts,) if options.polish else ()  # (the kept starts of a best batch)
    best_theta = np.full((rows_count,) + starts + (cls.num_params,), np.nan)
    best_cost, best_raw = np.full(rows_count, np.inf), np.full(rows_count, np.inf)
    best_count = np.zeros(rows_count)
    last_improvement = np.zeros(rows_count, int)
    drawn = np.zeros(rows_count, int)
    status = np.array([Status.MAX_HYPOTHESES] * rows_count, dtype=object)
    active = np.arange(rows_count) < count
    batch, batch_size = 0, options.batch_size
    while active.any() and batch * batch_size < options.max_hypotheses:
        searching = subset_rows(active, len(devices))
        a = on(searching)
        # (the refinement's thread starts once the kernel is traced and lowered)
        with after_export(None if ahead is None else ahead.start):
            theta, cost, found, _ = batch_best_many(
                cls, batch_size, est.name, a["points"], a["normals"], a["n"],
                a["n_sample"], a["keys"], a["threshold"], a["bounds"], batch, gated,
                options.sampler, options.scorer, beside_refinement=options.refine)
        if ahead is not None:  # the first refinement's program, compiled meanwhile
            ahead.join()
            ahead = None
        where = np.arange(rows_count) if searching is None else searching  # slot of each row
        early = None
        if options.refine and batch == 0 and searching is None:
            # The first batch improves every slot whose kernel found a valid hypothesis:
            # its refinement is dispatched before the kernel's costs are read, so that it
            # runs straight after the kernel (one wait on the device, not two); it is
            # dropped below where the slots to refine turn out otherwise.
            early = lo(theta, cost, a)
        if batch == 0:  # (``Search``'s first step ends here: the batch dispatched, not read)
            lowered = yield
            if lowered is not None:
                options = lowered
        batch += 1
        drawn[active] = batch * batch_size
        # LO-RANSAC: polish every so-far-best raw hypothesis (compared with raw ones only,
        # so a rough but right one is not hidden behind a polished wrong one).
        raw = np.full(rows_count, np.inf)
        raw[where] = np.asarray(cost, np.float64)[:, 0]  # (sliced on the host: see below)
        improved = active & (raw < best_raw)
        best_raw = np.where(improved, raw, best_raw)
        if options.refine and improved.any():
            polishing = subset_rows(improved, len(devices))
            if polishing is not None:  # (else every slot: the kernel ran on all of them)
                row = np.full(rows_count, -1)
                row[where[::-1]] = np.arange(len(where))[::-1]  # first row of each slot
                theta, cost = (put(np.asarray(x)[row[polishing]]) for x in (theta, cost))
                a = on(polishing)
            theta, cost, found = (early if early is not None and polishing is None
                                  else lo(theta, cost, a))
            where = np.arange(rows_count) if polishing is None else polishing
        else:
            # (indexing on the host: a JAX slice per array cost ~0.2 ms each)
            theta, cost, found = (np.asarray(x) for x in (theta, cost, found))
            # (with polish every start, an invalid one (cost +inf) as NaN)
            theta = (np.where(np.isfinite(cost)[..., None], theta, np.nan) if starts
                     else theta[:, 0])
            cost, found = cost[:, 0], found[:, 0]
        full = (np.full(best_theta.shape, np.nan), np.full(rows_count, np.inf),
                np.zeros(rows_count))
        for out, value in zip(full, (theta, cost, found), strict=True):
            out[where] = np.asarray(value)
        theta, cost, found = full
        better = improved & (cost < best_cost)
        best_theta[better], best_cost[better] = theta[better], cost[better]
        best_count[better] = found[better]
        last_improvement[better] = batch * batch_size
        live = np.flatnonzero(active)
        stops = options.stopping.status_many(best_count[live], host["n"][live], drawn[live],
                                             drawn[live] - last_improvement[live],
                                             est.sample_size, options)
        done = np.asarray([stop is not None for stop in stops], bool)
        status[live[done]] = [stop for stop in stops if stop is not None]
        active[live[done]] = False
    return best_theta[:count], drawn[:count], status[:count]


def stacked(rows: list, slots_count: int, dtype, size: int) -> np.ndarray:
    """(slots_count, size, 3) ``dtype``: rows[i] (N_i, 3) zero-padded in slot i, the slots
    past the rows repeating slot 0 (one array filled in place: a padded copy per cloud
    and their np.stack had cost ~8 us a cloud)."""
    out = np.zeros((slots_count, size, 3), dtype)
    for slot, r in enumerate(rows):
        out[slot, :len(r)] = r
    out[len(rows):] = out[0]
    return out


def unit_bounds(clouds: list[Cloud], dtype) -> Bounds:
    """``Bounds.stack`` of the clouds' ``unit_bounds()``, as ``dtype``: one division of
    the radii by the clouds' scales when the clouds share one ``Bounds`` (the call's)."""
    first = clouds[0].bounds
    if any(c.bounds is not first for c in clouds):
        return Bounds.stack([c.unit_bounds() for c in clouds], dtype)
    values = np.repeat(np.asarray(first.values, np.float64)[None], len(clouds), axis=0)
    values[:, :2] /= np.asarray([c.scale for c in clouds], np.float64)[:, None]
    return Bounds(values.astype(dtype))
