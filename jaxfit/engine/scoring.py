"""Scorers, and the scan that scores H hypotheses over a padded cloud.

The scan visits the points in chunks of ``CHUNK`` with all H hypotheses on the vector
axis, so no H x N matrix exists and XLA's fusion stays on its fast path for any N
(PERF.md). A scorer says what one point costs a hypothesis and whether it is an inlier;
a new scorer (MAGSAC++, a truncated L1, ...) is one new class of the same contract.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ..shapes import Model
from .backend import batched_like, hypothesis_blocks

#: Points per scan step of the scoring kernel; every bucket is a multiple of it.
CHUNK = 256
#: In buckets of more than SCREEN_POINTS points the kernel first scores every hypothesis
#: on SCREEN_POINTS of them (``spread_rows``), then only its SCREEN_KEEP best on all:
#: which hypotheses of a batch are worth anything is settled on a few thousand points,
#: and scoring all of them on 1e5 was most of a large fit (docs/engine.md, "Session 14").
SCREEN_POINTS = 2048
SCREEN_KEEP = 16
#: (point, hypothesis) pairs a scan step over a bucket of more than SCREEN_POINTS holds at
#: least: there a step of a few hypotheses (the screen's best, LO's starts) spans more
#: than CHUNK points, since such a step over CHUNK is mostly the loop's own overhead.
STEP_PAIRS = CHUNK * 256


def scan_chunk(bucket: int, hypotheses: int) -> int:
    """Points per scan step for H hypotheses over a bucket of B points: CHUNK, or in a
    bucket of more than SCREEN_POINTS the power of two (a divisor of B) that brings the
    step to STEP_PAIRS. Small buckets keep CHUNK, and so their sums' order."""
    chunk = CHUNK
    if bucket > SCREEN_POINTS:
        while chunk * hypotheses < STEP_PAIRS and bucket % (2 * chunk) == 0:
            chunk *= 2
    return chunk


class Scorer:
    """Interface (frozen and hashable: a static argument of the kernels).

    loss(r2, t2) : cost of points with squared residuals r2 (any shape) at squared
        threshold t2; lower is better, and a point's cost must not exceed ``loss(t2, t2)``
        (a point gated out on its normal costs that).
    inlier(r2, t2) : (same shape) bool, whether the points count as inliers.
    """

    def loss(self, r2, t2):  # pragma: no cover - abstract
        raise NotImplementedError

    def inlier(self, r2, t2):  # pragma: no cover - abstract
        raise NotImplementedError


@dataclasses.dataclass(frozen=True)
class MSAC(Scorer):
    """Torr & Zisserman's M-estimator SAC: a point costs min(r^2, t^2)."""

    def loss(self, r2, t2):
        return jnp.minimum(r2, t2)

    def inlier(self, r2, t2):
        return r2 < t2


#: The default scorer.
DEFAULT_SCORER = MSAC()


def live_chunks(n_valid):
    """Scan steps that hold at least one of the first n_valid points."""
    return (n_valid + CHUNK - 1) // CHUNK


def spread_rows(n_valid, count: int):
    """(count,) row indices of a subset of a padded cloud (the LM steps' rows, the
    kernel's screen): all of the first n_valid rows if they fit (then the rows past
    n_valid are padding), else count rows evenly spread over them (an integer stride
    would leave the tail of a cloud unseen)."""
    step = jnp.maximum(jnp.asarray(n_valid, jnp.float32) / count, 1.0)
    spread = jnp.minimum((jnp.arange(count) * step).astype(jnp.int32), n_valid - 1)
    return jnp.where(n_valid >= count, spread, jnp.arange(count))


def score(cls: type[Model], thetas, valid, points, n_valid, threshold, counts: bool = True,
          gate=None, n_chunks=None, scorer: Scorer = DEFAULT_SCORER):
    """Costs (H,) and inlier counts (H,) of hypotheses thetas (H, P) over the first
    n_valid of points (B, 3), B a multiple of CHUNK. Invalid hypotheses cost +inf.

    Only the first ``n_chunks`` chunks of CHUNK points are scanned (default: those that
    hold the n_valid points), so a bucket's padding costs nothing (a scan step may span
    several chunks: ``scan_chunk``); under ``vmap`` pass one unbatched
    ``n_chunks`` for all clouds (their largest), so the loop bound stays a scalar.

    ``gate`` = (normals (B, 3), min_cos): a point also needs |cos| >= min_cos between its
    normal and the surface's (``Model.residual_slope``) to count, else it costs t^2.

    With ``counts=False`` only the costs are computed (the count's second reduction per
    step is dear: the kernel counts inliers for its few best only).
    """
    t2 = threshold * threshold
    n_chunks = live_chunks(n_valid) if n_chunks is None else n_chunks
    blocks = hypothesis_blocks(thetas.shape[0])
    chunk = scan_chunk(points.shape[0], thetas.shape[0] // blocks)
    ratio = chunk // CHUNK
    steps = n_chunks if ratio == 1 else (n_chunks + ratio - 1) // ratio
    parts = [_score_block(cls, block.T, points, n_valid, t2, counts, gate, steps, chunk,
                          scorer)
             for block in jnp.split(thetas, blocks)]
    cost = jnp.where(valid, jnp.concatenate([p[0] for p in parts]), jnp.inf)
    if not counts:
        return cost
    return cost, jnp.where(valid, jnp.concatenate([p[1] for p in parts]), 0)


def score_one(cls: type[Model], theta, points, n_valid, threshold, gate=None, n_chunks=None,
              scorer: Scorer = DEFAULT_SCORER):
    """Cost and inlier count of one hypothesis theta (P,) (see ``score``)."""
    cost, count = score(cls, theta[None], jnp.ones(1, bool), points, n_valid, threshold,
                        gate=gate, n_chunks=n_chunks, scorer=scorer)
    return cost[0], count[0]


def _score_block(cls, theta_t, points, n_valid, t2, counts, gate, steps, size, scorer):
    """Costs (H,) and inlier counts (H,) of theta_t (P, H) (see ``score``), ``steps``
    scan steps of ``size`` points."""

    def step(i, carry):
        cost, count = carry
        start = i * size
        chunk = jax.lax.dynamic_slice_in_dim(points, start, size)
        live = ((start + jnp.arange(size)) < n_valid)[:, None]  # (C, 1)
        q = (chunk[:, 0:1], chunk[:, 1:2], chunk[:, 2:3])
        if gate is None:
            r = cls.theta_residual(theta_t, q, jnp)
            r2 = r * r  # (C, H)
        else:
            tangent = jax.lax.dynamic_slice_in_dim(gate[0], start, size)
            m = (tangent[:, 0:1], tangent[:, 1:2], tangent[:, 2:3])
            r, slope = cls.residual_slope(theta_t, q, m, jnp)
            r2 = jnp.where(jnp.abs(slope) >= gate[1], r * r, t2)
        cost = cost + jnp.sum(jnp.where(live, scorer.loss(r2, t2), 0.0), axis=0)
        if counts:
            count = count + jnp.sum(live & scorer.inlier(r2, t2), axis=0, dtype=jnp.int32)
        return cost, count

    zero = jnp.zeros(theta_t.shape[1], points.dtype)
    return jax.lax.fori_loop(0, steps, step, batched_like((zero, zero.astype(jnp.int32)),
                                                          theta_t))
