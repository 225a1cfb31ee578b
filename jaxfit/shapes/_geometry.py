"""Small geometric helpers shared by the estimators (JAX) and the models (NumPy).

Every function here is branch-free and NaN-free for any finite input, so it can run
inside ``vmap`` on degenerate samples: callers get a validity flag instead of an error.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

# Relative tolerance for degenerate samples. Points are normalised to the unit ball by
# the engine, so an absolute floor on lengths is meaningful too.
SIN_TOL = 1e-4
LEN_TOL = 1e-6
# Hypotheses whose radius/apex lies this far outside the unit ball are useless for a
# normalised cloud (an almost-flat sample gives a huge sphere); they are masked.
MAX_EXTENT = 10.0
# A gap of this many thresholds along a fitted surface separates its points from strays
# (outliers near the surface's unbounded continuation) when bounds are fixed.
GAP_THRESHOLDS = 5.0
#: Values expected per bin of ``main_interval`` at least, over the values' central 90 %:
#: bins of GAP_THRESHOLDS alone held a few points each on sparse clouds at tight
#: thresholds, and their chance gaps cut the bounds (docs/shapes.md).
MIN_PER_BIN = 16


def safe_norm(v, axis=-1, xp=jnp):
    """Euclidean norm whose gradient stays finite at 0. v : (..., 3) -> (...)."""
    sq = xp.sum(v * v, axis=axis)
    return xp.sqrt(xp.where(sq > 0, sq, 1.0)) * (sq > 0)


def safe_normalize(v, xp=jnp):
    """Unit vector along v (..., 3) and its length; a zero vector maps to +z (``xp``:
    jax.numpy or numpy)."""
    n = safe_norm(v, xp=xp)
    ok = n > 0
    fallback = xp.asarray([0.0, 0.0, 1.0], v.dtype)
    unit = xp.where(ok[..., None], v / xp.where(ok, n, 1.0)[..., None], fallback)
    return unit, n


def triangle(a, b, c):
    """Plane of three points (3,) each: unit normal along (b - a) x (c - a), and whether
    the points are distinct and not collinear. Also returns the edges u, v and u x v."""
    u, v = b - a, c - a
    w = jnp.cross(u, v)
    lu, lv, lw = safe_norm(u), safe_norm(v), safe_norm(b - c)
    valid = (safe_norm(w) > SIN_TOL * lu * lv) & (jnp.minimum(jnp.minimum(lu, lv), lw) > LEN_TOL)
    normal, _ = safe_normalize(w)
    return normal, valid, (u, v, w)


def closest_points(p1, d1, p2, d2):
    """Closest points of the lines p1 + s d1 and p2 + t d2 (all (3,)), and whether the
    lines are far from parallel (|d1 x d2| > SIN_TOL |d1| |d2|)."""
    a11, a12, a22 = jnp.dot(d1, d1), jnp.dot(d1, d2), jnp.dot(d2, d2)
    gap = p2 - p1
    b1, b2 = jnp.dot(d1, gap), jnp.dot(d2, gap)
    det = a11 * a22 - a12 * a12  # = |d1 x d2|^2
    valid = det > (SIN_TOL * SIN_TOL) * a11 * a22
    det = jnp.where(valid, det, 1.0)
    s, t = (a22 * b1 - a12 * b2) / det, (a12 * b1 - a11 * b2) / det
    return p1 + s * d1, p2 + t * d2, valid


def circle3(a, b, c):
    """Circle through three points (3,) each.

    Returns (centre (3,), unit normal (3,), radius (), valid ()): the circumcircle of the
    triangle in its own plane, with normal (b - a) x (c - a).
    """
    normal, valid, (u, v, w) = triangle(a, b, c)
    denom = jnp.where(valid, 2.0 * jnp.dot(w, w), 1.0)
    offset = (jnp.dot(u, u) * jnp.cross(v, w) + jnp.dot(v, v) * jnp.cross(w, u)) / denom
    radius = safe_norm(offset)
    return a + offset, normal, radius, valid & (radius < MAX_EXTENT)


def inverse_transpose3(m, xp=jnp):
    """inv(m).T of (3, 3) matrices m (..., 3, 3): their cofactors (row i the cross product
    of rows i + 1 and i + 2) over their determinants; no LAPACK call (``xp``: jax.numpy
    or numpy). A singular m gives inf or NaN, as an inverse would."""
    # Rows and columns rolled, whole arrays at a time: as ``cross`` of rows or entry by
    # entry, the box's refinement compiled XLA fusions by the dozen.
    after, second = _roll3(m, 1, -2, xp), _roll3(m, 2, -2, xp)
    cof = (_roll3(after, 1, -1, xp) * _roll3(second, 2, -1, xp)
           - _roll3(after, 2, -1, xp) * _roll3(second, 1, -1, xp))
    return cof / xp.sum(m[..., 0, :] * cof[..., 0, :], axis=-1)[..., None, None]


def _roll3(a, by: int, axis: int, xp):
    """``xp.roll(a, -by, axis)`` of a length-3 axis; in NumPy by ``take`` (the same
    entries: ``np.roll``'s own checks were most of a box's float64 refit)."""
    if xp is np:
        return a.take((by, (by + 1) % 3, (by + 2) % 3), axis=axis)
    return xp.roll(a, -by, axis=axis)


def weighted_scatter(points, weights):
    """The weighted centroid (3,) of points (N, 3) with weights (N,) (JAX; a positive
    sum), and their weighted scatter matrix about it (3, 3): sum_i w_i d_i d_i^T.

    Column by column, six sums of products: as a (3, N) x (N, 3) product, XLA's CPU runs
    one tiny matrix product per cloud and start under ``vmap`` (the plane's refinement
    of 1000 clouds 2x slower: docs/engine.md, "Session 20")."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    total = jnp.sum(weights)
    cx, cy, cz = jnp.sum(weights * x) / total, jnp.sum(weights * y) / total, \
        jnp.sum(weights * z) / total
    dx, dy, dz = x - cx, y - cy, z - cz
    wx, wy, wz = weights * dx, weights * dy, weights * dz
    xx, yy, zz = jnp.sum(wx * dx), jnp.sum(wy * dy), jnp.sum(wz * dz)
    xy, xz, yz = jnp.sum(wx * dy), jnp.sum(wx * dz), jnp.sum(wy * dz)
    scatter = jnp.stack([jnp.stack([xx, xy, xz]), jnp.stack([xy, yy, yz]),
                         jnp.stack([xz, yz, zz])])
    return jnp.stack([cx, cy, cz]), scatter


