"""Local optimisation (LO-RANSAC): a new best hypothesis refitted on its inliers.

A local optimiser is a frozen, hashable object (a static argument of the kernels) whose
``refine`` is traced under ``vmap`` for each cloud's best few hypotheses; a new one (a
graph-cut LO, IRLS, ...) is one new class of the same contract. The constants below are
the defaults of ``LevenbergMarquardt`` (how they were chosen: docs/engine.md).
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ..shapes import Model
from .backend import batched_like, map_leading
from .scoring import CHUNK, DEFAULT_SCORER, Scorer, score_one, spread_rows

#: An LO round counts as progress only if it lowers the cost by this fraction (on clean
#: data every round shaved off float noise, and the rounds ran to max_rounds).
LO_GAIN = 1e-4
#: Points the LM steps see at most (an evenly spread subset of larger clouds): the
#: accuracy of a refit is set by the noise long before 2048 points, and each round is
#: still accepted only if the cost over *all* points falls, except in buckets of at least
#: LO_SUBSET_BUCKET points (``lo_subset``).
LO_POINTS = 2048
#: In buckets of at least this many points a round of LO is accepted when it lowers the
#: cost over the LO_POINTS rows its steps see, and the rounds' result is judged against
#: its start on all points once (``lo_judged``): there a round's pass over every point is
#: most of LO's time, where in smaller ones the round's own fit is (docs/engine.md,
#: "Session 42").
LO_SUBSET_BUCKET = 1 << 16
#: A round's LM steps stop once an accepted step lowers the squared error by less than
#: LM_GAIN (relative) or after LM_REFUSALS refused steps in a row.
LM_GAIN = 1e-5
LM_REFUSALS = 5
#: LO rounds at most, and LM steps at most in each: a round starts again from its new
#: inliers, so steps past the fifth polished a fit the next round redoes (docs/engine.md,
#: "LM steps per round").
LO_ROUNDS = 20
LM_STEPS = 5
#: LO rounds refit on the points within this many thresholds of the current model: a
#: biased model refitted on exactly its own inliers keeps its bias; the wider band lets
#: it move.
LO_WIDEN = 2.0
#: ``host_lo`` (polish) ends with a refit on the inliers alone where their residuals sit
#: well inside the threshold, their RMS below this many thresholds (``narrows``): a
#: truncated Gaussian at 3 sigma has an RMS of 0.33 thresholds, noise that fills the band
#: (the thesis's SN scenarios) 0.58 (docs/engine.md, "Session 22"; LO's own rounds
#: narrowed so were measured and not kept).
NARROW_RMS = 0.45


class LocalOptimizer:
    """Interface (frozen and hashable).

    refine(cls, theta, points, n_valid, threshold, bounds, normals, n_chunks, rows,
    scorer) -> (theta (P,), cost, inlier count): JAX, traced under ``vmap``. theta (P,)
    is a hypothesis on padded points (B, 3) of which the first n_valid are real;
    ``bounds`` (one cloud's ``Bounds``) must hold for the result; with ``normals``
    (B, 3) inliers are gated on them; ``n_chunks`` as in ``scoring.score``; ``rows`` the
    points the steps may read (``lo_rows``). It must never return a hypothesis of
    higher ``scorer`` cost than the one it was given. ``refine_batch`` (all clouds of a
    call; this class maps ``refine`` over them) may be overridden with the same results.
    """

    def refine(self, cls, theta, points, n_valid, threshold, bounds, normals, n_chunks,
               rows, scorer):  # pragma: no cover - abstract
        raise NotImplementedError

    def refine_batch(self, cls, thetas, points, n_valid, threshold, bounds, normals,
                     n_chunks, rows, scorer, group: int):
        """``refine`` of every cloud's S starts thetas (C, S, P) on points (C, B, 3) (the
        other arguments with a leading (C,) axis, normals None or (C, B, 3)), ``group``
        clouds side by side (a divisor of C): (theta (C, S, P), cost (C, S), count (C, S)).
        A while_loop under vmap runs until its slowest member stops, so small groups keep
        one slow cloud from holding all the others. The starts of a group's clouds are
        one ``vmap`` (each start's cloud arrays gathered by index; one cloud's shared):
        a vmap of the starts inside a vmap of the clouds had traced every while_loop
        through two batching levels (a first fit of two parts: 2.5x the refinement's
        trace of one). A single cloud's starts are a scan instead (``lax.map``): its
        program then has no batched while_loop at all, and a cold first fit traces and
        compiles ~15 % less (docs/engine.md, "Session 36")."""
        count, starts = thetas.shape[:2]
        cloud = (points, n_valid, threshold, bounds, normals)

        def one(args):
            theta, c = args
            own = jax.tree.map(lambda a: a[0] if count == 1 else a[c], cloud)
            return self.refine(cls, theta, *own, n_chunks, rows, scorer)

        flat = (thetas.reshape(count * starts, thetas.shape[2]),
                jnp.repeat(jnp.arange(count), starts))
        out = map_leading(one, flat, None if count == 1 else group * starts)
        return jax.tree.map(lambda a: a.reshape(count, starts, *a.shape[1:]), out)


@dataclasses.dataclass(frozen=True)
class LevenbergMarquardt(LocalOptimizer):
    """Rounds of Levenberg-Marquardt steps on the points near the model (or the shape's
    closed-form ``least_squares`` fit where it has one), each round kept only if it
    lowers the cost over all points (in large buckets over the points the steps see,
    the result then judged on all: ``lo_subset``): at most ``max_rounds`` rounds of
    ``steps`` steps (None: the shape's ``lm_steps``, else ``LM_STEPS``)."""

    max_rounds: int = LO_ROUNDS
    steps: int | None = None

    def refine(self, cls, theta, points, n_valid, threshold, bounds, normals, n_chunks,
               rows, scorer):
        # (the plain function, not a jit of it: under the callers' vmap a nested jit is
        # traced, then traced again by the batching rule; ~20 % of the refinement's trace)
        return _refine_theta(cls, theta, points, n_valid, threshold, self.max_rounds,
                            self.steps_for(cls), bounds=bounds, normals=normals,
                            n_chunks=n_chunks, rows=rows, scorer=scorer)

    def refine_batch(self, cls, thetas, points, n_valid, threshold, bounds, normals,
                     n_chunks, rows, scorer, group: int):
        """``LocalOptimizer.refine_batch``, its clouds regrouped between rounds
        (``compacted``) when there are several groups: the same results, without a
        group's finished clouds riding along while one of them goes on. (One group, a
        single fit's, keeps the plain loop: the regrouping costs compile time there and
        saves nothing.)"""
        if thetas.shape[0] <= group:
            return super().refine_batch(cls, thetas, points, n_valid, threshold, bounds,
                                        normals, n_chunks, rows, scorer, group)
        return compacted(cls, thetas, points, n_valid, threshold, self.max_rounds,
                         self.steps_for(cls), bounds, normals, n_chunks, rows, scorer, group)

    def steps_for(self, cls: type[Model]) -> int:
        """The LM steps per round this refiner takes on shape ``cls``."""
        if self.steps is not None:
            return self.steps
        return LM_STEPS if cls.lm_steps is None else cls.lm_steps


#: The default local optimiser.
DEFAULT_REFINER = LevenbergMarquardt()


def lo_rows(n: int) -> int:
    """Points the LM steps see for clouds of at most n points: LO_POINTS, or the power of
    two (>= CHUNK) that holds n, whichever is smaller (so a small cloud's steps do not
    spend half their work on its bucket's padding)."""
    return min(LO_POINTS, max(CHUNK, 1 << (n - 1).bit_length()))


def lo_subset(bucket: int) -> bool:
    """Whether LO's rounds over a bucket of ``bucket`` points are measured on the rows
    its steps see (``LO_SUBSET_BUCKET``), their result then judged by ``lo_judged``."""
    return bucket >= LO_SUBSET_BUCKET


def lo_judged(cls: type[Model], start, theta, points, n_valid, threshold, bounds=None,
              normals=None, n_chunks=None, scorer: Scorer = DEFAULT_SCORER):
    """LO's result theta (P,) from ``start`` (P,) on padded points (B, 3), judged on all
    n_valid points: (theta, its cost, inlier count) where its cost is at most the
    start's, else (start, cost, count), so that LO never returns a worse hypothesis
    than it was given (``scoring.score_one`` of each, gated on ``normals`` (B, 3) at
    ``bounds.normal_cos`` if given: two hypotheses on the vector axis of one pass ran
    slower than two passes)."""
    gate = None if normals is None else (normals, bounds.normal_cos)
    old_cost, old_count = score_one(cls, start, points, n_valid, threshold, gate, n_chunks,
                                    scorer)
    cost, count = score_one(cls, theta, points, n_valid, threshold, gate, n_chunks, scorer)
    kept = cost <= old_cost  # (NaN: the start)
    return (jnp.where(kept, theta, start), jnp.where(kept, cost, old_cost),
            jnp.where(kept, count, old_count))


def solve_spd(a, b):
    """x (P,) with a x = b, a (P, P) symmetric positive definite (the damped normal
    equations of an LM step), by Gauss-Jordan elimination without pivoting in a loop of P
    steps: no LAPACK call (``jnp.linalg.solve`` is one on the CPU, and its presence
    costs every process scipy's import; docs/engine.md, "Compile cost, this round"). A
    pivot that round-off makes zero gives a non-finite x, which the step's test refuses."""
    size = a.shape[0]
    augmented = jnp.concatenate([a, b[:, None]], axis=1)  # (P, P + 1)
    index = jnp.arange(size)

    def eliminate(k, m):
        row = m[k] / m[k, k]
        column = jnp.where(index == k, 0.0, m[:, k])
        return (m - column[:, None] * row[None, :]).at[k].set(row)

    return jax.lax.fori_loop(0, size, eliminate, augmented)[:, size]


def _refine_theta(cls: type[Model], theta, points, n_valid, threshold,
                  max_rounds: int = LO_ROUNDS, steps: int = LM_STEPS, bounds=None,
                  normals=None, n_chunks=None,
                  rows: int | None = None, scorer: Scorer = DEFAULT_SCORER):
    """Local optimisation of a hypothesis theta (P,) on padded points (B, 3).

    Each round takes the current inliers (within LO_WIDEN thresholds) and runs ``steps``
    Levenberg-Marquardt steps on their signed geometric residuals (projected back with
    ``cls.canonicalize``), or the shape's closed-form ``least_squares`` fit to them where
    it has one (the plane). Rounds go on while they lower the cost over all points (in
    a bucket of at least ``LO_SUBSET_BUCKET``, over the points the steps see, and the
    result is then judged against theta on all points: ``lo_judged``), at most
    ``max_rounds``, so the inlier set can grow from a rough hypothesis to the whole
    surface, and refinement never makes the model worse by the loop's own measure.
    The steps see ``rows`` points (default and at most LO_POINTS; see ``lo_rows`` and
    ``spread_rows``). A step that would leave the user's ``bounds`` (``Bounds``) is
    refused. With ``normals`` (B, 3), inliers are gated on them with
    ``bounds.normal_cos`` (see ``scoring.score``). ``n_chunks``: as in ``scoring.score``.
    Returns the refined theta, its cost and inlier count.

    One program of few parts, since its XLA compile is a first fit's cost (docs/engine.md,
    "Compile cost, this round"): the cloud is scored in one place (the loop's round 0
    scores theta itself), each LM step evaluates the residuals and their Jacobian once (at
    its candidate, kept as the next step's normal equations when accepted), and the
    damped normal equations are solved by ``solve_spd``.
    """
    lo_round, going = lo_rounds(cls, points, n_valid, threshold, max_rounds, steps, bounds,
                                normals, n_chunks, rows, scorer)
    found, cost, count, _, _ = jax.lax.while_loop(going, lo_round,
                                                  batched_like(lo_start(theta), theta))
    if not lo_subset(points.shape[0]):
        return found, cost, count
    return lo_judged(cls, theta, found, points, n_valid, threshold, bounds, normals,
                     n_chunks, scorer)


def lo_start(theta):
    """The carry of ``lo_rounds`` before round 0: (theta, cost, inlier count, whether the
    last round was kept, the next round's index)."""
    return (theta, jnp.asarray(jnp.inf, theta.dtype), jnp.asarray(0, jnp.int32),
            jnp.asarray(True), jnp.asarray(0, jnp.int32))


def lo_rounds(cls: type[Model], points, n_valid, threshold, max_rounds: int, steps: int,
              bounds=None, normals=None, n_chunks=None, rows: int | None = None,
              scorer: Scorer = DEFAULT_SCORER):
    """(lo_round, going) of ``_refine_theta`` for one cloud: lo_round(carry) -> carry runs
    the carry's next round (``lo_start``), going(carry) says whether one is due. Apart, so
    that many clouds' refinements can be regrouped between rounds (``compacted``)."""
    subset = lo_subset(points.shape[0])
    rows = spread_rows(n_valid, min(points.shape[0], LO_POINTS if rows is None else rows))
    live = rows < n_valid
    sub = points[rows]
    p = (sub[:, 0], sub[:, 1], sub[:, 2])
    gate = None if normals is None else (normals, bounds.normal_cos)
    basis = jnp.eye(cls.num_params, dtype=points.dtype)

    def agrees(th):  # the gate of ``score`` on the LM points, (S,) bool
        if gate is None:
            return True
        m = normals[rows]
        _, slope = cls.residual_slope(th, p, (m[:, 0], m[:, 1], m[:, 2]), jnp)
        return jnp.abs(slope) >= gate[1]

    def measured(th):
        """A round's (cost, inlier count): ``score``'s over all points, or in a large
        bucket (``lo_subset``) over the LM points (their live ones are a prefix: all, or
        the first n_valid of a smaller cloud)."""
        if not subset:
            return score_one(cls, th, points, n_valid, threshold, gate, n_chunks, scorer)
        return score_one(cls, th, sub, jnp.minimum(n_valid, len(rows)), threshold,
                         None if gate is None else (normals[rows], gate[1]),
                         len(rows) // CHUNK, scorer)

    def normal_equations(th, weight):
        """The weighted residuals' squared sum, J^T J (P, P) and J^T r (P,) at th, J the
        residuals' Jacobian through canonicalize (the shape's ``theta_jacobian`` where
        ``lm_analytic``, else one JVP per parameter; the residuals evaluated once)."""
        # Through canonicalize: a step must not spend the length of an axis (or a
        # plane's normal), which canonicalize throws away; with it the cone's steps were
        # mostly refused and refinement stalled short of the least-squares fit (noisy
        # cones: median axis error 0.39 -> 0.17 deg).
        # The chain rule by hand, a barrier between its two halves: XLA had fused the
        # projection (the box's polar factor) into the per-point residuals and computed
        # it again for every point (the box's refinement 3x slower).
        flat, along = jax.vmap(lambda v: jax.jvp(cls.canonicalize, (th,), (v,)),
                               out_axes=(None, 0))(basis)  # (P,), (P, P)
        flat, along = jax.lax.optimization_barrier((flat, along))
        if cls.theta_jacobian is not None and cls.lm_analytic:  # (no JVPs to trace)
            r = cls.theta_residual(flat, p, jnp) * weight
            jt = along @ (jnp.asarray(cls.theta_jacobian(flat, p, jnp)) * weight)  # (P, S)
            return jnp.sum(r * r), jt @ jt.T, jt @ r
        resid = lambda t: cls.theta_residual(t, p, jnp) * weight  # noqa: E731
        r, jac = jax.vmap(lambda v: jax.jvp(resid, (flat,), (v,)), out_axes=(None, 1))(along)
        return jnp.sum(r * r), jac.T @ jac, jac.T @ r

    def lm_step(carry):
        # Step 0 only evaluates the round's start (its step is 0: J^T r is still 0).
        th, sse, jtj, jtr, weight, lam, i, refusals = carry
        damping = lam * (jnp.diag(jnp.diag(jtj)) + 1e-9 * basis)
        candidate = cls.canonicalize(th + solve_spd(jtj + damping, -jtr))
        candidate = jnp.where(i == 0, th, candidate)
        new_sse, new_jtj, new_jtr = normal_equations(candidate, weight)
        better = jnp.isfinite(new_sse) & (new_sse < sse) & jnp.all(jnp.isfinite(candidate))
        if bounds is not None:
            better &= bounds.admits(cls, candidate)
        better |= i == 0
        # A refused step raises the damping (a shorter, safer step next); an accepted
        # one that gained almost nothing means the round has converged.
        stale = jnp.where(better, jnp.where(new_sse < sse * (1.0 - LM_GAIN), 0, LM_REFUSALS),
                          refusals + 1)
        stale = jnp.where(i == 0, 0, stale)
        keep = lambda new, old: jnp.where(better, new, old)  # noqa: E731
        return (keep(candidate, th), keep(new_sse, sse), keep(new_jtj, jtj),
                keep(new_jtr, jtr), weight, jnp.where(i == 0, lam, keep(lam * 0.3, lam * 10.0)),
                i + 1, stale)

    def refit(th, k):
        """Round k's candidate from th: LM steps or the closed-form fit on the points
        near th (round 0: th itself, its steps not run)."""
        r = cls.theta_residual(th, p, jnp)
        weight = (live & (jnp.abs(r) < LO_WIDEN * threshold) & agrees(th)).astype(th.dtype)
        if cls.least_squares is not None:  # the same least-squares fit, in closed form
            return jnp.where(k == 0, th, cls.canonicalize(cls.least_squares(sub, weight)))

        def stepping(carry):
            return (k > 0) & (carry[6] <= steps) & (carry[7] < LM_REFUSALS)

        zero = jnp.zeros((th.size, th.size), th.dtype)
        init = (th, jnp.asarray(jnp.inf, th.dtype), zero, zero[0], weight,
                jnp.asarray(1e-3, th.dtype), 0, 0)
        return jax.lax.while_loop(stepping, lm_step, batched_like(init, th))[0]

    def lo_round(carry):
        # Round 0 scores theta itself; round k > 0 scores the k-th refit.
        th, cost, count, _, k = carry
        candidate = th if max_rounds == 0 else refit(th, k)
        new_cost, new_count = measured(candidate)
        better = new_cost < cost * (1.0 - LO_GAIN)
        if bounds is not None:
            better &= bounds.admits(cls, candidate)
        better |= k == 0
        return (jnp.where(better, candidate, th), jnp.where(better, new_cost, cost),
                jnp.where(better, new_count, count), better, k + 1)

    return lo_round, partial(lo_due, max_rounds=max_rounds)


def narrows(r, live, threshold) -> bool:
    """Whether ``host_lo``, converged on LO's wide band at a model whose residuals are r
    (S,) (the points where live (S,) holds), refits on its inliers alone: where their
    residuals sit well inside the threshold (RMS below NARROW_RMS thresholds), the noise
    is small against it, and the wide band's outliers only pull the fit away from the
    inliers' least-squares fit (RN: 1.4-2.4x closer); where noise fills the band, a cut
    at one threshold biases the fit (SN), and the wide band's fit stays."""
    inside = live & (np.abs(r) < threshold)
    mean2 = np.sum(np.where(inside, r * r, 0.0)) / max(np.count_nonzero(inside), 1)
    return bool(mean2 < (NARROW_RMS * threshold) ** 2)


def lo_due(carry, max_rounds: int):
    """Whether the carry (``lo_start``; any leading axes) is due another LO round: its
    last round was kept and the cap is not reached."""
    return carry[3] & (carry[4] <= max_rounds)


def compacted(cls: type[Model], thetas, points, n_valid, threshold, max_rounds: int,
              steps: int, bounds, normals, n_chunks, rows, scorer, group: int):
    """``_refine_theta`` of every cloud's S starts thetas (C, S, P) (as ``refine_batch``),
    one round at a time: before each round the clouds with a start still going are moved
    to the front, and only the groups of ``group`` clouds that hold them run it (a vmap'd
    while_loop over rounds had run every group until its slowest cloud stopped: after two
    rounds ~4 % of the spheres go on, but half the groups of 16 had one)."""
    def one_round(carry, c):
        """Cloud c's S starts' carries (S, ...) after their next round (unchanged where
        not going)."""
        lo_round, going = lo_rounds(
            cls, points[c], n_valid[c], threshold[c], max_rounds, steps,
            jax.tree.map(lambda a: a[c], bounds), None if normals is None else normals[c],
            n_chunks, rows, scorer)

        def start(carry_s):
            new = lo_round(carry_s)
            return jax.tree.map(lambda a, b: jnp.where(going(carry_s), a, b), new, carry_s)

        return jax.vmap(start)(carry)

    def alive(carry):  # (C,): whether any of a cloud's starts is due another round
        return jnp.any(lo_due(carry, max_rounds), axis=1)

    def phase(carry):
        going = alive(carry)
        order = jnp.argsort(~going, stable=True)  # going clouds first
        groups = (jnp.sum(going) + group - 1) // group

        def run(g, carry):
            clouds = jax.lax.dynamic_slice(order, (g * group,), (group,))
            moved = jax.vmap(one_round)(jax.tree.map(lambda a: a[clouds], carry), clouds)
            return jax.tree.map(lambda a, b: a.at[clouds].set(b), carry, moved)

        return jax.lax.fori_loop(0, groups, run, carry)

    carry = jax.vmap(jax.vmap(lo_start))(thetas)  # (C, S, ...)
    theta, cost, found, _, _ = jax.lax.while_loop(lambda c: jnp.any(alive(c)), phase, carry)
    if not lo_subset(points.shape[1]):
        return theta, cost, found

    def judged(starts, theta, points, n_valid, threshold, bounds, normals):  # one cloud's
        return jax.vmap(lambda s, t: lo_judged(cls, s, t, points, n_valid, threshold, bounds,
                                               normals, n_chunks, scorer))(starts, theta)

    return jax.vmap(judged)(thetas, theta, points, n_valid, threshold, bounds, normals)


# ----- the final refit (host NumPy, float64) ------------------------------------------

#: Clouds of at most this many points skip the final refit: LO's steps already saw every
#: one of their points (``lo_rows`` >= n), so it would repeat that fit (docs/refit.md).
FINAL_MIN_POINTS = LO_POINTS
#: Gauss-Newton steps of the final refit: it starts from LO's fit on LO_POINTS points, a
#: few noise widths from the optimum, where Gauss-Newton converges in one or two steps.
FINAL_STEPS = 2
#: Damped retries of a step whose candidate raised the cost or left the bounds.
FINAL_RETRIES = 3
#: The refit stops once a step lowers the MSAC cost by less than this fraction.
FINAL_GAIN = 1e-7
#: Points per chunk of the final refit's sums: its memory is a few (FINAL_CHUNK, P)
#: float64 arrays, whatever the cloud's size, small enough that a chunk's temporaries
#: stay in the core's cache (2^16 had made a 1e5-point refit 2-3x slower; docs/refit.md).
FINAL_CHUNK = 1 << 14
#: Step of the forward differences that give the residual's Jacobian (unit frame).
FINAL_STEP = 1e-7


def host_canonical(cls: type[Model]):
    """theta (P,) -> theta (P,): ``cls.canonicalize`` in NumPy float64, or None for a
    shape whose ``canonicalize`` takes no ``xp`` (then the final refit leaves its fits
    alone)."""
    if not _projects_in_numpy(cls):
        return None
    return lambda theta: cls.canonicalize(np.asarray(theta, np.float64), np)


@functools.cache
def _projects_in_numpy(cls: type[Model]) -> bool:
    """Whether ``cls.canonicalize`` takes ``xp`` (kept per class: reading a signature
    cost ~0.1 ms, a tenth of a refit at 1e4 points)."""
    return "xp" in inspect.signature(cls.canonicalize).parameters


def _chunks(n: int):
    return [slice(s, min(s + FINAL_CHUNK, n)) for s in range(0, n, FINAL_CHUNK)]


def _evaluate(cls, theta, columns, threshold, normals, normal_cos, canonical=None,
              widen: float = 1.0, raw: bool = False):
    """MSAC cost () of theta (P,) over the points whose coordinates are columns (3, N)
    (with normals (3, N) or None), the loop's measure (a point gated out on its normal
    costs t^2), and with ``canonical`` the normal equations of the least-squares fit on
    its inliers (with ``widen``, on the points within that many thresholds): J^T J
    (P, P) and J^T r (P,), J through ``canonical`` (the shape's ``theta_jacobian`` times
    the projection's own Jacobian, else forward differences of the residuals), or with
    ``raw`` the shape's ``theta_jacobian`` alone (``host_least_squares`` reads its
    J^T J). One pass, ``FINAL_CHUNK`` points at a time, in float64 (the columns
    contiguous, made once by ``final_refit`` for all its passes: a boolean gather of
    (N, 3) rows had cost as much as the differences)."""
    t2, cost, size = threshold * threshold, 0.0, theta.size
    jtj, jtr = np.zeros((size, size)), np.zeros(size)
    equations = canonical is not None
    moved = None  # (P, P): canonical of theta with each entry nudged (one call if batched)
    if equations and not raw:
        nudged = theta + FINAL_STEP * np.eye(size)
        moved = canonical(nudged) if cls.batched_canonical else \
            np.stack([canonical(t) for t in nudged])
    # (P, P) d canonical / d theta, by differences of P-vectors: with it the points'
    # Jacobian is one analytic pass, where the differences take P residual passes
    chain = None if moved is None or cls.theta_jacobian is None else \
        (moved - theta).T / FINAL_STEP
    analytic = raw or chain is not None
    step = 1.0 if analytic else FINAL_STEP  # (the differences' rows are * step)
    for part in _chunks(columns.shape[1]):
        block = columns[:, part]  # (3, n), each row contiguous
        q = tuple(block)
        if normals is None:
            r = cls.theta_residual(theta, q, np)
            r2 = r * r
        else:
            r, slope = cls.residual_slope(theta, q, tuple(normals[:, part]), np)
            r2 = np.where(np.abs(slope) >= normal_cos, r * r, t2)
        inside = r2 < t2
        cost += float(np.sum(np.fmin(r2, t2)))  # (where(inside, r2, t2), NaN included)
        if equations:
            keep = np.flatnonzero(inside if widen == 1.0 else r2 < widen * widen * t2)
            qi, ri = tuple(block.take(keep, axis=1)), r.take(keep)
            if analytic:  # (with a chain, the projection applied to the sums at the end)
                jac = cls.theta_jacobian(theta, qi, np)  # (P, M)
            else:
                jac = np.empty((size, len(keep)))  # (P, M): each row one contiguous write
                for k, m in enumerate(moved):
                    np.subtract(cls.theta_residual(m, qi, np), ri, out=jac[k])
            jtj += jac @ jac.T
            jtr += jac @ ri
    if chain is not None:
        jtj, jtr = chain.T @ jtj @ chain, chain.T @ jtr
    jtj /= step * step
    jtr /= step
    return cost, jtj, jtr


def final_refit(cls: type[Model], theta, points, threshold: float, bounds=None,
                normals=None, steps: int = FINAL_STEPS, widen: float = 1.0,
                min_gain: float = FINAL_GAIN, columns=None):
    """A least-squares refit of theta (P,) on all the inliers of points (N, 3), in float64
    NumPy (no compiled program): Gauss-Newton steps on the residuals of the current
    inliers (Levenberg-damped on a refusal), or where the shape has one its closed-form
    fit to them (``host_least_squares``: the plane), each kept only if the MSAC cost
    over all points does not rise and the bounds hold.

    LO refines on at most LO_POINTS points (in the kernels' float32), so its accuracy
    stops growing with N; this sums over every point, ``FINAL_CHUNK`` at a time.
    ``bounds``: one cloud's ``Bounds`` (unbatched) in the points' frame, or None;
    with ``normals`` (N, 3), inliers are gated on them at the bounds' normal cosine.
    ``points`` are the cloud in the normalised frame, where theta's parameters are O(1).
    theta is first projected in float64 (``host_canonical``: the kernels' float32 axis
    is unit only to ~1e-7, the differences' own step, and had made the Jacobian noise).
    ``widen``: each step fits the points within that many thresholds (LO's band,
    ``host_lo``); ``min_gain``: the relative fall in cost below which it stops.
    ``columns``: points.T as contiguous rows (3, N), where the caller has them
    (``Cloud.columns``): the transposed copy is then not made again.
    Returns (theta (P,), its MSAC cost, the cost of the projected theta given); theta
    unchanged when it is not finite or the shape has no NumPy projection.
    """
    theta = np.asarray(theta, np.float64)
    canonical = host_canonical(cls)
    if not np.all(np.isfinite(theta)) or canonical is None:
        return theta, np.inf, np.inf
    if columns is None:
        columns = np.ascontiguousarray(np.asarray(points).T)
    args = (columns, threshold,
            None if normals is None else np.ascontiguousarray(np.asarray(normals).T),
            None if normals is None else float(bounds.normal_cos))
    theta = canonical(theta)
    # (the closed form reads the points' moments from theta_jacobian's J^T J)
    closed = cls.host_least_squares if cls.theta_jacobian is not None else None
    cost, jtj, jtr = _evaluate(cls, theta, *args, canonical=canonical, widen=widen,
                               raw=closed is not None)
    start, damping = cost, 0.0
    for step_index in range(steps):
        last = step_index == steps - 1  # (its normal equations would go unused)
        diag = np.diag(np.diag(jtj))
        # A closed-form fit has one candidate; Gauss-Newton retries with more damping.
        for _ in range(1 if closed is not None else FINAL_RETRIES):
            candidate = canonical(closed(jtj, theta) if closed is not None else
                                  theta - pseudo_solve(jtj + damping * diag, jtr))
            if np.all(np.isfinite(candidate)) and (bounds is None
                                                   or bounds.admits(cls, candidate, np)):
                found = _evaluate(cls, candidate, *args, canonical=None if last else canonical,
                                  widen=widen, raw=closed is not None)
                if found[0] <= cost:
                    break
            damping = max(10.0 * damping, 1e-3)
        else:
            break  # every candidate refused: theta stays where it was
        gain = cost - found[0]
        theta, (cost, jtj, jtr), damping = candidate, found, 0.1 * damping
        if gain <= min_gain * cost:
            break
    return theta, cost, start


def pseudo_solve(a, b, rcond: float = 1e-12):
    """pinv(a) @ b for a symmetric a (P, P) and b (P,): by one eigendecomposition, with
    the eigenvalues at most rcond times the largest in magnitude left out (a gauge
    direction, an axis's length or a cylinder's centre along its axis, then gets no step,
    where a plain solve would amplify noise). ``np.linalg.pinv(hermitian=True)``'s
    result to rounding, in ~0.03 against ~0.1 ms (its sorting, sign and wrapper
    passes)."""
    values, vectors = np.linalg.eigh(a)
    size = np.abs(values)
    kept = size > rcond * size.max()
    inverse = np.divide(1.0, values, out=np.zeros_like(values), where=kept)
    return vectors @ (inverse * (vectors.T @ b))


def host_lo(cls: type[Model], theta, points, threshold: float, bounds=None, normals=None,
            columns=None):
    """LO-RANSAC's refit of a hypothesis theta (P,), on the host (no compiled program):
    ``final_refit``'s steps on the points within ``LO_WIDEN`` thresholds (each step
    recomputes them, as an LO round does, for up to ``LO_ROUNDS`` steps), then on its
    inliers where they sit well inside the threshold (``narrows``); arguments and return
    as ``final_refit``'s. For one-off fits in a fresh process, where compiling LO's
    program costs more than all its rounds."""
    if columns is None:
        columns = np.ascontiguousarray(np.asarray(points).T)
    theta, cost, start = final_refit(cls, theta, points, threshold, bounds, normals,
                                     steps=LO_ROUNDS, widen=LO_WIDEN, min_gain=LO_GAIN,
                                     columns=columns)
    if np.all(np.isfinite(theta)):
        q = tuple(columns)
        r = cls.theta_residual(theta, q, np)
        live = True if normals is None else np.abs(cls.residual_slope(
            theta, q, tuple(normals.T), np)[1]) >= bounds.normal_cos
        if narrows(r, live, threshold):
            theta, cost, _ = final_refit(cls, theta, points, threshold, bounds, normals,
                                         columns=columns)
    return theta, cost, start
