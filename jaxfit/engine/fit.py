"""``fit`` and ``fit_batch``: check the input, prepare the clouds, run the host loop, and
turn each cloud's best hypothesis into a bounded model in the input's coordinates."""

from __future__ import annotations

import numbers

import numpy as np

from .. import _checks
from ..io.inputs import converted_batch
from ..shapes import Model
from .cloud import Cloud, estimate_normals, for_shape, prepare, prepare_many
from .loop import lower, searches
from .options import Bounds, FitOptions
from .refine import FINAL_MIN_POINTS, final_refit, host_lo
from .result import FitResult
from .scoring import MSAC

#: Calls of at least this many clouds are prepared in array code (``prepare_many``):
#: for one cloud its dozen extra array operations cost more than they save.
MANY_MIN = 4


def fit(points, shape, *, normals=None, threshold: float | None = None, key=0,
        options: FitOptions | None = None, **settings) -> FitResult:
    """Fit one primitive to a point cloud with batched RANSAC and MSAC scoring.

    Parameters
    ----------
    points : (N, 3) array-like of finite coordinates.
    shape : a registered name ("plane", "sphere", "cylinder", "cone", "box") or its class.
    normals : optional (N, 3) normals (any length, any sign), read by the oriented
        estimators and the normal gate. When they are needed and not given, they are
        estimated from the points (``jaxfit.estimate_normals``).
    threshold : inlier distance, in the points' units. Default: 0.5 % of the diagonal of
        the cloud's axis-aligned bounding box.
    key : int seed or JAX PRNG key. ``fit(points, ...)`` equals
        ``fit_batch([points], ...)[0]``: batch b uses ``fold_in(fold_in(key, 0), b)``.
    options : a ``FitOptions``; ``settings`` (any of its fields, e.g. ``confidence=0.999``,
        ``estimator="thesis"``, ``radius_range=(1, 2)``) replace its values.

    Returns
    -------
    FitResult
    """
    options = FitOptions.build(options, **settings)  # (fit_batch's own keywords are not
    # settings: skip_failures=True made fit return None)
    return fit_batch([points], shape, normals=None if normals is None else [normals],
                     thresholds=threshold, key=key, options=options)[0]


def fit_batch(clouds, shape, *, normals=None, thresholds=None, key=0,
              skip_failures: bool = False, separate: bool = False,
              options: FitOptions | None = None, **settings) -> list[FitResult | None]:
    """Fit one primitive to each of several clouds, all in the same compiled calls.

    Clouds of similar sizes are padded to one point bucket (and their count to a power
    of two) and each kernel call scores H hypotheses for every one of them at once;
    clouds of very different sizes run in separate loops (``loop.call_groups``), so a
    small cloud is never padded to a large one's bucket. Each cloud keeps its own key and
    stopping state, exactly as ``fit`` would (``fit`` is this with one cloud): its result
    does not depend on the other clouds of the call, up to float rounding.

    Parameters
    ----------
    clouds : sequence of (N_i, 3) arrays.
    normals : None or a sequence of (N_i, 3) arrays (or None entries), as in ``fit``.
    thresholds : None, one float for all clouds, or one per cloud (None entries take
        each cloud's default).
    key : cloud i uses ``fold_in(key, i)``.
    skip_failures : give None for a cloud on which no model can be fitted instead of
        raising ``FitError``. Invalid input always raises.
    separate : fit each cloud in a loop of its own, one after another, each padded as
        the call's largest cloud (its point bucket and LO's rows): the same results up to
        float rounding, and one program of one cloud whatever the number and sizes of
        the clouds, where a batch compiles a kernel and a refinement for each slot count
        (a power of two) and bucket it meets. For callers whose number of clouds changes
        from call to call and whose clouds are large enough (thousands of points) that
        batching gains little in a warm process: the decompositions and ``detect``
        (figures: docs/engine.md, "Session 35"; docs/detect.md).
    options, settings : as in ``fit``.

    Returns
    -------
    list of FitResult (or None), one per cloud.
    """
    return started_batch(clouds, shape, normals=normals, thresholds=thresholds, key=key,
                         skip_failures=skip_failures, separate=separate, options=options,
                         **settings)()