#: Cyclic Jacobi sweeps of ``smallest_eigenvector``: each squares the off-diagonal part
#: (three sweeps from a diagonal-free start already reach float32's resolution).
JACOBI_SWEEPS = 5


def smallest_eigenvector(a):
    """The unit eigenvector (3,) of the least eigenvalue of a symmetric (3, 3) matrix a
    (JAX), by cyclic Jacobi rotations: no LAPACK call (``jnp.linalg.eigh`` is one on the
    CPU). Sign arbitrary; for a repeated least eigenvalue any vector of its space.

    Each rotation updates the entries it changes, as scalars: one elementwise fusion a
    sweep, where products of rotation matrices were nine small dots (docs/engine.md,
    "Session 34")."""

    def rotate(m, v, i, j):
        # The rotation P in the (i, j) plane that zeroes m[i, j], m <- P^T m P and
        # v <- v P (Golub & Van Loan 8.5.2; P[i, i] = P[j, j] = c, P[i, j] = s = -P[j, i]).
        # m: the upper triangle's entries keyed (row, column); v: its columns keyed by index.
        k = 3 - i - j  # (the third index)
        mij = m[i, j]
        tau = m[j, j] - m[i, i]
        denominator = jnp.abs(tau) + jnp.sqrt(tau * tau + 4.0 * mij * mij)
        t = jnp.where(denominator > 0, 2.0 * mij * jnp.where(tau >= 0, 1.0, -1.0)
                      / jnp.where(denominator > 0, denominator, 1.0), 0.0)
        c = 1.0 / jnp.sqrt(1.0 + t * t)
        s = t * c
        ik, jk = _pair(i, k), _pair(j, k)
        m = {**m, (i, i): m[i, i] - t * mij, (j, j): m[j, j] + t * mij,
             (i, j): jnp.zeros_like(mij), ik: c * m[ik] - s * m[jk],
             jk: s * m[ik] + c * m[jk]}
        v = {**v, i: c * v[i] - s * v[j], j: s * v[i] + c * v[j]}
        return m, v

    def sweep(_, state):
        m, v = state
        for i, j in ((0, 1), (0, 2), (1, 2)):
            m, v = rotate(m, v, i, j)
        return m, v

    upper = {(i, j): a[i, j] for i in range(3) for j in range(i, 3)}
    eye = jnp.eye(3, dtype=a.dtype)
    columns = {i: eye[:, i] for i in range(3)}
    m, v = jax.lax.fori_loop(0, JACOBI_SWEEPS, sweep, (upper, columns))
    diagonal = jnp.stack([m[i, i] for i in range(3)])
    return jnp.stack([v[i] for i in range(3)], axis=1)[:, jnp.argmin(diagonal)]


