"""The engine: sampling, the jitted scoring kernel, the stopping rule, refinement and the
host loop behind ``jaxfit.fit``.

The cloud is centred and scaled into the unit ball, padded with a validity mask to a
power-of-two *bucket* of points (so a new cloud size reuses a compiled kernel), and then
scored in batches of H hypotheses. One compiled kernel per (shape, H, bucket) does
sample -> estimate (vmap) -> residuals -> MSAC cost and inlier count -> the batch's best.
Points are scanned in chunks of ``CHUNK`` with all H hypotheses on the vector axis, so no
H x N matrix exists and XLA's fusion stays on its fast path for any N (PERF.md).
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
import numbers
import warnings
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from . import _checks
from ._cache import stored_jit
from .shapes import Model
from .shapes._geometry import column_bounds, row_norms

#: Points per scan step of the scoring kernel; every bucket is a multiple of it.
CHUNK = 256
#: The scoring kernel splits H hypotheses into this many independent loops on the CPU,
#: when each gets at least BLOCK_MIN of them: XLA's CPU runtime runs independent loops
#: side by side, and splits one loop's body over the cores only when it is large.
#: Sphere, H = 4096, interleaved runs under load: +9 % at 1e3 points, +5 % at 1e4 and
#: 1e5; the cylinder unchanged within noise.
HYPOTHESIS_BLOCKS = 2
BLOCK_MIN = 256
#: Smallest point-count bucket; larger clouds pad to the next power of two.
MIN_BUCKET = 1024
#: Points drawn per batch for estimators that read the cloud (the box's histogram modes):
#: 256 finds the modes as reliably as 1024 on the test clouds (30 seeds) at a quarter of
#: the cost of the histogram scatter, which dominates the box kernel.
SUPPORT = 256
#: Upper bound on (clouds x points x hypotheses) in one step of a batched scan (a few MB).
GROUP_ELEMENTS = 1 << 20
#: An LO round counts as progress only if it lowers the MSAC cost by this fraction: on
#: clean data every round shaved off float noise, and the rounds ran to max_rounds.
LO_GAIN = 1e-4
#: Points the LM steps of LO-RANSAC see (a strided subsample of larger clouds): refining
#: cost 60-95 % of a fit on 1e4-1e5 points when every step read every point, while the
#: accuracy of a refit is set by the noise long before 2048 points (each round is still
#: accepted only if the MSAC cost over *all* points falls).
LO_POINTS = 2048
#: A round's Levenberg-Marquardt steps stop early, once an accepted step lowers the
#: squared error by less than LM_GAIN (relative) or after LM_REFUSALS refused steps in a
#: row: the rest of a fixed count of steps only shaved float noise, and they were most
#: of the refinement's time (sphere: 1000 clouds of 500 points in fit_batch, refinement
#: 0.85 -> 0.4-0.5 s; one 1e4-point fit, 3.6 -> 1.8-2.8 ms, on the loaded machine).
#: Fewer refusals were too few: a
#: box's non-smooth residual and a noisy cone refuse several steps, with a rising
#: damping, before they move on (3 refusals took the cone's median axis error at SN 0.05
#: with estimated normals from 0.38 to 0.84 deg; 5 leave it at 0.38-0.39).
LM_GAIN = 1e-5
LM_REFUSALS = 5
#: LO rounds refit on the points within this many thresholds of the current model: a
#: biased model keeps its bias when refitted on exactly its own inliers (those on its
#: far side are cut off); the wider band lets it move. On noisy cones (SN 0.05) this
#: took the median axis error from ~1 deg to ~0.35 deg, with a lower MSAC cost.
LO_WIDEN = 2.0
#: Oriented estimators draw their samples from a random pool of at most this many points,
#: the only ones whose normals are estimated (when none are given): on a 1e5-point cloud
#: estimating every normal cost seconds, while 2048 pooled points still give ~2048^2
#: distinct pairs. 4096 had made the normals half of a 10k-point cylinder fit (17 of 32
#: ms); 2048 fits 10k-point cylinders and cones 15-25 % faster, as accurately (40 clouds
#: each at cone SNIM 0.05 / SN 0.1 and cylinder SNIM 0.1, median axis error 0.24 / 0.31
#: / 0.11 deg against 0.23 / 0.31 / 0.13 with 4096).
NORMAL_POOL = 2048
#: Default threshold as a fraction of the cloud's bounding-box diagonal.
DEFAULT_THRESHOLD_FRACTION = 0.005


class Status(str, enum.Enum):
    """Why the hypothesis loop stopped."""

    CONVERGED = "converged"  # the confidence-based hypothesis count T was reached
    MAX_HYPOTHESES = "max_hypotheses"  # the max_hypotheses budget ran out first
    STALLED = "stalled"  # max_stall hypotheses in a row brought no better model


@dataclasses.dataclass(frozen=True)
class FitResult:
    """Outcome of ``jaxfit.fit``.

    model : the fitted, bounded primitive (in the input's coordinates).
    inliers : (N,) bool, points within ``threshold`` of the bounded model
        (``model.distance``).
    num_inliers : int.
    cost : MSAC cost sum(min(e^2, threshold^2)) of the final model over all points.
    num_hypotheses : hypotheses drawn and scored.
    status : a ``Status``.
    threshold : the inlier threshold used (the default if none was given).
    """

    model: Model
    inliers: np.ndarray
    num_inliers: int
    cost: float
    num_hypotheses: int
    status: Status
    threshold: float


#: Per-function XLA CPU options for the scoring kernel (PERF.md): together ~1.1-1.5x on
#: this machine's CPU. Passed to jax.jit so users' XLA_FLAGS stay untouched; ignored by
#: other backends. The first is experimental: if a jax version rejects any of them, the
#: kernel falls back to default options (see ``_jit_tuned``).
CPU_OPTIONS = {
    "xla_cpu_experimental_ynn_fusion_type": "",
    "xla_cpu_prefer_vector_width": 512,
    "xla_cpu_enable_fast_min_max": True,
}


def _jit_tuned(fn, static_argnames=()):
    """``stored_jit`` with CPU_OPTIONS on the CPU, and without them where they are refused."""
    plain = stored_jit(fn, static_argnames)
    if jax.default_backend() != "cpu":
        return plain
    tuned = stored_jit(fn, static_argnames, CPU_OPTIONS)
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


# ----- pure pieces --------------------------------------------------------------------


def lo_rows(n: int) -> int:
    """Points the LM steps of refinement see for clouds of at most n points: LO_POINTS,
    or the power of two (>= CHUNK) that holds n, whichever is smaller. A 500-point cloud
    sits in a 1024-row bucket; stepping on all of it spent half the work on padding
    (fit_batch of 1000 such spheres: 0.48 -> 0.33 s)."""
    return min(LO_POINTS, max(CHUNK, 1 << (n - 1).bit_length()))


def spread_rows(n_valid, count: int):
    """(count,) row indices the LM steps read: all of the first n_valid rows if they fit
    (then the rows past n_valid are padding), else count rows evenly spread over them.
    An integer stride n_valid // count left the tail of a 3000-point cloud unseen (a
    whole side of a scan stored line by line)."""
    step = jnp.maximum(jnp.asarray(n_valid, jnp.float32) / count, 1.0)
    spread = jnp.minimum((jnp.arange(count) * step).astype(jnp.int32), n_valid - 1)
    return jnp.where(n_valid >= count, spread, jnp.arange(count))


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


def bucket_size(n: int) -> int:
    """Padded point count for a cloud of n points: a power of two, at least MIN_BUCKET."""
    return max(MIN_BUCKET, 1 << (int(n) - 1).bit_length())


def required_hypotheses(inlier_ratio: float, sample_size: int, confidence: float) -> float:
    """T = log(1 - p) / log(1 - w^k): hypotheses needed to draw one all-inlier sample
    with probability ``confidence`` (p) when a fraction w of the points are inliers."""
    if inlier_ratio <= 0:
        return math.inf
    if inlier_ratio >= 1:
        return 1.0
    all_inlier = inlier_ratio**sample_size
    if all_inlier <= 0:
        return math.inf
    return math.ceil(math.log1p(-confidence) / math.log1p(-all_inlier))


def draw_samples(key, n_valid, batch_size: int, sample_size: int):
    """Indices (H, k) of H minimal samples among the first n_valid points, drawn in O(k)
    each (with replacement), and whether each sample's indices are distinct (H,)."""
    idx = uniform_indices(jax.random.bits(key, (batch_size, sample_size), jnp.uint32),
                          n_valid)
    distinct = jnp.ones(batch_size, bool)
    for i in range(sample_size):
        for j in range(i + 1, sample_size):
            distinct &= idx[:, i] != idx[:, j]
    return idx, distinct