def started_batch(clouds, shape, *, normals=None, thresholds=None, key=0,
                  skip_failures: bool = False, separate: bool = False,
                  options: FitOptions | None = None, start: bool = False, **settings):
    """``fit_batch`` in two steps: the call is checked and its clouds prepared now (with
    ``start`` its searches' first batches dispatched too, ``loop.searches``), and
    ``finish(max_hypotheses=None)`` is returned, which runs the rest and gives
    fit_batch's list; ``max_hypotheses`` lowers the options' (the first batch does not
    depend on it). So a caller can dispatch several calls' first batches at once
    (``detect``'s shapes of a round)."""
    cls = _checks.model_class(shape)
    checked = FitOptions.build(options, **settings).check(cls)
    clouds, normals = converted_batch(clouds, normals, seed=lambda: _checks.numpy_seed(key))
    if not clouds:
        raise ValueError("clouds is empty: give at least one (N, 3) array")
    if normals is not None and len(normals) != len(clouds):
        raise ValueError(f"normals must be one array per cloud ({len(clouds)}), got {len(normals)}")
    if thresholds is None or isinstance(thresholds, numbers.Real | str) or np.ndim(thresholds) == 0:
        thresholds = [thresholds] * len(clouds)  # one for all (checked per cloud)
    if len(thresholds) != len(clouds):
        raise ValueError(f"thresholds must be one per cloud ({len(clouds)}), got {len(thresholds)}")
    seed, key = _seed_key(key)
    uses_normals = cls.estimator(checked.estimator).uses_normals
    named = _naming(len(clouds))
    prepared, which = None, list(range(len(clouds)))  # the clouds of the loop, their places
    if len(clouds) >= MANY_MIN and normals is None and not (uses_normals or checked.bounds.gated):
        prepared = prepare_many(clouds, cls, thresholds, checked.bounds)
    if prepared is None:  # (cloud by cloud: the first bad one named, coincident ones skipped)
        prepared, which = [], []
        for i, points in enumerate(clouds):
            try:
                prepared.append(prepare(points, cls, None if normals is None else normals[i],
                                        thresholds[i], uses_normals, key, i, checked.bounds))
                which.append(i)
            except _checks.FitError as err:  # well-formed, but no shape in it (coincident)
                if not skip_failures:
                    raise named(i, err) from None
            except ValueError as err:
                raise named(i, err) from None
    return _started(cls, checked, prepared, which, len(clouds), key, seed, skip_failures,
                    start, separate)


def started_shared(clouds: list[Cloud], shape, *, key=0, skip_failures: bool = False,
                   separate: bool = False, options: FitOptions | None = None,
                   start: bool = False, **settings):
    """``started_batch`` of clouds made by ``cloud.shared`` (checked, in their frames,
    with their normals; None for one that failed it, whose result is None): each shape's
    Cloud is ``cloud.for_shape`` of them, so a caller that fits several shapes to the same
    clouds (detect's groups) prepares them once."""
    cls = _checks.model_class(shape)
    checked = FitOptions.build(options, **settings).check(cls)
    uses_normals = cls.estimator(checked.estimator).uses_normals
    seed, key = _seed_key(key)
    which = [i for i, c in enumerate(clouds) if c is not None]
    prepared = [for_shape(clouds[i], cls, uses_normals, checked.bounds) for i in which]
    return _started(cls, checked, prepared, which, len(clouds), key, seed, skip_failures,
                    start, separate)


def _seed_key(key):
    """(int seed or None, key): an int seed becomes a key only where one is needed."""
    seed = _checks.seed_of(key)
    return seed, (_checks.prng_key(key) if seed is None else key)


def _naming(count: int):
    """The error of cloud i, naming it when a call has several clouds."""
    return lambda i, err: type(err)(f"cloud {i}: {err}") if count > 1 else err


def _started(cls: type[Model], checked: FitOptions, prepared: list[Cloud], which: list[int],
             count: int, key, seed, skip_failures: bool, start: bool, separate: bool):
    """``started_batch`` from its prepared clouds (``which``: each one's place among the
    call's ``count`` clouds)."""
    named = _naming(count)
    results: list[FitResult | None] = [None] * count
    if not prepared:
        return lambda max_hypotheses=None: results
    estimate_normals(prepared)
    run = searches(cls, checked, prepared, key, seed, which, start, separate)

    def finish(max_hypotheses: int | None = None) -> list[FitResult | None]:
        lowered = checked if max_hypotheses is None else lower(checked, cls, max_hypotheses)
        failed = None  # (index, FitError) of the call's first cloud that failed
        for part, (thetas, drawn, status) in run(lowered):
            # (while the next parts are searched: ``loop.searches``)
            # (not ``clouds``: ``named`` reads the call's count from it)
            searched = [prepared[j] for j in part]
            if lowered.polish or (lowered.refine and lowered.final_refit):
                thetas = refitted(cls, searched, thetas, lowered)
            found = (results_many(cls, searched, thetas, drawn, status)
                     if len(searched) >= MANY_MIN else [None] * len(searched))
            for k, j in enumerate(part):
                i = which[j]
                if found[k] is not None:
                    results[i] = found[k]
                    continue
                try:  # (cloud by cloud: where results_many gave none, this raises the why)
                    results[i] = result(cls, searched[k], thetas[k], drawn[k], status[k],
                                        lowered)
                except _checks.FitError as err:
                    # (raised once every part is in: parts may finish in any order)
                    if not skip_failures and (failed is None or i < failed[0]):
                        failed = (i, err)
        if failed is not None:
            raise named(*failed) from None
        return results

    return finish


