"""The jitted entry points the host loop calls: the fused hypothesis kernel and the
batched refinement, for every cloud of a call at once.

One compiled kernel per (shape, H, point bucket, stages) does sample (``Sampler``) ->
estimate (the shape's estimator under ``vmap``) -> mask degenerate and out-of-bounds
hypotheses -> score (``Scorer``) -> the batch's best few; the stages are static
arguments, so the whole chain is traced into one program and stays fused.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from ..shapes import Model
from .backend import BESIDE_OPTIONS, REFINE_OPTIONS, jit_tuned, map_leading
from .refine import DEFAULT_REFINER, LocalOptimizer
from .sampling import DEFAULT_SAMPLER, Sampler, fold_in, uniform_indices, words
from .scoring import (
    CHUNK,
    DEFAULT_SCORER,
    SCREEN_KEEP,
    SCREEN_POINTS,
    Scorer,
    live_chunks,
    score,
    spread_rows,
)

#: Points drawn per support group for estimators that read the cloud (the box's
#: histogram modes), and the groups of a batch (each group's hypotheses share one).
SUPPORT = 256
SUPPORT_GROUPS = 16
#: Upper bound on (clouds x points x hypotheses) in one step of a batched scan (a few MB):
#: one vmap over hundreds of clouds spills every step out of cache.
GROUP_ELEMENTS = 1 << 20


def estimate_batch(cls: type[Model], samples, support, normals=None,
                   estimator: str = "thesis"):
    """vmap'd estimator: samples (H, k, 3), support (M, 3) shared, or (G, M, 3) with
    hypothesis h reading support group h // (H / G) (G divides H), and for the oriented
    estimator the samples' normals (H, k, 3) -> thetas (H, P), valid (H,)."""
    est = cls.estimator(estimator)
    one = jax.vmap(est.estimate, in_axes=(0, 0 if est.uses_normals else None, None))
    if getattr(support, "ndim", 2) == 2:  # (None: an estimator that reads no support)
        return one(samples, normals if est.uses_normals else None, support)
    groups, per = support.shape[0], samples.shape[0] // support.shape[0]
    split = lambda a: None if a is None else a.reshape(groups, per, *a.shape[1:])  # noqa: E731
    thetas, valid = jax.vmap(one, in_axes=(0, 0 if est.uses_normals else None, 0))(
        split(samples), split(normals) if est.uses_normals else None, support)
    return thetas.reshape(samples.shape[0], -1), valid.reshape(-1)


def _batch_best(cls: type[Model], batch_size: int, points, n_valid, key, threshold,
                normals=None, estimator: str = "thesis", top: int | None = None,
                n_sample=None, bounds=None, gated: bool = False, n_chunks=None,
                sampler: Sampler = DEFAULT_SAMPLER, scorer: Scorer = DEFAULT_SCORER,
                counts: bool = True):
    """The one kernel: H hypotheses from ``key`` scored on padded points (B, 3) (with
    their normals (B, 3) for the oriented estimator). Samples are drawn among the first
    ``n_sample`` points (default all n_valid). Hypotheses outside the user's ``bounds``
    (``Bounds``) are invalid; ``gated``: scores gate on normals at
    ``bounds.normal_cos``. ``n_chunks``: as in ``scoring.score``. In a bucket of more
    than ``SCREEN_POINTS`` points only the ``SCREEN_KEEP`` (or ``top``) best on a spread
    subset (``screened``) are scored on all points; the costs returned are always over
    all n_valid points.
    Returns the best (theta (P,), cost, inlier count) and the number of valid samples;
    with ``top`` the ``top`` best, best first: thetas (top, P), costs (top,), counts (top,).
    ``counts=False``: the counts are -1, not computed (a search with LO reads LO's own, so
    its kernel skips their scoring pass: one scan loop less to compile).
    """
    est = cls.estimator(estimator)
    n_sample = n_valid if n_sample is None else n_sample
    idx, distinct = sampler.draw(key, n_sample, batch_size, est.sample_size)
    # A support per group of hypotheses: a batch sharing one had all its box offsets
    # from the same 256 points, and where those missed a thin side face, all missed it.
    # Its indices are the words of key's stream after the samples' (``sampling``).
    shape = (math.gcd(batch_size, SUPPORT_GROUPS), SUPPORT) if cls.reads_support else \
        (SUPPORT,)
    drawn = words(key, math.prod(shape), batch_size * est.sample_size)
    support = points[uniform_indices(drawn, n_valid).reshape(shape)]
    thetas, valid = estimate_batch(cls, points[idx], support,
                                   normals[idx] if est.uses_normals else None, estimator)
    valid &= distinct
    if bounds is not None:
        valid &= jax.vmap(lambda theta: bounds.admits(cls, theta))(thetas)
    gate = (normals, bounds.normal_cos) if gated else None
    wanted = 1 if top is None else top
    keep = min(batch_size, max(SCREEN_KEEP, wanted))
    if points.shape[0] > SCREEN_POINTS and keep < batch_size:
        # (the bucket is static: small clouds' programs are not changed by this)
        kept = screened(cls, thetas, valid, points, n_valid, threshold, gate, keep, scorer)
        scored = score(cls, thetas[kept], valid[kept], points, n_valid, threshold,
                       counts=counts, gate=gate, n_chunks=n_chunks, scorer=scorer)
        costs, found = scored if counts else (scored, jnp.full(keep, -1, jnp.int32))
        _, order = jax.lax.top_k(-costs, wanted)
        best, costs, found = kept[order], costs[order], found[order]
    else:
        costs = score(cls, thetas, valid, points, n_valid, threshold, counts=False,
                      gate=gate, n_chunks=n_chunks, scorer=scorer)
        _, best = jax.lax.top_k(-costs, wanted)
        costs = costs[best]
        found = score(cls, thetas[best], valid[best], points, n_valid, threshold, gate=gate,
                      n_chunks=n_chunks, scorer=scorer)[1] if counts else \
            jnp.full(wanted, -1, jnp.int32)
    if top is None:
        return thetas[best[0]], costs[0], found[0], jnp.sum(valid)
    return thetas[best], costs, found, jnp.sum(valid)