def uniform_indices(bits, n):
    """Indices in [0, n) from uniform 32-bit words ``bits`` (any shape): exactly
    floor(bits * n / 2^32), by 16-bit halves in uint32 arithmetic (no 64-bit integers
    without x64).

    ``jax.random.randint`` draws two words per index to reduce its bias; one word gives a
    bias below n / 2^32 (2e-4 at a million points), and the RNG was a quarter of the
    kernel at 1e3 points (H = 4096).
    """
    n = jnp.asarray(n).astype(jnp.uint32)
    hi, lo = bits >> 16, bits & 0xFFFF
    n_hi, n_lo = n >> 16, n & 0xFFFF
    cross_a, cross_b = hi * n_lo, lo * n_hi
    carry = ((cross_a & 0xFFFF) + (cross_b & 0xFFFF) + ((lo * n_lo) >> 16)) >> 16
    return (hi * n_hi + (cross_a >> 16) + (cross_b >> 16) + carry).astype(jnp.int32)


def live_chunks(n_valid):
    """Scan steps that hold at least one of the first n_valid points."""
    return (n_valid + CHUNK - 1) // CHUNK


def score(cls: type[Model], thetas, valid, points, n_valid, threshold, counts: bool = True,
          gate=None, n_chunks=None):
    """MSAC costs (H,) and inlier counts (H,) of hypotheses thetas (H, P) over the first
    n_valid of points (B, 3), B a multiple of CHUNK. Invalid hypotheses cost +inf.

    Only the first ``n_chunks`` chunks of CHUNK points are scanned (default: those that
    hold the n_valid points), so the padding of a bucket costs nothing: a 1e4-point cloud
    in its 16,384 bucket scans 40 chunks, not 64 (and fit_batch's 500-point clouds in
    their 1024 bucket 2, not 4: its kernel time halved). Under ``vmap`` pass one
    unbatched ``n_chunks`` for all clouds (their largest), so the loop bound stays a
    scalar.

    ``gate`` = (normals (B, 3), min_cos): a point also needs |cos| >= min_cos between its
    normal and the surface's to count as an inlier (else it costs threshold^2). The
    surface normal comes for free as the residual's derivative along the point's normal
    (one JVP; every residual here is a distance, whose gradient has unit length).

    With ``counts=False`` only the costs are computed: the count's second reduction per
    step cost ~3x in the scan (sphere, H = 4096: 0.6 -> 1.9-3.7 billion evaluations/s
    measured side by side), so the kernel counts inliers for its few best only.
    """
    t2 = threshold * threshold
    n_chunks = live_chunks(n_valid) if n_chunks is None else n_chunks
    blocks = _blocks(thetas.shape[0])
    # One loop per block of hypotheses: independent loops, which the CPU runtime runs
    # side by side on its cores where it would not split one small loop body itself.
    parts = [_score_block(cls, block.T, points, n_valid, t2, counts, gate, n_chunks)
             for block in jnp.split(thetas, blocks)]
    cost = jnp.where(valid, jnp.concatenate([p[0] for p in parts]), jnp.inf)
    if not counts:
        return cost
    return cost, jnp.where(valid, jnp.concatenate([p[1] for p in parts]), 0)