def result(cls: type[Model], cloud: Cloud, theta, drawn, status,
           options: FitOptions | None = None) -> FitResult:
    """The FitResult of hypothesis theta (P,) (normalised frame) on ``cloud``; raises
    ``FitError`` when no hypothesis was valid or the best has no inliers."""
    if not np.isfinite(theta).all():
        bounded_by = [f"{name}={getattr(options, name)!r}" for name in
                      ("radius_range", "axis_prior") if getattr(options, name, None) is not None]
        why = (f"none within the bounds {', '.join(bounded_by)}, or the points are "
               "degenerate" if bounded_by else "the points are degenerate")
        raise _checks.FitError(
            f"no valid {cls.name} hypothesis in {drawn} samples: {why} for a {cls.name} "
            "(coincident, collinear or coplanar)"
        )
    unit_threshold = cloud.threshold / cloud.scale
    theta = np.asarray(theta, np.float64)
    agree = agreeing(cls, theta, cloud)
    model = bounded(cls, theta, cloud.unit, unit_threshold, True if agree is None else agree,
                    cloud.columns)
    if agree is not None:  # (the gate, as the distance below, on the bounded primitive)
        agree = np.abs(model.normal_cosines(cloud.unit, cloud.normals)) >= cloud.bounds.normal_cos
    model = model.rescaled(cloud.scale, cloud.center)
    # Final inliers are judged against the bounded primitive the user gets back.
    distance = model.distance(cloud.points)
    inliers = distance < cloud.threshold
    if agree is not None:  # (without a gate, ~15 us of all-true masks a cloud)
        inliers &= agree
        distance = np.where(agree, distance, np.inf)
    cost = float(np.minimum(distance**2, cloud.threshold**2).sum())
    return FitResult(model, inliers, int(np.count_nonzero(inliers)), cost, int(drawn),
                     status, cloud.threshold)


#: Points per block of ``results_many``: the arrays of a block stay in the cache (one
#: pass over all clouds' points at once was slower than cloud by cloud).
RESULTS_BLOCK = 1 << 15


def results_many(cls: type[Model], clouds: list[Cloud], thetas, drawn, status) -> list:
    """``result`` of every cloud, bit for bit, in array code over blocks of clouds
    (``RESULTS_BLOCK`` points each), for shapes with ``pointwise_theta`` and clouds
    without a normal gate: in each block the residuals of all its clouds in one pass over
    their concatenated points (each point with its cloud's parameters), the bounding in
    one ``from_theta_many``. Returns (C,) FitResults, with None for a cloud whose theta is
    not finite or whose best hypothesis has no inliers (``result`` then raises the
    error), or all None for other shapes and gated clouds.

    Why: ``result`` is ~40 us of NumPy calls a sphere and ~200 us a plane (the patch's
    medians and ``main_interval``), 15-40 % of ``fit_batch`` on 500-point clouds
    (docs/engine.md, "Results for many clouds")."""
    out: list = [None] * len(clouds)
    # (each distinct Bounds asked once: the clouds of a call share the call's; every
    # cloud's own ``gated``, a cached_property, took 4-5 ms for 1000 clouds)
    if not cls.pointwise_theta or any(b.gated for b in {id(c.bounds): c.bounds
                                                          for c in clouds}.values()):
        return out
    thetas = np.asarray(thetas, np.float64)
    ok = np.flatnonzero(np.isfinite(thetas).all(axis=1)).tolist()
    block, points = [], 0
    for j in ok + [None]:
        if block and (j is None or points + len(clouds[j].points) > RESULTS_BLOCK):
            for k, found in zip(block, _results_block(
                    cls, [clouds[k] for k in block], thetas[block], drawn[block],
                    [status[k] for k in block]), strict=True):
                out[k] = found
            block, points = [], 0
        if j is not None:
            block.append(j)
            points += len(clouds[j].points)
    return out


