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
from .backend import hypothesis_blocks

#: Points per scan step of the scoring kernel; every bucket is a multiple of it.
CHUNK = 256


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


def score(cls: type[Model], thetas, valid, points, n_valid, threshold, counts: bool = True,
          gate=None, n_chunks=None, scorer: Scorer = DEFAULT_SCORER):
    """Costs (H,) and inlier counts (H,) of hypotheses thetas (H, P) over the first
    n_valid of points (B, 3), B a multiple of CHUNK. Invalid hypotheses cost +inf.

    Only the first ``n_chunks`` chunks are scanned (default: those that hold the n_valid
    points), so a bucket's padding costs nothing; under ``vmap`` pass one unbatched
    ``n_chunks`` for all clouds (their largest), so the loop bound stays a scalar.

    ``gate`` = (normals (B, 3), min_cos): a point also needs |cos| >= min_cos between its
    normal and the surface's (``Model.residual_slope``) to count, else it costs t^2.

    With ``counts=False`` only the costs are computed (the count's second reduction per
    step is dear: the kernel counts inliers for its few best only).
    """
    t2 = threshold * threshold
    n_chunks = live_chunks(n_valid) if n_chunks is None else n_chunks
    blocks = hypothesis_blocks(thetas.shape[0])
    parts = [_score_block(cls, block.T, points, n_valid, t2, counts, gate, n_chunks, scorer)
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


def _score_block(cls, theta_t, points, n_valid, t2, counts, gate, n_chunks, scorer):
    """Costs (H,) and inlier counts (H,) of theta_t (P, H) (see ``score``)."""

    def step(i, carry):
        cost, count = carry
        start = i * CHUNK
        chunk = jax.lax.dynamic_slice_in_dim(points, start, CHUNK)
        live = ((start + jnp.arange(CHUNK)) < n_valid)[:, None]  # (C, 1)
        q = (chunk[:, 0:1], chunk[:, 1:2], chunk[:, 2:3])
        if gate is None:
            r = cls.theta_residual(theta_t, q, jnp)
            r2 = r * r  # (C, H)
        else:
            tangent = jax.lax.dynamic_slice_in_dim(gate[0], start, CHUNK)
            m = (tangent[:, 0:1], tangent[:, 1:2], tangent[:, 2:3])
            r, slope = cls.residual_slope(theta_t, q, m, jnp)
            r2 = jnp.where(jnp.abs(slope) >= gate[1], r * r, t2)
        cost = cost + jnp.sum(jnp.where(live, scorer.loss(r2, t2), 0.0), axis=0)
        if counts:
            count = count + jnp.sum(live & scorer.inlier(r2, t2), axis=0, dtype=jnp.int32)
        return cost, count

    zero = jnp.zeros(theta_t.shape[1], points.dtype)
    return jax.lax.fori_loop(0, n_chunks, step, (zero, zero.astype(jnp.int32)))