def _blocks(hypotheses: int) -> int:
    """Independent scoring loops for H hypotheses (see ``score``)."""
    if jax.default_backend() != "cpu" or hypotheses % HYPOTHESIS_BLOCKS:
        return 1
    return HYPOTHESIS_BLOCKS if hypotheses >= BLOCK_MIN * HYPOTHESIS_BLOCKS else 1


def _score_block(cls, theta_t, points, n_valid, t2, counts, gate, n_chunks):
    """MSAC costs (H,) and inlier counts (H,) of theta_t (P, H) (see ``score``)."""

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
            r, slope = jax.jvp(lambda *c: cls.theta_residual(theta_t, c, jnp), q, m)
            r2 = jnp.where(jnp.abs(slope) >= gate[1], r * r, t2)
        cost = cost + jnp.sum(jnp.where(live, jnp.minimum(r2, t2), 0.0), axis=0)
        if counts:
            count = count + jnp.sum(live & (r2 < t2), axis=0, dtype=jnp.int32)
        return cost, count

    zero = jnp.zeros(theta_t.shape[1], points.dtype)
    return jax.lax.fori_loop(0, n_chunks, step, (zero, zero.astype(jnp.int32)))


def estimate_batch(cls: type[Model], samples, support, normals=None,
                   estimator: str = "thesis"):
    """vmap'd estimator: samples (H, k, 3), support (M, 3) and, for the oriented
    estimator, the samples' normals (H, k, 3) -> thetas (H, P), valid (H,)."""
    est = cls.estimator(estimator)
    return jax.vmap(est.estimate, in_axes=(0, 0 if est.uses_normals else None, None))(
        samples, normals if est.uses_normals else None, support)


def _batch_best(cls: type[Model], batch_size: int, points, n_valid, key, threshold,
                normals=None, estimator: str = "thesis", top: int | None = None,
                n_sample=None, limits=None, gated: bool = False, n_chunks=None):
    """The one kernel: H hypotheses from ``key`` scored on padded points (B, 3) (with
    their normals (B, 3) for the oriented estimator). Samples are drawn among the first
    ``n_sample`` points (default all n_valid). Hypotheses outside the user's ``limits``
    (7,) (see ``Model.within``) are invalid; ``gated``: scores gate on normals with
    min_cos = limits[6] (see ``score``). ``n_chunks``: as in ``score``.
    Returns the best (theta (P,), cost, inlier count) and the number of valid samples;
    with ``top`` the ``top`` best, best first: thetas (top, P), costs (top,), counts (top,).
    """
    est = cls.estimator(estimator)
    key_sample, key_support = jax.random.split(key)
    n_sample = n_valid if n_sample is None else n_sample
    idx, distinct = draw_samples(key_sample, n_sample, batch_size, est.sample_size)
    support = points[jax.random.randint(key_support, (SUPPORT,), 0, n_valid)]
    thetas, valid = estimate_batch(cls, points[idx], support,
                                   normals[idx] if est.uses_normals else None, estimator)
    valid &= distinct
    if limits is not None:
        valid &= jax.vmap(cls.within, in_axes=(0, None))(thetas, limits)
    gate = (normals, limits[6]) if gated else None
    costs = score(cls, thetas, valid, points, n_valid, threshold, counts=False, gate=gate,
                  n_chunks=n_chunks)
    _, best = jax.lax.top_k(-costs, 1 if top is None else top)
    _, counts = score(cls, thetas[best], valid[best], points, n_valid, threshold, gate=gate,
                      n_chunks=n_chunks)
    if top is None:
        return thetas[best[0]], costs[best[0]], counts[0], jnp.sum(valid)
    return thetas[best], costs[best], counts, jnp.sum(valid)


batch_best = _jit_tuned(_batch_best, static_argnames=("cls", "batch_size", "estimator",
                                                      "gated"))


def _msac(cls, theta, points, n_valid, threshold, gate=None, n_chunks=None):
    """MSAC cost and inlier count of one hypothesis theta (P,)."""
    cost, count = score(cls, theta[None], jnp.ones(1, bool), points, n_valid, threshold,
                        gate=gate, n_chunks=n_chunks)
    return cost[0], count[0]