def _results_block(cls: type[Model], clouds: list[Cloud], thetas, drawn, status) -> list:
    """``results_many`` of a few clouds with finite thetas (C, P): one pass each."""
    out: list = [None] * len(clouds)
    sizes = np.asarray([len(c.points) for c in clouds], np.int64)
    unit_thresholds = np.asarray([c.threshold / c.scale for c in clouds])
    unit = np.concatenate([c.unit for c in clouds])  # (N, 3)
    near = np.abs(cls.theta_residual(np.repeat(thetas.T, sizes, axis=1),
                                     (unit[:, 0], unit[:, 1], unit[:, 2]), np))
    near = near < np.repeat(unit_thresholds, sizes)
    has = np.add.reduceat(near, np.cumsum(sizes) - sizes, dtype=np.int64) > 0
    if not has.all():  # (no inliers: left to ``result``, which raises)
        near = near[np.repeat(has, sizes)]
    ok = np.flatnonzero(has)
    chosen, sizes = [clouds[j] for j in ok], sizes[ok]
    if not chosen:
        return out
    models = cls.from_theta_many(thetas[ok], [c.unit for c in chosen], near,
                                 unit_thresholds[ok], [c.scale for c in chosen],
                                 np.stack([c.center for c in chosen]))
    # Judged against the bounded models, in the input's coordinates (as ``result``).
    points = np.concatenate([c.points for c in chosen])
    per_point = np.repeat(np.stack([m.theta() for m in models], axis=1), sizes, axis=1)
    distance = np.abs(cls.theta_residual(per_point, (points[:, 0], points[:, 1],
                                                     points[:, 2]), np))
    thresholds = [c.threshold for c in chosen]
    inliers = distance < np.repeat(thresholds, sizes)
    costs = np.minimum(distance**2, np.repeat([t**2 for t in thresholds], sizes))
    ends = np.cumsum(sizes)
    counts = np.add.reduceat(inliers, ends - sizes, dtype=np.int64).tolist()
    for j, model, end, size, t, count in zip(ok.tolist(), models, ends.tolist(),
                                             sizes.tolist(), thresholds, counts, strict=True):
        # (each cost summed over its own slice: reduceat sums in another order)
        out[j] = FitResult(model, inliers[end - size:end], count,
                           float(costs[end - size:end].sum()), int(drawn[j]), status[j], t)
    return out


def refitted(cls: type[Model], clouds: list[Cloud], thetas, options: FitOptions):
    """thetas (C, P) (normalised frames) after ``refine.final_refit`` on all points of
    each cloud larger than ``FINAL_MIN_POINTS`` (LO saw every point of the others), or
    with ``options.polish`` after ``refine.host_lo`` on every cloud, for the MSAC scorer
    (the least-squares fit on the inliers is MSAC's own optimum)."""
    if options.polish:
        return np.stack([polished(cls, cloud, starts) for cloud, starts in
                         zip(clouds, thetas, strict=True)])
    if type(options.scorer) is not MSAC:
        return thetas
    out = np.array(thetas, np.float64)
    for j, cloud in enumerate(clouds):
        if len(cloud.points) > FINAL_MIN_POINTS and np.all(np.isfinite(out[j])):
            out[j] = final_refit(cls, out[j], *_refit_args(cloud), columns=cloud.columns)[0]
    return out


def polished(cls: type[Model], cloud: Cloud, starts):
    """theta (P,): the lowest-cost ``refine.host_lo`` of the finite starts (S, P) (the
    search's with ``FitOptions.polish``) on ``cloud`` (normalised frame); NaN if none."""
    best, lowest = np.full(starts.shape[-1], np.nan), np.inf
    args = _refit_args(cloud)
    for start in np.asarray(starts, np.float64):
        if np.all(np.isfinite(start)):
            theta, cost, _ = host_lo(cls, start, *args, columns=cloud.columns)
            if cost < lowest:
                best, lowest = theta, cost
    return best


def _refit_args(cloud: Cloud):
    """The arguments of ``final_refit`` after theta for ``cloud``: its unit points, its
    threshold and bounds in their frame, and its normals where they gate."""
    return (cloud.unit, cloud.threshold / cloud.scale,
            Bounds(np.asarray(cloud.unit_bounds().values, np.float64)),
            cloud.normals if cloud.gated else None)


def agreeing(cls: type[Model], theta, cloud: Cloud):
    """(N,) whether each point passes the normal gate of hypothesis theta (normalised
    frame): the kernel's measure, in float64 NumPy (``Model.residual_slope``); None
    without a gate (every point passes)."""
    if not cloud.gated:
        return None
    _, slope = cls.residual_slope(theta, tuple(cloud.columns), tuple(cloud.normals.T), np)
    return np.abs(slope) >= cloud.bounds.normal_cos


def bounded(cls: type[Model], theta, unit, unit_threshold, agree=True, columns=None):
    """The bounded model from a hypothesis, in the normalised frame (float64), bounded by
    the points unit (N, 3) near its surface (and passing the normal gate, ``agree``
    (N,)); ``columns``: unit.T (3, N) where the caller has it (contiguous reads)."""
    q = tuple(columns) if columns is not None else (unit[:, 0], unit[:, 1], unit[:, 2])
    residual = cls.theta_residual(theta, q, np)
    inliers = np.abs(residual) < unit_threshold
    if agree is not True:
        inliers &= agree
    if not inliers.any():
        raise _checks.FitError(f"the best {cls.name} hypothesis has no inliers")
    return cls.from_theta(theta, unit, inliers, unit_threshold)