def _pair(i: int, j: int) -> tuple[int, int]:
    """The upper-triangle key (min, max) of entry (i, j) of a symmetric matrix."""
    return (i, j) if i <= j else (j, i)


#: The coordinate axes, rows (read-only): ``frame``'s helpers.
_EYE = np.eye(3)
_EYE.flags.writeable = False


def frame(axis):
    """Right-handed rotation (3, 3) whose third column is the unit vector ``axis`` (3,).

    NumPy, deterministic: the first column is the axis crossed with the coordinate axis
    least aligned with it, so nearby axes give nearby frames.
    """
    axis = np.asarray(axis, dtype=np.float64)
    x = cross3(_EYE[np.abs(axis).argmin()], axis)
    x /= math.sqrt(x @ x)
    out = np.empty((3, 3))  # (by column: with np.eye and np.stack it took 21 against 12 us)
    out[:, 0], out[:, 1], out[:, 2] = x, cross3(axis, x), axis
    return out


def cross3(a, b):
    """Cross product (3,) of two 3-vectors (NumPy), without ``np.cross``'s general-axis
    machinery, which costs more than the arithmetic (docs/shapes.md)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def transform(rotation, translation):
    """4x4 homogeneous matrix from a (3, 3) rotation and a (3,) translation."""
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = translation
    return m


def column_bounds(points):
    """(lowest (D,), highest (D,)) of each column of points (N, D), N >= 1, reduced over
    contiguous columns: NumPy's axis-0 reductions of an (N, 3) array stride through it
    with an inner loop of length 3 (0.65 ms a bound on 23k points, against ~0.03 ms for
    the copy and both bounds; docs/shapes.md)."""
    columns = np.ascontiguousarray(points.T)
    return columns.min(axis=1), columns.max(axis=1)


def rows(columns):
    """columns (D, N) as a C-contiguous (N, D) array: one strided write per column, where
    ``np.ascontiguousarray(columns.T)`` copies element by element (1e5 points: 0.1 against
    0.36 ms); the same values."""
    out = np.empty(columns.shape[::-1], dtype=columns.dtype)
    for j, column in enumerate(columns):
        out[:, j] = column
    return out


def median(values):
    """np.median () of a 1-D array (N,) by one partition at one rank (``_middle``: of a
    bracket around it for large N; ``partitioned``), without np.median's general-axis
    machinery (docs/shapes.md); bit-identical: the mean of the two middle
    values is their half-sum, the lower one the largest value left of the upper one (a
    partition at two distinct ranks, np.median's, took ~10x as long: docs/shapes.md).
    NaN for an empty array."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return np.nan
    k = v.size // 2
    below, at = _middle(v, k)
    return at if v.size % 2 else 0.5 * (below.max() + at)


def order_statistic(values, rank: int):
    """The rank-th smallest of values (N,) (0-based), by one partition at that rank."""
    return partitioned(values, rank)[rank]


def partitioned(values, rank: int) -> np.ndarray:
    """``np.partition(values, rank)`` of a 1-D array (N,): the rank-th smallest value at
    ``rank``, none larger left of it, none smaller right of it (NaN the largest). Which
    way NumPy orders each side is not part of it: callers read the value at ``rank`` and
    the largest left of it, the same bits either way. Why not np.partition itself: NumPy
    takes a single rank to x86-simd-sort's vectorised select and a repeated one,
    ``(rank, rank)``, to its introselect, and which is faster depends on the CPU (an AMD
    EPYC with AVX-512: the select 4-6x slower on 2,000-20,000 values; docs/shapes.md), so
    the form is timed once per process (``_repeated_rank``)."""
    return np.partition(values, (rank, rank) if _repeated_rank() else rank)


@functools.cache
def _repeated_rank() -> bool:
    """Whether a partition at a repeated rank was the faster form on this CPU: both
    timed on the same 4,096 values, three turns each, the best of each compared
    (~0.5 ms once per process, kept; either form gives the same order statistics)."""
    import time

    values = np.random.default_rng(0).random(4096)
    best = {False: math.inf, True: math.inf}
    for _ in range(3):
        for repeated in best:
            start = time.perf_counter()
            np.partition(values, (2048, 2048) if repeated else 2048)
            best[repeated] = min(best[repeated], time.perf_counter() - start)
    return best[True] < best[False]


#: Values from which ``_middle`` first narrows to a bracket of a strided sample, and
#: the sample's size: a partition of 1e5 float64 takes ~0.9 ms, the bracket ~0.3.
BRACKET_FROM = 1 << 14
BRACKET_SAMPLE = 1024


def _middle(v, k: int):
    """(values of v (N,) float64 that rank below k, the k-th smallest value):
    ``np.partition(v, k)``'s ``[:k]`` and ``[k]``, or for a large v a part of ``[:k]``
    that holds its maximum (the (k-1)-th smallest; a partition leaves it anywhere in
    ``[:k]``). The two ranks are then first bracketed between two values of a strided
    sample, and only the values between them are partitioned: the values below the
    bracket are all smaller than any inside it. The same order statistics come out (NaN
    counts as the largest value, as in a partition); a bracket that misses the ranks
    falls back to the whole partition."""
    if v.size >= BRACKET_FROM and k >= 1:
        sample = np.sort(v[::v.size // BRACKET_SAMPLE])
        at = k * len(sample) // v.size  # the ranks' place in the sample, +- 4 sigma:
        width = 2 * int(np.sqrt(len(sample))) + 1  # binomial spread sqrt(m p (1 - p))
        lo, hi = sample[max(at - width, 0)], sample[min(at + width, len(sample) - 1)]
        under = int(np.count_nonzero(v < lo))
        inside = v[(v >= lo) & (v <= hi)]
        if under <= k - 1 and k < under + inside.size:
            part = partitioned(inside, k - under)
            return part[:k - under], part[k - under]
    part = partitioned(v, k)
    return part[:k], part[k]


def row_norms(v):
    """Euclidean norms (N,) of the rows of v (N, 3), column by column: NumPy's
    ``norm(axis=1)`` and ``sum(axis=1)`` over (N, 3) run an inner loop of length 3 and
    are several times slower (docs/shapes.md)."""
    return np.sqrt(v[:, 0] ** 2 + v[:, 1] ** 2 + v[:, 2] ** 2)


def axial_radial(points, origin, axis):
    """Axial coordinate t (N,) and radial distance rho (N,) of points (N, 3) about a line.
    Column by column: the same bits as ``v = points - origin``, ``t = v @ axis`` and
    ``row_norms(v - t[:, None] * axis)``, whose (N, 3) broadcasts run NumPy's inner loop
    over 3 values (1e5 points: 2.6 ms for the radial part alone, 0.2 ms in columns)."""
    v = offsets(points, origin)
    t = v @ axis
    w0, w1, w2 = (v[:, j] - t * axis[j] for j in range(3))
    return t, np.sqrt(w0 ** 2 + w1 ** 2 + w2 ** 2)


def line_terms(theta, p):
    """(dx, dy, dz, t, rho2) of points p (3 coordinates, each (...)) about the line
    through theta[0:3] along theta[3:6] (a cylinder's or cone's theta, the direction not
    necessarily unit): the offsets d = p - theta[0:3], t = d . theta[3:6] and
    rho2 = |d|^2 - t^2, in the order the residuals and their Jacobians share."""
    dx, dy, dz = p[0] - theta[0], p[1] - theta[1], p[2] - theta[2]
    t = dx * theta[3] + dy * theta[4] + dz * theta[5]
    return dx, dy, dz, t, dx * dx + dy * dy + dz * dz - t * t


#: Squared radial distances are clamped here before their root: a point on the axis
#: has a finite residual and a zero derivative, not a NaN.
RHO2_FLOOR = 1e-30


def radial_distance(rho2, xp):
    """sqrt(rho2), rho2 clamped at ``RHO2_FLOOR``."""
    return xp.sqrt(xp.maximum(rho2, RHO2_FLOOR))


def negative_inverse_root(rho2, xp):
    """-1 / ``radial_distance``, 0 where rho2 is clamped (the residual's derivative is
    0 there too)."""
    return xp.where(rho2 > RHO2_FLOOR, -1.0 / radial_distance(rho2, xp), 0.0)


def offsets(points, origin):
    """points (N, 3) - origin (3,) as float64, in points' memory order (the layout
    ``v @ axis`` sums by), written column by column (see ``axial_radial``)."""
    points = np.asarray(points, dtype=np.float64)
    v = np.empty_like(points)
    for j in range(3):
        np.subtract(points[:, j], origin[j], out=v[:, j])
    return v


def axial(points, origin, axis):
    """``axial_radial``'s t (N,) alone, the same bits (a bounded fit's extent along its
    axis needs no radial distances: at 1e5 inliers they were ~2/3 of a cylinder's
    ``from_theta``)."""
    return offsets(points, origin) @ axis


def segment_distance_2d(px, py, ax, ay, bx, by):
    """Distance of 2-D points (px, py) (N,) to the segment from (ax, ay) to (bx, by)."""
    dx, dy = bx - ax, by - ay
    length2 = dx * dx + dy * dy
    s = np.clip(((px - ax) * dx + (py - ay) * dy) / max(length2, 1e-300), 0.0, 1.0)
    return np.hypot(px - (ax + s * dx), py - (ay + s * dy))


def sign_canonical(vectors):
    """Flip each row of (..., 3) so its largest-magnitude component is positive (NumPy).
    This is the documented sign rule for plane normals, cylinder axes and box axes."""
    v = np.asarray(vectors, dtype=np.float64)
    if v.ndim == 1:  # (one vector, a fit's result: 4 us, against 11 by take_along_axis)
        return v * (-1.0 if v[np.abs(v).argmax()] < 0 else 1.0)
    big = np.take_along_axis(v, np.argmax(np.abs(v), axis=-1)[..., None], axis=-1)
    return v * np.where(big < 0, -1.0, 1.0)


def main_interval(values, gap):
    """(lo, hi) of the main run of values (N,) along an axis: bins at least ``gap`` wide
    holding at least a fifth of the fullest bin's count, the contiguous run of them with
    the most values. Strays (outliers near a surface's unbounded continuation) are far
    sparser than the surface, so they fall below the cut and do not stretch the bounds.
    Bins are widened until they expect MIN_PER_BIN values over the central 90 %, so the
    chance gaps of a sparse sample do not cut it.

    Only occupied bins are counted when there are far more bins than values (a gap far
    below the spread), so memory is O(N) for any gap."""
    v = np.asarray(values, dtype=np.float64)
    lo = v.min()
    # The central 90 % can widen the bins only where the whole range can: q95 - q05 <=
    # max - min, in floats too (rounding is monotone), so the same gap comes out, and
    # the two partitions (~2 ms at 1e5 values) are left out where they cannot matter.
    if not MIN_PER_BIN * (v.max() - lo) / (0.9 * len(v)) <= gap:
        k05, k95 = int(0.05 * (len(v) - 1)), int(0.95 * (len(v) - 1))
        # (one partition per rank: one at both ranks took ~5x as long as the two)
        q05, q95 = order_statistic(v, k05), order_statistic(v, k95)
        gap = max(gap, MIN_PER_BIN * (q95 - q05) / (0.9 * len(v)))
    with np.errstate(over="ignore"):  # (a gap below the spread / 1e308: one inf bin)
        cell = np.floor((v - lo) / gap)  # bin of each value (float: no int overflow)
    if cell.max() < 4 * len(v) + 16:  # few bins: count them all
        counts = np.bincount(cell.astype(np.int64))
        occupied = counts > 0
        ids = occupied.nonzero()[0].astype(np.float64)
        counts = counts[occupied]
    else:
        ids, counts = np.unique(cell, return_counts=True)
    dense = counts >= 0.2 * counts.max()
    ids, counts = ids[dense], counts[dense]
    # runs of adjacent dense bins (4 us, where np.r_ and np.diff took 15)
    starts = np.concatenate(([True], ids[1:] - ids[:-1] != 1)).nonzero()[0]
    run = int(np.add.reduceat(counts, starts).argmax())
    first, last = starts[run], (starts[run + 1] if run + 1 < len(starts) else len(ids)) - 1
    inside = v[(cell >= ids[first]) & (cell <= ids[last])]
    return inside.min(), inside.max()


def random_units(count: int, rng) -> np.ndarray:
    """(count, 3) unit vectors uniform on the sphere, from ``rng.normal``."""
    v = rng.normal(size=(count, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def axial_cut_direction(axis, rng) -> np.ndarray:
    """Unit normal (3,) of a random plane containing the line along ``axis`` (3,): a
    direction orthogonal to the axis at a uniform angle. Either side of such a plane
    holds half of a surface of revolution about that line (and of a disk about it)."""
    angle = rng.uniform(0.0, 2.0 * np.pi)
    return frame(axis) @ np.array([np.cos(angle), np.sin(angle), 0.0])


def disk_bounds(center, normal, radius):
    """Axis-aligned bounds (lo (3,), hi (3,)) of a disk of ``radius`` about ``center``
    (3,) with unit ``normal`` (3,): it reaches radius * sqrt(1 - n_i^2) along axis i."""
    reach = radius * np.sqrt(np.clip(1.0 - np.asarray(normal) ** 2, 0.0, None))
    return np.asarray(center) - reach, np.asarray(center) + reach


def union_bounds(bounds):
    """Axis-aligned bounds (lo (3,), hi (3,)) enclosing every (lo, hi) pair in ``bounds``."""
    return np.min([b[0] for b in bounds], axis=0), np.max([b[1] for b in bounds], axis=0)


def axis_angle_deg(a, b) -> float:
    """Angle in degrees, in [0, 90], between the lines along vectors a (3,) and b (3,).

    atan2 of |a x b| and |a . b| rather than arccos, which loses digits near 0 degrees.
    """
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), abs(a @ b))))


def point_distance(a, b) -> float:
    """Euclidean distance between two points a (3,) and b (3,)."""
    return float(np.linalg.norm(np.asarray(a, float) - np.asarray(b, float)))


def unit(v) -> np.ndarray:
    """v (3,) scaled to unit length (NumPy, float64)."""
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


# ----- the same, for many clouds at once (segments of one array) ----------------------


def sorted_segments(values, counts):
    """values (M,), counts (C,) >= 1 summing to M (segment i is the next counts[i]
    values) -> (C, max(counts)) float64, each row its segment sorted ascending and padded
    with +inf: one sort for every segment (a partition per segment costs ~5 us of NumPy
    calls each)."""
    counts = np.asarray(counts, np.int64)
    rows = _placed(np.full((len(counts), int(counts.max())), np.inf), values, counts, 0)
    rows.sort(axis=1)
    return rows


def _placed(rows, values, counts, lead):
    """rows (C, W) with segment s of values (M,) (the next counts[s] values) written in
    row s from column lead (an int, or (C,) one a row): value i of segment s goes to flat
    place s * W + lead[s] + (i - start of s)."""
    shift = np.arange(len(counts)) * rows.shape[1] + lead - (np.cumsum(counts) - counts)
    rows.ravel()[np.arange(int(counts.sum())) + np.repeat(shift, counts)] = values
    return rows


def segment_medians(values, counts):
    """``median`` (C,) of each segment of values (M,) (segment i the next counts[i] >= 1
    values), bit for bit. Segments of similar lengths (a batch's clouds) go in one
    partition: each is a row padded so that its middle value falls in one column for all
    rows (``-inf`` before it, ``+inf`` after), the row's lower middle then being the
    largest value left of that column. Segments of very unequal lengths, whose rows would
    be mostly padding, take ``median`` each (an 80 x ~350 block: 0.38 -> 0.20 ms; a
    sort of all segments, ``sorted_segments``, had cost more than the slices)."""
    counts = np.asarray(counts, np.int64)
    half = counts // 2
    middle = int(half.max())
    width = middle + int((counts - half).max())
    if width * len(counts) > 2 * int(counts.sum()):
        ends = np.cumsum(counts).tolist()
        return np.array([median(values[end - n:end])
                         for end, n in zip(ends, counts.tolist(), strict=True)])
    lead = middle - half  # -inf before each segment's values, +inf after them
    rows = _placed(np.where(np.arange(width) < lead[:, None], -np.inf, np.inf), values,
                   counts, lead)
    rows.partition(middle, axis=1)
    upper = rows[:, middle]
    lower = rows[:, :middle].max(axis=1) if middle else upper
    return np.where(counts % 2 == 1, upper, 0.5 * (lower + upper))


def frames(axes):
    """``frame`` of each row of axes (C, 3): (C, 3, 3), bit for bit (the same elementwise
    products, and each squared length by the same dot product, ``matmul`` of stacked
    vectors)."""
    axes = np.asarray(axes, dtype=np.float64)
    helper = np.eye(3)[np.argmin(np.abs(axes), axis=1)]
    x = cross3(helper.T, axes.T).T  # (C, 3)
    x /= np.sqrt(np.matmul(x[:, None, :], x[:, :, None])[:, 0])
    return np.stack([x, cross3(axes.T, x.T).T, axes], axis=2)


def main_intervals(values, counts, gaps):
    """``main_interval`` of each segment of values (M,) (``sorted_segments``) at its own
    gap (C,): (lo (C,), hi (C,)), bit for bit. On each sorted segment the bins are runs of
    equal bin index, so counting, the dense cut and the runs of adjacent dense bins are
    segment reductions over all clouds at once."""
    counts = np.asarray(counts, np.int64)
    size = len(counts)
    rows = sorted_segments(values, counts)
    index = np.arange(size)
    k05 = (0.05 * (counts - 1)).astype(np.int64)  # (int() of the same float products)
    k95 = (0.95 * (counts - 1)).astype(np.int64)
    spread = rows[index, k95] - rows[index, k05]
    gap = np.maximum(np.asarray(gaps, np.float64), MIN_PER_BIN * spread / (0.9 * counts))
    lo = rows[:, 0]
    v = rows[np.isfinite(rows)]  # (M,) the segments sorted, in order
    owner = np.repeat(index, counts)
    with np.errstate(over="ignore"):
        cell = np.floor((v - lo[owner]) / gap[owner])
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])  # each segment's first value
    opens = np.ones(len(v), bool)  # a value that opens a bin: new segment or new cell
    opens[1:] = (cell[1:] != cell[:-1]) | (owner[1:] != owner[:-1])
    bins = np.flatnonzero(opens)
    bin_owner, bin_id = owner[bins], cell[bins]
    bin_count = np.diff(np.append(bins, len(v)))
    owner_bins = np.flatnonzero(np.r_[True, bin_owner[1:] != bin_owner[:-1]])
    fullest = np.maximum.reduceat(bin_count, owner_bins)
    dense = bin_count >= 0.2 * fullest[bin_owner]
    d_owner, d_id, d_count = bin_owner[dense], bin_id[dense], bin_count[dense]
    runs = np.flatnonzero(np.r_[True, (np.diff(d_id) != 1) | (d_owner[1:] != d_owner[:-1])])
    run_sum, run_owner = np.add.reduceat(d_count, runs), d_owner[runs]
    run_last = np.append(runs[1:], len(d_id)) - 1
    owner_runs = np.flatnonzero(np.r_[True, run_owner[1:] != run_owner[:-1]])
    best = np.flatnonzero(run_sum == np.maximum.reduceat(run_sum, owner_runs)[run_owner])
    best = best[np.r_[True, run_owner[best][1:] != run_owner[best][:-1]]]  # argmax: first
    low, high = d_id[runs[best]], d_id[run_last[best]]
    inside = (cell >= low[owner]) & (cell <= high[owner])
    return (np.minimum.reduceat(np.where(inside, v, np.inf), first),
            np.maximum.reduceat(np.where(inside, v, -np.inf), first))