@partial(jax.jit, static_argnames=("cls", "max_rounds", "steps", "rows"))
def refine_theta(cls: type[Model], theta, points, n_valid, threshold, max_rounds: int = 20,
                 steps: int = 10, limits=None, normals=None, n_chunks=None,
                 rows: int | None = None):
    """Local optimisation of a hypothesis theta (P,) on padded points (B, 3).

    Each round takes the current inliers (within LO_WIDEN thresholds) and runs ``steps``
    Levenberg-Marquardt steps on their signed geometric residuals (projected back with
    ``cls.canonicalize``), or the shape's closed-form ``least_squares`` fit to them where
    it has one (the plane). Rounds go on while they lower the MSAC cost over all points
    (at most ``max_rounds``), so the inlier set can grow from a rough hypothesis to the
    whole surface, and refinement never makes the model worse by the loop's own measure.
    The steps see ``rows`` points (default and at most LO_POINTS; see ``lo_rows`` and
    ``spread_rows``). A step that would leave the user's ``limits`` (7,)
    (``Model.within``) is refused. With ``normals`` (B, 3), inliers are gated on them
    with min_cos = limits[6] (see ``score``).
    ``n_chunks``: as in ``score``.
    Returns the refined theta, its MSAC cost and inlier count.
    """
    rows = spread_rows(n_valid, min(points.shape[0], LO_POINTS if rows is None else rows))
    live = rows < n_valid
    sub = points[rows]
    p = (sub[:, 0], sub[:, 1], sub[:, 2])
    gate = None if normals is None else (normals, limits[6])

    def agrees(th):  # the gate of ``score`` on the LM points, (S,) bool
        if gate is None:
            return True
        m = normals[rows]
        _, slope = jax.jvp(lambda *c: cls.theta_residual(th, c, jnp), p,
                           (m[:, 0], m[:, 1], m[:, 2]))
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
        if limits is not None:
            better &= cls.within(candidate, limits)
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
        new_cost = _msac(cls, candidate, points, n_valid, threshold, gate, n_chunks)[0]
        better = new_cost < cost * (1.0 - LO_GAIN)
        if limits is not None:
            better &= cls.within(candidate, limits)
        return (jnp.where(better, candidate, th), jnp.where(better, new_cost, cost), better,
                rounds + 1)

    def going(carry):
        return carry[2] & (carry[3] < max_rounds)

    cost = _msac(cls, theta, points, n_valid, threshold, gate, n_chunks)[0]
    theta, _, _, _ = jax.lax.while_loop(going, lo_round, (theta, cost, True, 0))
    return (theta, *_msac(cls, theta, points, n_valid, threshold, gate, n_chunks))


# ----- host side ----------------------------------------------------------------------


def _normalise(points: np.ndarray, bounds=None):
    """Centre (3,) and scale that map the cloud into the unit ball; ``bounds``: the
    cloud's (lo, hi) if already known."""
    lo, hi = column_bounds(points) if bounds is None else bounds
    center = 0.5 * (lo + hi)
    scale = float(row_norms(points - center).max())
    if not scale > 0:
        raise ValueError("all points coincide: there is no shape to fit")
    return center, scale


def _padded(rows: np.ndarray, dtype, size: int | None = None):
    n = rows.shape[0]
    out = np.zeros((size or bucket_size(n), 3), dtype=dtype)
    out[:n] = rows
    return out


def _batch_best_many(cls, batch_size, estimator, points, normals, n_valid, n_sample,
                     cloud_keys, threshold, limits, batch, gated=False):
    """``batch_best`` for every cloud: points (C, B, 3), normals (C, B, 3) or None,
    n_valid (C,), n_sample (C,), cloud_keys (C,), threshold (C,), limits (C, 7);
    batch b of cloud c uses fold_in(cloud_keys[c], b)."""

    n_chunks = live_chunks(jnp.max(n_valid))  # one loop bound for all clouds

    def one(args):
        p, nrm, n, m, k, t, lim = args
        return _batch_best(cls, batch_size, p, n, jax.random.fold_in(k, batch), t, nrm,
                           estimator, cls.lo_starts, m, lim, gated, n_chunks)

    return jax.lax.map(one, (points, normals, n_valid, n_sample, cloud_keys, threshold,
                             limits),
                       batch_size=_group(points.shape[0], CHUNK * batch_size))


_batch_best_many = _jit_tuned(_batch_best_many,
                              static_argnames=("cls", "batch_size", "estimator", "gated"))


def _fold_in_each(key, indices):
    """fold_in(key, i) for each i of indices (S,)."""
    return jax.vmap(jax.random.fold_in, in_axes=(None, 0))(key, indices)


def _seed_keys(seed, slots: int):
    """``_fold_in_each`` of jax.random.key(seed) (a uint32 seed) over range(slots)."""
    return _fold_in_each(jax.random.key(seed), jnp.arange(slots, dtype=jnp.int32))


_keys_of_key = stored_jit(_fold_in_each)
_keys_of_seed = stored_jit(_seed_keys, ("slots",))


def _cloud_keys(key, slots: int):
    """fold_in(key, i) for the clouds i < slots: cloud i's key (see ``fit_batch``)."""
    return _keys_of_key(key, np.arange(slots, dtype=np.int32))


@functools.lru_cache(maxsize=256)
def _seed_cloud_keys(seed: int, impl: str, slots: int):
    """``_cloud_keys`` of ``jax.random.key(seed)``, in one dispatch (making the key and
    folding it had been two: a fit with a new int seed spent 170 us on its keys, 20 % of
    a 500-point sphere fit; now ~25 us) and kept for the seed. Keys are immutable;
    ``impl`` keys the cache on JAX's PRNG setting."""
    return _keys_of_seed(np.uint32(seed), slots)