def screened(cls: type[Model], thetas, valid, points, n_valid, threshold, gate, keep: int,
             scorer: Scorer = DEFAULT_SCORER):
    """Indices (keep,) of the hypotheses thetas (H, P) of lowest cost on SCREEN_POINTS
    rows of points (B, 3) spread over the first n_valid (``spread_rows``); ``gate`` as
    in ``score``."""
    rows = spread_rows(n_valid, SCREEN_POINTS)
    gate = None if gate is None else (gate[0][rows], gate[1])
    rough = score(cls, thetas, valid, points[rows], jnp.minimum(n_valid, SCREEN_POINTS),
                  threshold, counts=False, gate=gate, n_chunks=SCREEN_POINTS // CHUNK,
                  scorer=scorer)
    return jax.lax.top_k(-rough, keep)[1]


_STAGES = ("sampler", "scorer")
batch_best = jit_tuned(_batch_best, static_argnames=("cls", "batch_size", "estimator", "gated",
                                                     *_STAGES))


def _batch_best_many(cls, batch_size, estimator, points, normals, n_valid, n_sample,
                     cloud_keys, threshold, bounds, batch, gated=False,
                     sampler: Sampler = DEFAULT_SAMPLER, scorer: Scorer = DEFAULT_SCORER,
                     counts: bool = True):
    """``batch_best`` for every cloud: points (C, B, 3), normals (C, B, 3) or None,
    n_valid (C,), n_sample (C,), cloud_keys (C,), threshold (C,), bounds (``Bounds``
    with a leading (C,) axis); batch b of cloud c draws from
    ``sampling.fold_in(cloud_keys[c], b)``.
    Returns each cloud's ``cls.lo_starts`` best: thetas (C, S, P), costs (C, S),
    counts (C, S) (-1 with ``counts=False``), and its valid samples (C,)."""

    n_chunks = live_chunks(jnp.max(n_valid))  # one loop bound for all clouds

    def one(args):
        p, nrm, n, m, k, t, b = args
        return _batch_best(cls, batch_size, p, n, fold_in(k, batch), t, nrm,
                           estimator, cls.lo_starts, m, b, gated, n_chunks, sampler, scorer,
                           counts)

    return map_leading(one, (points, normals, n_valid, n_sample, cloud_keys, threshold,
                             bounds), group(points.shape[0], CHUNK * batch_size))


_KERNEL_ARGS = ("cls", "batch_size", "estimator", "gated", *_STAGES, "counts")
_batch_best_alone = jit_tuned(_batch_best_many, _KERNEL_ARGS)
_batch_best_beside = jit_tuned(_batch_best_many, _KERNEL_ARGS, BESIDE_OPTIONS)


def batch_best_many(*args, beside_refinement: bool = False, **kwargs):
    """``_batch_best_many``, jitted; ``beside_refinement``: for a search with LO, whose
    refinement program compiles beside the kernel's (``BESIDE_OPTIONS``: its code
    generated unsplit, which can round a float32 result differently) and gives the inlier
    counts the loop reads (so this kernel computes none: ``counts=False``)."""
    if beside_refinement:
        return _batch_best_beside(*args, counts=False, **kwargs)
    return _batch_best_alone(*args, **kwargs)


def group(clouds: int, elements: int) -> int:
    """Clouds processed side by side (vmap) inside the map over clouds: as many as keep
    one step's (clouds, elements) block within GROUP_ELEMENTS, a divisor of clouds."""
    size = max(1, min(clouds, GROUP_ELEMENTS // elements))
    while clouds % size:
        size -= 1
    return size


def _refine_many(cls, thetas, costs, points, n_valid, threshold, bounds, normals=None,
                 rows=None, refiner: LocalOptimizer = DEFAULT_REFINER,
                 scorer: Scorer = DEFAULT_SCORER):
    """``refiner.refine`` for each cloud's ``cls.lo_starts`` hypotheses thetas (C, S, P)
    with their kernel costs (C, S), gated on normals (C, B, 3) if given; returns the best
    refined theta (C, P), its cost (C,) and inlier count (C,) per cloud. A start the
    kernel found invalid (cost +inf: degenerate, or outside the bounds) never wins, though
    refinement gives it a finite cost: a batch with fewer valid hypotheses than starts
    had let an out-of-bounds one win under an axis_prior."""

    n_chunks = live_chunks(jnp.max(n_valid))  # one loop bound for all clouds
    theta, cost, count = refiner.refine_batch(
        cls, thetas, points, n_valid, threshold, bounds, normals, n_chunks, rows, scorer,
        group(points.shape[0], points.shape[1] * 64))
    cost = jnp.where(jnp.isfinite(costs), cost, jnp.inf)
    best = jnp.argmin(cost, axis=1)[:, None]
    pick = lambda a: jnp.take_along_axis(a, best.reshape(best.shape + (1,) * (a.ndim - 2)),  # noqa: E731
                                          axis=1)[:, 0]
    return pick(theta), pick(cost), pick(count)


refine_many = jit_tuned(_refine_many, ("cls", "rows", "refiner", "scorer"), REFINE_OPTIONS)
