"""Local optimisation (LO-RANSAC): a new best hypothesis refitted on its inliers.

A local optimiser is a frozen, hashable object (a static argument of the kernels) whose
``refine`` is traced under ``vmap`` for each cloud's best few hypotheses; a new one (a
graph-cut LO, IRLS, ...) is one new class of the same contract. The constants below are
the defaults of ``LevenbergMarquardt`` (how they were chosen: docs/engine.md).
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp

from ..shapes import Model
from .scoring import CHUNK, DEFAULT_SCORER, Scorer, score_one

#: An LO round counts as progress only if it lowers the cost by this fraction (on clean
#: data every round shaved off float noise, and the rounds ran to max_rounds).
LO_GAIN = 1e-4
#: Points the LM steps see at most (an evenly spread subset of larger clouds): the
#: accuracy of a refit is set by the noise long before 2048 points, and each round is
#: still accepted only if the cost over *all* points falls.
LO_POINTS = 2048
#: A round's LM steps stop once an accepted step lowers the squared error by less than
#: LM_GAIN (relative) or after LM_REFUSALS refused steps in a row.
LM_GAIN = 1e-5
LM_REFUSALS = 5
#: LO rounds refit on the points within this many thresholds of the current model: a
#: biased model refitted on exactly its own inliers keeps its bias; the wider band lets
#: it move.
LO_WIDEN = 2.0


class LocalOptimizer:
    """Interface (frozen and hashable).

    refine(cls, theta, points, n_valid, threshold, bounds, normals, n_chunks, rows,
    scorer) -> (theta (P,), cost, inlier count): JAX, traced under ``vmap``. theta (P,)
    is a hypothesis on padded points (B, 3) of which the first n_valid are real;
    ``bounds`` (one cloud's ``Bounds``) must hold for the result; with ``normals``
    (B, 3) inliers are gated on them; ``n_chunks`` as in ``scoring.score``; ``rows`` the
    points the steps may read (``lo_rows``). It must never return a hypothesis of
    higher ``scorer`` cost than the one it was given.
    """

    def refine(self, cls, theta, points, n_valid, threshold, bounds, normals, n_chunks,
               rows, scorer):  # pragma: no cover - abstract
        raise NotImplementedError


@dataclasses.dataclass(frozen=True)
class LevenbergMarquardt(LocalOptimizer):
    """Rounds of Levenberg-Marquardt steps on the points near the model (or the shape's
    closed-form ``least_squares`` fit where it has one), each round kept only if it
    lowers the cost over all points: at most ``max_rounds`` rounds of ``steps`` steps."""

    max_rounds: int = 20
    steps: int = 10

    def refine(self, cls, theta, points, n_valid, threshold, bounds, normals, n_chunks,
               rows, scorer):
        return refine_theta(cls, theta, points, n_valid, threshold, self.max_rounds,
                            self.steps, bounds=bounds, normals=normals, n_chunks=n_chunks,
                            rows=rows, scorer=scorer)


#: The default local optimiser.
DEFAULT_REFINER = LevenbergMarquardt()


def lo_rows(n: int) -> int:
    """Points the LM steps see for clouds of at most n points: LO_POINTS, or the power of
    two (>= CHUNK) that holds n, whichever is smaller (so a small cloud's steps do not
    spend half their work on its bucket's padding)."""
    return min(LO_POINTS, max(CHUNK, 1 << (n - 1).bit_length()))


def spread_rows(n_valid, count: int):
    """(count,) row indices the LM steps read: all of the first n_valid rows if they fit
    (then the rows past n_valid are padding), else count rows evenly spread over them
    (an integer stride would leave the tail of a cloud unseen)."""
    step = jnp.maximum(jnp.asarray(n_valid, jnp.float32) / count, 1.0)
    spread = jnp.minimum((jnp.arange(count) * step).astype(jnp.int32), n_valid - 1)
    return jnp.where(n_valid >= count, spread, jnp.arange(count))


def _refine_theta(cls: type[Model], theta, points, n_valid, threshold, max_rounds: int = 20,
                  steps: int = 10, bounds=None, normals=None, n_chunks=None,
                  rows: int | None = None, scorer: Scorer = DEFAULT_SCORER):
    """Local optimisation of a hypothesis theta (P,) on padded points (B, 3).

    Each round takes the current inliers (within LO_WIDEN thresholds) and runs ``steps``
    Levenberg-Marquardt steps on their signed geometric residuals (projected back with
    ``cls.canonicalize``), or the shape's closed-form ``least_squares`` fit to them where
    it has one (the plane). Rounds go on while they lower the cost over all points
    (at most ``max_rounds``), so the inlier set can grow from a rough hypothesis to the
    whole surface, and refinement never makes the model worse by the loop's own measure.
    The steps see ``rows`` points (default and at most LO_POINTS; see ``lo_rows`` and
    ``spread_rows``). A step that would leave the user's ``bounds`` (``Bounds``) is
    refused. With ``normals`` (B, 3), inliers are gated on them with
    ``bounds.normal_cos`` (see ``scoring.score``). ``n_chunks``: as in ``scoring.score``.
    Returns the refined theta, its cost and inlier count.
    """
    rows = spread_rows(n_valid, min(points.shape[0], LO_POINTS if rows is None else rows))
    live = rows < n_valid
    sub = points[rows]
    p = (sub[:, 0], sub[:, 1], sub[:, 2])
    gate = None if normals is None else (normals, bounds.normal_cos)

    def agrees(th):  # the gate of ``score`` on the LM points, (S,) bool
        if gate is None:
            return True
        m = normals[rows]
        _, slope = cls.residual_slope(th, p, (m[:, 0], m[:, 1], m[:, 2]), jnp)
        return jnp.abs(slope) >= gate[1]

    def lm_step(carry):
        th, lam, sse, weight, i, refusals = carry
        # Through canonicalize: a step must not spend the length of an axis (or a
        # plane's normal), which canonicalize throws away; with it the cone's steps were
        # mostly refused and refinement stalled short of the least-squares fit (noisy
        # cones: median axis error 0.39 -> 0.17 deg).
        resid = lambda t: cls.theta_residual(cls.canonicalize(t), p, jnp) * weight  # noqa: E731
        r, jac = resid(th), jax.jacfwd(resid)(th)
        normal = jac.T @ jac
        damping = lam * (jnp.diag(jnp.diag(normal)) + 1e-9 * jnp.eye(th.size, dtype=th.dtype))
        candidate = cls.canonicalize(th + jnp.linalg.solve(normal + damping, -(jac.T @ r)))
        new_sse = jnp.sum(resid(candidate) ** 2)
        better = jnp.isfinite(new_sse) & (new_sse < sse) & jnp.all(jnp.isfinite(candidate))
        if bounds is not None:
            better &= bounds.admits(cls, candidate)
        # A refused step raises the damping (a shorter, safer step next); an accepted
        # one that gained almost nothing means the round has converged.
        stale = jnp.where(better, jnp.where(new_sse < sse * (1.0 - LM_GAIN), 0, LM_REFUSALS),
                          refusals + 1)
        return (jnp.where(better, candidate, th), jnp.where(better, lam * 0.3, lam * 10.0),
                jnp.where(better, new_sse, sse), weight, i + 1, stale)

    def stepping(carry):
        return (carry[4] < steps) & (carry[5] < LM_REFUSALS)

    def lo_round(carry):
        th, cost, _, rounds = carry
        r = cls.theta_residual(th, p, jnp)
        weight = (live & (jnp.abs(r) < LO_WIDEN * threshold) & agrees(th)).astype(th.dtype)
        if cls.least_squares is None:
            init = (th, jnp.asarray(1e-3, th.dtype), jnp.sum((r * weight) ** 2), weight, 0, 0)
            candidate = jax.lax.while_loop(stepping, lm_step, init)[0]
        else:  # the same least-squares fit, in closed form
            candidate = cls.canonicalize(cls.least_squares(sub, weight))
        new_cost = score_one(cls, candidate, points, n_valid, threshold, gate, n_chunks, scorer)[0]
        better = new_cost < cost * (1.0 - LO_GAIN)
        if bounds is not None:
            better &= bounds.admits(cls, candidate)
        return (jnp.where(better, candidate, th), jnp.where(better, new_cost, cost), better,
                rounds + 1)

    def going(carry):
        return carry[2] & (carry[3] < max_rounds)

    cost = score_one(cls, theta, points, n_valid, threshold, gate, n_chunks, scorer)[0]
    theta, _, _, _ = jax.lax.while_loop(going, lo_round, (theta, cost, True, 0))
    return (theta, *score_one(cls, theta, points, n_valid, threshold, gate, n_chunks, scorer))


# ----- host side ----------------------------------------------------------------------


refine_theta = partial(jax.jit, static_argnames=("cls", "max_rounds", "steps", "rows",
                                                 "scorer"))(_refine_theta)