def _group(clouds: int, elements: int) -> int:
    """Clouds processed side by side (vmap) inside the map over clouds: as many as keep
    one scan step's (clouds, elements) block within GROUP_ELEMENTS, a divisor of clouds.
    One vmap over hundreds of clouds spills every step out of cache (measured: 0.12
    billion evaluations/s at 256 clouds against 0.7 at 16)."""
    group = max(1, min(clouds, GROUP_ELEMENTS // elements))
    while clouds % group:
        group -= 1
    return group


def _refine_many(cls, thetas, points, n_valid, threshold, limits, normals=None, rows=None):
    """refine_theta for each cloud's ``cls.lo_starts`` hypotheses thetas (C, S, P), gated on
    normals (C, B, 3) if given; returns the best refined theta (C, P), its cost (C,) and
    inlier count (C,) per cloud."""

    n_chunks = live_chunks(jnp.max(n_valid))  # one loop bound for all clouds

    def refine(theta, p, n, t, lim, nrm):
        return refine_theta(cls, theta, p, n, t, limits=lim, normals=nrm, n_chunks=n_chunks,
                            rows=rows)

    starts = jax.vmap(refine, in_axes=(0, None, None, None, None, None))
    # A while_loop under vmap runs until its slowest member stops: small groups keep
    # one slow cloud from holding all the others for max_rounds.
    theta, cost, count = jax.lax.map(lambda a: starts(*a),
                                     (thetas, points, n_valid, threshold, limits, normals),
                                     batch_size=_group(points.shape[0], points.shape[1] * 64))
    best = jnp.argmin(cost, axis=1)[:, None]
    pick = lambda a: jnp.take_along_axis(a, best.reshape(best.shape + (1,) * (a.ndim - 2)),  # noqa: E731
                                          axis=1)[:, 0]
    return pick(theta), pick(cost), pick(count)


_refine_many = stored_jit(_refine_many, ("cls", "rows"))


@dataclasses.dataclass
class _Cloud:
    """One validated cloud, in the normalised frame the kernels see."""

    points: np.ndarray  # (N, 3) float64, as given
    # (M, 3) unit normals of points[pool] (all N points without a pool), kept when the
    # estimator or the normal gate reads them
    normals: np.ndarray | None
    pool: np.ndarray | None  # (M,) indices samples are drawn from (None: all points)
    center: np.ndarray
    scale: float
    threshold: float  # in the cloud's units
    limits: np.ndarray  # (7,) the user's bounds (limits_for), in the cloud's units
    wanted: np.ndarray | None = None  # indices whose normals are still to be estimated

    @property
    def gated(self) -> bool:
        return self.limits[6] > -1

    @functools.cached_property
    def unit(self):
        return (self.points - self.center) / self.scale

    def unit_limits(self):
        """The limits in the normalised frame: radii scale, directions do not."""
        return np.concatenate([self.limits[:2] / self.scale, self.limits[2:]])

    def kernel_rows(self):
        """Unit points (N, 3) with the pool first, the pool's normals (M, 3) or None,
        and M: the kernel draws samples among the first M rows and scores all."""
        if self.pool is None:
            return self.unit, self.normals, len(self.points)
        rest = np.setdiff1d(np.arange(len(self.points)), self.pool, assume_unique=True)
        return self.unit[np.concatenate([self.pool, rest])], self.normals, len(self.pool)


def _normals_key(key, cloud: int):
    """The key choosing cloud i's normal pool: a stream apart from its batches' keys
    fold_in(fold_in(key, i), b)."""
    return jax.random.fold_in(jax.random.fold_in(key, cloud), 0x6E6F726D)


def limits_for(cls: type[Model], radius_range=None, axis_prior=None,
               normal_angle=None) -> np.ndarray:
    """The user's bounds as the (7,) vector the kernel reads, with clear errors:
    ``Model.within`` reads the first six, the normal gate (``score``) the last.

    radius_range : None or (low, high), 0 <= low < high (sphere, cylinder).
    axis_prior : None or (direction (3,), max_angle_deg in (0, 90]): the axis (the
        normal, for a plane) within that angle of the direction, either sign (plane,
        cylinder, cone).
    normal_angle : None or degrees in (0, 90]: a point is an inlier only if its normal is
        within that angle of the surface's (either sign).
    """
    limits = np.array([0.0, np.inf, 0.0, 0.0, 1.0, 0.0, -2.0])  # -2: no gate
    if normal_angle is not None:
        if (isinstance(normal_angle, bool) or not isinstance(normal_angle, numbers.Real)
                or not 0 < normal_angle <= 90):
            raise ValueError(f"normal_angle must be in (0, 90] degrees, got {normal_angle!r}")
        limits[6] = np.cos(np.radians(float(normal_angle)))
    if radius_range is not None:
        if cls.radius_index is None:
            raise ValueError(f"radius_range does not apply to a {cls.name} (sphere, cylinder)")
        low, high = (float(v) for v in radius_range)
        if not 0 <= low < high:
            raise ValueError(f"radius_range must be (low, high) with 0 <= low < high, got "
                             f"{radius_range!r}")
        limits[:2] = low, high
    if axis_prior is not None:
        if cls.axis_index is None:
            raise ValueError(f"axis_prior does not apply to a {cls.name} "
                             "(plane, cylinder, cone)")
        direction, angle = axis_prior
        direction = np.asarray(direction, np.float64).reshape(-1)
        length = np.linalg.norm(direction) if direction.shape == (3,) else np.nan
        if not (np.isfinite(length) and length > 0):
            raise ValueError(f"axis_prior direction must be a non-zero finite 3-vector, got "
                             f"{axis_prior[0]!r}")
        if not 0 < float(angle) <= 90:
            raise ValueError(f"axis_prior angle must be in (0, 90] degrees, got {angle!r}")
        limits[2:5] = direction / length
        limits[5] = np.cos(np.radians(float(angle)))
    return limits


def _prepare(points, cls, normals, threshold, est, key, index, limits) -> _Cloud:
    """Cloud ``index`` of a call, validated; ``key`` is the call's (see ``_normals_key``).
    Normals the fit needs and was not given are left for ``_estimate_normals``: its
    ``normals`` is None and ``wanted`` holds the indices to estimate them at."""
    cloud = _checks.points_for(points, cls)
    normals = _checks.normals_for(normals, cloud)
    lo, hi = column_bounds(cloud)
    center, scale = _normalise(cloud, (lo, hi))
    if threshold is None:
        threshold = DEFAULT_THRESHOLD_FRACTION * np.linalg.norm(hi - lo)
    threshold = _checks.positive(threshold, "threshold")
    pool = wanted = None
    gated = limits[6] > -1
    if not (est.uses_normals or gated):
        normals = None
    elif normals is None and gated:  # the gate reads every point's normal
        wanted = np.arange(len(cloud))
    elif normals is None:
        if len(cloud) > NORMAL_POOL:
            # Derived here only: two fold_ins per cloud cost ~0.6 ms, more than a whole
            # kernel call for a small cloud in fit_batch.
            pool_key = jax.random.key_data(_normals_key(_checks.prng_key(key), index))
            rng = np.random.default_rng(np.asarray(pool_key))
            pool = np.sort(rng.choice(len(cloud), NORMAL_POOL, replace=False))
        wanted = np.arange(len(cloud)) if pool is None else pool
    return _Cloud(cloud, normals, pool, center, scale, threshold, limits, wanted)


def _estimate_normals(clouds: list[_Cloud]):
    """Fill in the normals ``_prepare`` left wanted, for all clouds in one batched call
    (scipy's KD-tree: imported only when needed)."""
    todo = [c for c in clouds if c.wanted is not None]
    if todo:
        from .normals import normals_at_many

        found = normals_at_many([c.points for c in todo], [c.wanted for c in todo],
                                [min(16, len(c.points)) for c in todo])
        for cloud, normals in zip(todo, found, strict=True):
            cloud.normals, cloud.wanted = normals, None


def fit(
    points,
    shape,
    *,
    normals=None,
    threshold: float | None = None,
    confidence: float = 0.99,
    max_hypotheses: int = 100_000,
    batch_size: int = 256,
    max_stall: int = 20_000,
    min_hypotheses: int | None = None,
    refine: bool = True,
    estimator: str | None = None,
    radius_range=None,
    axis_prior=None,
    normal_angle: float | None = None,
    key=0,
) -> FitResult:
    """Fit one primitive to a point cloud with batched RANSAC and MSAC scoring.

    Parameters
    ----------
    points : (N, 3) array-like of finite coordinates.
    shape : "plane", "sphere", "cylinder", "cone", "box", or the model class.
    normals : optional (N, 3) normals (any length, any sign), read by the oriented
        estimators. When such an estimator runs and none are given, they are estimated
        from the points (``jaxfit.estimate_normals``).
    threshold : inlier distance, in the points' units. Default: 0.5 % of the diagonal of
        the cloud's axis-aligned bounding box.
    confidence : probability p of having drawn one all-inlier sample when stopping.
    max_hypotheses : budget of hypotheses (rounded up to whole batches).
    batch_size : hypotheses per kernel call (H); each value compiles its own kernel. 256
        gave the shortest time to solution on average (benchmarks/solution.py: 128-1024
        compared on plane, sphere and cylinder clouds of 1e3-1e5 points).
    max_stall : stop after this many hypotheses without a better model.
    min_hypotheses : floor on the confidence-based count T; default the estimator's own
        (the thesis's cylinder 8192 and cone 16384, else none).
        ``min_hypotheses=max_hypotheses`` (with a large ``max_stall``) runs a fixed number.
    refine : local optimisation (LO-RANSAC): each new best hypothesis is refitted on its
        inliers by Levenberg-Marquardt, its inliers reclassified, until the MSAC cost
        stops falling; the stopping rule then uses the refined inlier count.
    estimator : "thesis" (the thesis's minimal samples: plane 3, sphere 4, cylinder 3,
        cone 4, box 5 points) or "oriented" (points with normals: sphere 2, cylinder 2,
        cone 3, box 2; the plane has no oriented estimator and uses the thesis's).
        Default: the best measured per shape, ``Model.default_estimator``: oriented for
        the cylinder, cone and box, thesis for the plane and sphere.
    radius_range : optional (low, high) in the points' units (sphere, cylinder): every
        hypothesis outside it is discarded and refinement never leaves it.
    axis_prior : optional (direction (3,), max_angle_deg): the axis (a plane's normal)
        must stay within that angle of the direction, either sign (plane, cylinder,
        cone), before and after refinement.
    normal_angle : optional degrees in (0, 90]: a point counts as an inlier (in scoring,
        refinement and the result) only if its normal is within that angle of the
        surface's, either sign. Uses ``normals``, estimated for every point if not given.
    key : int seed or JAX PRNG key. ``fit(points, ...)`` equals
        ``fit_batch([points], ...)[0]``: batch b uses ``fold_in(fold_in(key, 0), b)``.

    Returns
    -------
    FitResult
    """
    return fit_batch(
        [points], shape, normals=None if normals is None else [normals], thresholds=threshold,
        confidence=confidence, max_hypotheses=max_hypotheses, batch_size=batch_size,
        max_stall=max_stall, min_hypotheses=min_hypotheses, refine=refine,
        estimator=estimator, radius_range=radius_range, axis_prior=axis_prior,
        normal_angle=normal_angle, key=key,
    )[0]


def fit_batch(
    clouds,
    shape,
    *,
    normals=None,
    thresholds=None,
    confidence: float = 0.99,
    max_hypotheses: int = 100_000,
    batch_size: int = 256,
    max_stall: int = 20_000,
    min_hypotheses: int | None = None,
    refine: bool = True,
    estimator: str | None = None,
    radius_range=None,
    axis_prior=None,
    normal_angle: float | None = None,
    key=0,
    skip_failures: bool = False,
) -> list[FitResult | None]:
    """Fit one primitive to each of several clouds, all in the same compiled calls.

    The clouds are padded to one point bucket (and their count to a power of two) and
    each kernel call scores H hypotheses for every cloud at once; each cloud keeps its own
    stopping state, exactly as ``fit`` would (``fit`` is this with one cloud).

    Parameters
    ----------
    clouds : sequence of (N_i, 3) arrays.
    normals : None or a sequence of (N_i, 3) arrays (or None entries), as in ``fit``.
    thresholds : None, one float for all clouds, or one per cloud (None entries take
        each cloud's default).
    key : cloud i uses ``fold_in(key, i)``.
    skip_failures : give None for a cloud on which no model can be fitted instead of
        raising ``FitError``. Invalid input always raises.
    Other parameters as in ``fit``.

    Returns
    -------
    list of FitResult (or None), one per cloud.
    """
    cls = _checks.model_class(shape)
    est = cls.estimator(estimator)
    clouds = list(clouds)
    if not clouds:
        raise ValueError("clouds is empty: give at least one (N, 3) array")
    if normals is not None and len(normals) != len(clouds):
        raise ValueError(f"normals must be one array per cloud ({len(clouds)}), got {len(normals)}")
    if thresholds is None or isinstance(thresholds, numbers.Real):
        thresholds = [thresholds] * len(clouds)
    if len(thresholds) != len(clouds):
        raise ValueError(f"thresholds must be one per cloud ({len(clouds)}), got {len(thresholds)}")
    seed = _checks.seed_of(key)
    if seed is None:  # (an int seed becomes a key only where one is needed: ~50 us)
        key = _checks.prng_key(key)
    limits = limits_for(cls, radius_range, axis_prior, normal_angle)
    prepared = []
    for i, points in enumerate(clouds):
        try:
            prepared.append(_prepare(points, cls, None if normals is None else normals[i],
                                     thresholds[i], est, key, i, limits))
        except ValueError as err:
            raise type(err)(f"cloud {i}: {err}" if len(clouds) > 1 else str(err)) from None
    confidence = _checks.probability(confidence, "confidence")
    max_hypotheses = _checks.positive(max_hypotheses, "max_hypotheses", integer=True)
    batch_size = _checks.positive(batch_size, "batch_size", integer=True)
    max_stall = _checks.positive(max_stall, "max_stall", integer=True)
    if min_hypotheses is None:
        min_hypotheses = est.min_hypotheses
    elif not (isinstance(min_hypotheses, int) and min_hypotheses >= 0):
        raise ValueError(f"min_hypotheses must be a non-negative integer, got {min_hypotheses!r}")
    _estimate_normals(prepared)

    thetas, drawn, status = _search(cls, est, prepared, key, seed, confidence, max_hypotheses,
                                    batch_size, max_stall, min_hypotheses, refine)
    results = []
    for i, cloud in enumerate(prepared):
        try:
            results.append(_result(cls, cloud, thetas[i], drawn[i], status[i]))
        except _checks.FitError:
            if not skip_failures:
                raise
            results.append(None)
    return results


def _placer(devices):
    """How the host loop puts per-cloud arrays (clouds first) on the devices: split along
    the cloud axis over all local devices (GPUs, or CPU devices forced with
    ``--xla_force_host_platform_device_count``), so every jitted call below runs on all
    of them; on one device, plain arrays."""
    if len(devices) == 1:
        return lambda array: array  # jit takes NumPy arrays on its fast path
    mesh = jax.sharding.Mesh(np.asarray(devices), ("clouds",))
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("clouds"))
    return lambda array: jax.device_put(array, sharding)


def _search(cls, est, clouds, key, seed, confidence, max_hypotheses, batch_size, max_stall,
            min_hypotheses, refine):
    """The host loop over batches for all clouds in lockstep.

    Returns the best theta (C, P) per cloud (NaN where none was valid), hypotheses drawn
    (C,) and the Status (C,) of each cloud.
    """
    count = len(clouds)
    devices = jax.local_devices()
    # Pad the cloud count to a power of two (fewer compilations) and to whole devices.
    slots = max(1 << (count - 1).bit_length(), len(devices))
    slots = -(-slots // len(devices)) * len(devices)
    n_max = max(c.points.shape[0] for c in clouds)
    size = bucket_size(n_max)
    dtype = jax.dtypes.canonicalize_dtype(np.float64)  # float32 unless x64 is on
    order = list(range(count)) + [0] * (slots - count)  # padding slots repeat cloud 0
    put = _placer(devices)
    built = [cloud.kernel_rows() for cloud in clouds]  # padding slots reuse cloud 0's
    rows = [built[i] for i in order]
    gated = clouds[0].gated  # one normal_angle for all clouds of a call
    host = {  # per-slot arrays, clouds first
        "points": np.stack([_padded(unit, dtype, size) for unit, _, _ in rows]),
        "normals": (np.stack([_padded(nrm, dtype, size) for _, nrm, _ in rows])
                    if est.uses_normals or gated else None),
        "n": np.asarray([clouds[i].points.shape[0] for i in order], np.int32),
        "n_sample": np.asarray([m for _, _, m in rows], np.int32),
        "keys": (_cloud_keys(key, slots) if seed is None
                 else _seed_cloud_keys(seed, jax.config.jax_default_prng_impl, slots)),
        "threshold": np.asarray([clouds[i].threshold / clouds[i].scale for i in order], dtype),
        "limits": np.stack([clouds[i].unit_limits() for i in order]).astype(dtype),
    }
    every = {name: None if a is None else put(a) for name, a in host.items()}

    def on(slots_of):
        """The per-slot arrays for the rows ``slots_of`` (None: every slot), placed."""
        if slots_of is None:
            return every
        return {name: None if a is None else put(a[slots_of]) for name, a in host.items()}

    best_theta = np.full((slots, cls.num_params), np.nan)
    best_cost, best_raw = np.full(slots, np.inf), np.full(slots, np.inf)
    best_count = np.zeros(slots)
    last_improvement = np.zeros(slots, int)
    drawn = np.zeros(slots, int)
    status = np.array([Status.MAX_HYPOTHESES] * slots, dtype=object)
    active = np.arange(slots) < count
    batch = 0
    while active.any() and batch * batch_size < max_hypotheses:
        searching = subset_rows(active, len(devices))
        a = on(searching)
        theta, cost, found, _ = _batch_best_many(cls, batch_size, est.name, a["points"],
                                                 a["normals"], a["n"], a["n_sample"],
                                                 a["keys"], a["threshold"], a["limits"],
                                                 batch, gated)
        where = np.arange(slots) if searching is None else searching  # slot of each row
        batch += 1
        drawn[active] = batch * batch_size
        # LO-RANSAC: polish every so-far-best raw hypothesis (compared with raw ones only,
        # so a rough but right one is not hidden behind a polished wrong one).
        raw = np.full(slots, np.inf)
        raw[where] = np.asarray(cost, np.float64)[:, 0]  # (sliced on the host: see below)
        improved = active & (raw < best_raw)
        best_raw = np.where(improved, raw, best_raw)
        if refine and improved.any():
            polishing = subset_rows(improved, len(devices))
            if polishing is not None:  # (else every slot: the kernel ran on all of them)
                row = np.full(slots, -1)
                row[where[::-1]] = np.arange(len(where))[::-1]  # first row of each slot
                theta, a = put(np.asarray(theta)[row[polishing]]), on(polishing)
            theta, cost, found = _refine_many(cls, theta, a["points"], a["n"], a["threshold"],
                                              a["limits"], a["normals"] if gated else None,
                                              lo_rows(n_max))
            where = np.arange(slots) if polishing is None else polishing
        else:
            # (indexing on the host: a JAX slice per array cost ~0.2 ms each)
            theta, cost, found = (np.asarray(x)[:, 0] for x in (theta, cost, found))
        full = np.full((slots, cls.num_params), np.nan), np.full(slots, np.inf), np.zeros(slots)
        for out, value in zip(full, (theta, cost, found), strict=True):
            out[where] = np.asarray(value)
        theta, cost, found = full
        better = improved & (cost < best_cost)
        best_theta[better], best_cost[better] = theta[better], cost[better]
        best_count[better] = found[better]
        last_improvement[better] = batch * batch_size
        for i in np.flatnonzero(active):
            ratio = best_count[i] / clouds[i].points.shape[0]
            needed = max(required_hypotheses(ratio, est.sample_size, confidence), min_hypotheses)
            if drawn[i] >= needed:
                status[i], active[i] = Status.CONVERGED, False
            elif drawn[i] - last_improvement[i] >= max_stall:
                status[i], active[i] = Status.STALLED, False
    return best_theta[:count], drawn[:count], status[:count]


def _result(cls, cloud: _Cloud, theta, drawn, status) -> FitResult:
    if not np.all(np.isfinite(theta)):
        raise _checks.FitError(
            f"no valid {cls.name} hypothesis in {drawn} samples: the points are degenerate "
            f"for a {cls.name} (coincident, collinear or coplanar)"
        )
    unit_threshold = cloud.threshold / cloud.scale
    theta = np.asarray(theta, np.float64)
    agree = _agreeing(cls, theta, cloud)
    model = _bounded(cls, theta, cloud.unit, unit_threshold, agree)
    model = model.rescaled(cloud.scale, cloud.center)
    # Final inliers are judged against the bounded primitive the user gets back.
    distance = model.distance(cloud.points)
    inliers = (distance < cloud.threshold) & agree
    distance = np.where(agree, distance, np.inf)
    cost = float(np.sum(np.minimum(distance**2, cloud.threshold**2)))
    return FitResult(model, inliers, int(inliers.sum()), cost, int(drawn), status,
                     cloud.threshold)


def _agreeing(cls, theta, cloud: _Cloud):
    """(N,) whether each point passes the normal gate of hypothesis theta (normalised
    frame): the kernel's JVP as a central difference, in float64 NumPy."""
    if not cloud.gated:
        return np.ones(len(cloud.points), bool)
    unit, step = cloud.unit, 1e-6
    ahead, back = (cls.theta_residual(theta, tuple((unit + s * cloud.normals).T), np)
                   for s in (step, -step))
    return np.abs(ahead - back) / (2 * step) >= cloud.limits[6]


def _bounded(cls, theta, unit, unit_threshold, agree=True):
    """The bounded model from a hypothesis, in the normalised frame (float64), bounded by
    the points near its surface (and passing the normal gate, ``agree`` (N,))."""
    residual = cls.theta_residual(theta, (unit[:, 0], unit[:, 1], unit[:, 2]), np)
    inliers = (np.abs(residual) < unit_threshold) & agree
    if not inliers.any():
        raise _checks.FitError(f"the best {cls.name} hypothesis has no inliers")
    return cls.from_theta(theta, unit, inliers, unit_threshold)
