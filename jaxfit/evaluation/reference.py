"""A plain NumPy implementation of the thesis's RANSAC/MSAC: the benchmark baseline and
a test oracle for the JAX engine.

Everything here is written in the classic style of THESIS.md section 2 (the thesis's
MATLAB way): one minimal sample at a time, ``if`` on degenerate cases, ``np.linalg``
solves in float64. Only three things are shared with the engine, so that both sides mean
the same thing by a hypothesis:

- the parameter layouts ``theta`` documented in ``jaxfit/shapes/*.py``;
- each model class's residual ``Cls.theta_residual(theta, (x, y, z), np)``;
- the degeneracy tolerances (``SIN_TOL``, ``LEN_TOL``, ``MAX_EXTENT``, the cone's minimal
  half-angle) and the box's ``HISTOGRAM_BINS``.

The estimators are computed differently from the JAX ones (linear solves and a
least-squares line intersection instead of closed forms), which is what makes them an
oracle. Like the engine's, the tolerances assume a cloud normalised into the unit ball.

Public API
----------
ESTIMATORS : name -> ``estimate(sample (k, 3), support (M, 3) | None) -> (theta, valid)``
estimate, estimate_batch : one sample / a loop over samples.
msac_cost, score_batch : MSAC cost and inlier count of one / many hypotheses.
ransac : the one-hypothesis-at-a-time loop.
"""

from __future__ import annotations

import math

import numpy as np

from .. import _checks
from ..engine import required_hypotheses
from ..shapes import Model
from ..shapes._geometry import LEN_TOL, MAX_EXTENT, SIN_TOL
from ..shapes.box import HISTOGRAM_BINS
from ..shapes.cone import MIN_ANGLE

#: Memory budget of one block of ``score_batch`` (bytes), and the number of (block, H)
#: float64 temporaries a residual formula keeps alive at once (the cone's needs ~8).
BLOCK_BYTES = 64 * 2**20
_TEMPORARIES = 8


# ----- small geometry -----------------------------------------------------------------


def _invalid(num_params: int) -> tuple[np.ndarray, bool]:
    """The answer for a degenerate sample: (theta of NaNs (P,), False)."""
    return np.full(num_params, np.nan), False


def _plane_normal(a, b, c):
    """Unit normal (3,) along (b - a) x (c - a) of three points (3,) each, or None when
    two of them coincide (an edge <= LEN_TOL) or they are collinear
    (|(b - a) x (c - a)| <= SIN_TOL |b - a| |c - a|)."""
    u, v = b - a, c - a
    w = np.cross(u, v)
    area = np.linalg.norm(w)
    lu, lv, lbc = np.linalg.norm(u), np.linalg.norm(v), np.linalg.norm(c - b)
    if not (area > SIN_TOL * lu * lv and min(lu, lv, lbc) > LEN_TOL):
        return None
    return w / area


def _circle(a, b, c):
    """Circumcircle of three points (3,) each: (centre (3,), unit normal (3,), radius), or
    None for a degenerate triangle or a radius >= MAX_EXTENT.

    The centre y = c0 - a solves the 3x3 linear system of the two perpendicular
    bisectors (b - a) . y = |b - a|^2 / 2, (c - a) . y = |c - a|^2 / 2 and the plane
    n . y = 0.
    """
    normal = _plane_normal(a, b, c)
    if normal is None:
        return None
    u, v = b - a, c - a
    y = np.linalg.solve(np.stack([u, v, normal]), np.array([u @ u / 2, v @ v / 2, 0.0]))
    radius = float(np.linalg.norm(y))
    if not radius < MAX_EXTENT:
        return None
    return a + y, normal, radius


def _line_intersection(p, d, q, e):
    """Parameters (s, t) of the closest points p + s d and q + t e of two lines (3,) each,
    by least squares on p + s d = q + t e (their intersection when they are coplanar)."""
    (s, t), *_ = np.linalg.lstsq(np.stack([d, -e], axis=1), q - p, rcond=None)
    return float(s), float(t)


def histogram_modes(normals, support):
    """Offsets (3,) of the planes with normals (3, 3) (rows) through the densest slabs.

    The projections of ``support`` (M, 3) (points in the unit ball) on each normal are
    binned into ``HISTOGRAM_BINS`` bins over [-1, 1] (bin = clip(floor((proj + 1) *
    HISTOGRAM_BINS / 2), 0, HISTOGRAM_BINS - 1)); the offset is the mean projection in
    the fullest bin, the first one on ties.
    """
    offsets = np.empty(3)
    for i, normal in enumerate(normals):
        proj = support @ normal
        bins = np.floor((proj + 1.0) * (HISTOGRAM_BINS / 2))
        bins = np.clip(bins, 0, HISTOGRAM_BINS - 1).astype(np.int64)
        mode = np.argmax(np.bincount(bins, minlength=HISTOGRAM_BINS))
        offsets[i] = proj[bins == mode].mean()
    return offsets


# ----- the five estimators --------------------------------------------------------------


def estimate_plane(sample, support=None):
    """Plane (nx, ny, nz, d), n . p + d = 0, through the sample's three points (3, 3)."""
    normal = _plane_normal(*sample[:3])
    if normal is None:
        return _invalid(4)
    return np.concatenate([normal, [-normal @ sample[0]]]), True


def estimate_sphere(sample, support=None):
    """Sphere (cx, cy, cz, r) through four points (4, 3): x = centre - p1 solves
    2 (p_i - p1) . x = |p_i - p1|^2, i = 2..4. Invalid when some p_i - p1 is <= LEN_TOL
    long, the points are coplanar (|det| <= SIN_TOL prod |p_i - p1|) or r >= MAX_EXTENT."""
    q = sample[1:4] - sample[0]
    lengths = np.linalg.norm(q, axis=1)
    det = np.linalg.det(q)
    if not (abs(det) > SIN_TOL * np.prod(lengths) and lengths.min() > LEN_TOL):
        return _invalid(4)
    x = np.linalg.solve(2.0 * q, np.sum(q * q, axis=1))
    radius = np.linalg.norm(x)
    if not radius < MAX_EXTENT:
        return _invalid(4)
    return np.concatenate([sample[0] + x, [radius]]), True


def estimate_cylinder(sample, support=None):
    """Cylinder (c0 (3), n (3), r) from three points (3, 3): the axis passes through their
    circumcentre c0 along the plane normal n = normalize((p2 - p1) x (p3 - p1)), and r is
    the circumradius (THESIS.md section 3)."""
    circle = _circle(*sample[:3])
    if circle is None:
        return _invalid(7)
    centre, normal, radius = circle
    return np.concatenate([centre, normal, [radius]]), True


def estimate_cone(sample, support=None):
    """Cone (apex (3), axis (3), half_angle) from four points (4, 3), the thesis's apex
    construction: circle (c0, n, r) of p1..p3; p4' = p4 projected on its plane; the ray
    from c0 through p4' meets the circle at s; the line (s, p4) meets the axis line at the
    apex. The axis points from the apex toward c0; the half-angle is the acute angle
    between the line (s, p4) and the axis.

    Invalid when the circle is, when p4 is within LEN_TOL of the axis or of the plane, or
    when the line (s, p4) is parallel to the axis (|rho4 - r| <= LEN_TOL, rho4 = |p4' - c0|);
    when the half-angle is within the cone's minimal angle of 0 or 90 degrees; and when
    the apex is MAX_EXTENT or more from c0.
    """
    circle = _circle(*sample[:3])
    if circle is None:
        return _invalid(7)
    c0, normal, radius = circle
    p4 = sample[3]
    height = (p4 - c0) @ normal
    radial = p4 - height * normal - c0  # p4' - c0
    rho = np.linalg.norm(radial)
    if not (rho > LEN_TOL and abs(height) > LEN_TOL and abs(rho - radius) > LEN_TOL):
        return _invalid(7)
    s = c0 + radius * radial / rho
    direction = p4 - s  # of the generator line L3 through s and p4
    _, along = _line_intersection(s, direction, c0, normal)
    half_angle = math.atan2(np.linalg.norm(np.cross(direction, normal)), abs(direction @ normal))
    if not (MIN_ANGLE < half_angle < math.pi / 2 - MIN_ANGLE and abs(along) < MAX_EXTENT):
        return _invalid(7)
    axis = normal if along < 0 else -normal  # from the apex c0 + along n toward c0
    return np.concatenate([c0 + along * normal, axis, [half_angle]]), True


def estimate_box(sample, support):
    """Box (n1 (3), n2 (3), n3 (3), D1, D2, D3), faces n_i . p = D_i, from five points
    (5, 3) and the cloud ``support`` (M, 3) (points in the unit ball).

    n1 is the plane normal of p1..p3; with p4' = p4 - ((p4 - p1) . n1) n1,
    n2 = normalize((p4 - p4') x (p5 - p4)) and n3 = n1 x n2. D_i is the histogram mode of
    the support's projections on n_i (``histogram_modes``). Invalid when p1..p3 are, when
    p4 lies within LEN_TOL of the first face, or when p5 - p4 is (nearly) parallel to n1:
    |(p4 - p4') x (p5 - p4)| <= SIN_TOL |p4 - p4'| |p5 - p4|.
    """
    p1, p4, p5 = sample[0], sample[3], sample[4]
    n1 = _plane_normal(*sample[:3])
    if n1 is None:
        return _invalid(12)
    h4 = (p4 - p1) @ n1
    foot = p4 - h4 * n1
    m = np.cross(p4 - foot, p5 - p4)
    length = np.linalg.norm(m)
    if not (abs(h4) > LEN_TOL and length > SIN_TOL * abs(h4) * np.linalg.norm(p5 - p4)):
        return _invalid(12)
    n2 = m / length
    normals = np.stack([n1, n2, np.cross(n1, n2)])
    return np.concatenate([normals.reshape(-1), histogram_modes(normals, support)]), True


#: name -> estimate(sample (k, 3), support (M, 3) | None) -> (theta (P,), valid bool).
ESTIMATORS = {
    "plane": estimate_plane,
    "sphere": estimate_sphere,
    "cylinder": estimate_cylinder,
    "cone": estimate_cone,
    "box": estimate_box,
}


# ----- public functions -----------------------------------------------------------------


def _model(shape) -> type[Model]:
    """The model class of a name or class (ValueError for anything else)."""
    return _checks.model_class(shape)


def _support(cls, support):
    if cls.name != "box":
        return None
    if support is None:
        raise ValueError("the box estimator needs the support points (M, 3)")
    support = np.asarray(support, dtype=np.float64)
    if support.ndim != 2 or support.shape[1] != 3 or support.shape[0] == 0:
        raise ValueError(f"support must have shape (M, 3) with M > 0, got {support.shape}")
    return support


def estimate(shape, sample, support=None) -> tuple[np.ndarray, bool]:
    """Closed-form estimate from one minimal sample.

    Parameters
    ----------
    shape : "plane", "sphere", "cylinder", "cone", "box" or the model class.
    sample : (k, 3) the minimal sample, k = the model's ``sample_size``.
    support : (M, 3) points in the unit ball, required for the box (its offsets are
        histogram modes over them), ignored otherwise.

    Returns
    -------
    theta : (P,) float64 parameters in the model's layout; NaN when invalid.
    valid : bool, False for degenerate samples (never raises for them).
    """
    cls = _model(shape)
    sample = np.asarray(sample, dtype=np.float64)
    if sample.shape != (cls.sample_size, 3):
        raise ValueError(f"a {cls.name} sample has shape ({cls.sample_size}, 3), "
                         f"got {sample.shape}")
    return ESTIMATORS[cls.name](sample, _support(cls, support))


def estimate_batch(shape, samples, support=None) -> tuple[np.ndarray, np.ndarray]:
    """``estimate`` on each of samples (H, k, 3), one at a time.

    Returns thetas (H, P) float64 (NaN rows for invalid samples) and valid (H,) bool.
    """
    cls = _model(shape)
    samples = np.asarray(samples, dtype=np.float64)
    if samples.ndim != 3 or samples.shape[1:] != (cls.sample_size, 3):
        raise ValueError(f"{cls.name} samples have shape (H, {cls.sample_size}, 3), "
                         f"got {samples.shape}")
    support = _support(cls, support)
    thetas = np.full((samples.shape[0], cls.num_params), np.nan)
    valid = np.zeros(samples.shape[0], dtype=bool)
    for h, sample in enumerate(samples):
        thetas[h], valid[h] = ESTIMATORS[cls.name](sample, support)
    return thetas, valid


def residuals(shape, theta, points) -> np.ndarray:
    """Signed distances (N,) of points (N, 3) to the unbounded surface of theta (P,)."""
    cls = _model(shape)
    points = np.asarray(points, dtype=np.float64)
    theta = np.asarray(theta, dtype=np.float64)
    return cls.theta_residual(theta, (points[:, 0], points[:, 1], points[:, 2]), np)


def msac_cost(shape, theta, points, threshold) -> tuple[float, int]:
    """MSAC cost sum_j min(e_j^2, t^2) and inlier count #{|e_j| < t} of one hypothesis
    theta (P,) over points (N, 3), all points at once."""
    e = residuals(shape, theta, points)
    cost = np.sum(np.minimum(e * e, threshold * threshold))
    return float(cost), int(np.sum(np.abs(e) < threshold))


def score_batch(shape, thetas, valid, points, threshold) -> tuple[np.ndarray, np.ndarray]:
    """MSAC costs and inlier counts of many hypotheses, vectorised NumPy.

    Parameters
    ----------
    thetas : (H, P) hypotheses; rows with ``valid`` False are not evaluated.
    valid : (H,) bool.
    points : (N, 3).
    threshold : inlier distance t.

    Returns
    -------
    costs : (H,) float64, sum_j min(e_j^2, t^2); +inf for invalid hypotheses.
    counts : (H,) int64, #{|e_j| < t}; 0 for invalid hypotheses.

    The residuals of all valid hypotheses are computed at once for blocks of points, the
    hypotheses on the last axis; blocks hold at most ``BLOCK_BYTES`` of temporaries.
    """
    cls = _model(shape)
    thetas = np.asarray(thetas, dtype=np.float64).reshape(-1, cls.num_params)
    valid = np.asarray(valid, dtype=bool).reshape(-1)
    points = np.asarray(points, dtype=np.float64)
    costs = np.full(thetas.shape[0], np.inf)
    counts = np.zeros(thetas.shape[0], dtype=np.int64)
    live = np.flatnonzero(valid)
    if live.size == 0:
        return costs, counts
    theta_t = thetas[live].T  # (P, L): hypotheses on the fast axis
    rows = max(1, BLOCK_BYTES // (8 * _TEMPORARIES * live.size))
    t2 = float(threshold) ** 2
    cost, count = np.zeros(live.size), np.zeros(live.size, dtype=np.int64)
    for start in range(0, points.shape[0], rows):
        block = points[start:start + rows]
        e = cls.theta_residual(theta_t, (block[:, 0:1], block[:, 1:2], block[:, 2:3]), np)
        cost += np.sum(np.minimum(e * e, t2), axis=0)
        count += np.sum(np.abs(e) < threshold, axis=0)
    costs[live], counts[live] = cost, count
    return costs, counts


def ransac(points, shape, *, threshold, confidence=0.99, max_hypotheses=10_000,
           max_stall=None, seed=0) -> dict:
    """The classic RANSAC/MSAC loop of THESIS.md section 2, one hypothesis at a time.

    Each iteration draws k distinct indices (``rng.choice(N, k, replace=False)`` with
    ``rng = np.random.default_rng(seed)``), estimates, scores the hypothesis on all points
    with ``msac_cost`` and keeps it if its cost is the lowest so far. Whenever the best
    model changes, the number of iterations needed is recomputed from its inlier count,
    T = log(1 - p) / log(1 - w^k) (``jaxfit.ransac.required_hypotheses``; the engine's
    per-shape floor ``min_hypotheses`` is not applied). Degenerate samples count as
    iterations.

    Parameters
    ----------
    points : (N, 3) the cloud, **already normalised into the unit ball** by the caller:
        the degeneracy tolerances assume it, and the box's histogram modes bin the
        projections over [-1, 1]. The box's support is the whole cloud.
    shape : "plane", "sphere", "cylinder", "cone", "box" or the model class.
    threshold : inlier distance t, in the points' units.
    confidence : p, the probability of having drawn an all-inlier sample at convergence.
    max_hypotheses : iteration budget.
    max_stall : stop after this many iterations without a better model (None: never).
    seed : seed of ``np.random.default_rng``.

    Returns
    -------
    dict with
        theta : (P,) best hypothesis (NaN if no sample was valid),
        cost : its MSAC cost (inf if none), num_inliers : int,
        inliers : (N,) bool, |e| < t for the best hypothesis' unbounded surface,
        num_hypotheses : iterations done,
        status : "converged" (T reached), "max_hypotheses" or "stalled".
    """
    cls = _model(shape)
    cloud = _checks.points_for(points, cls)
    threshold = _checks.positive(threshold, "threshold")
    confidence = _checks.probability(confidence, "confidence")
    max_hypotheses = _checks.positive(max_hypotheses, "max_hypotheses", integer=True)
    if max_stall is not None:
        max_stall = _checks.positive(max_stall, "max_stall", integer=True)
    rng = np.random.default_rng(seed)
    n, k = cloud.shape[0], cls.sample_size
    estimator, support = ESTIMATORS[cls.name], _support(cls, cloud)

    best_theta, best_cost, best_count = np.full(cls.num_params, np.nan), math.inf, 0
    needed, drawn, last_improvement, status = math.inf, 0, 0, "max_hypotheses"
    while drawn < max_hypotheses:
        theta, valid = estimator(cloud[rng.choice(n, k, replace=False)], support)
        drawn += 1
        if valid:
            cost, count = msac_cost(cls, theta, cloud, threshold)
            if cost < best_cost:
                best_theta, best_cost, best_count, last_improvement = theta, cost, count, drawn
                needed = required_hypotheses(count / n, k, confidence)
        if drawn >= needed:
            status = "converged"
            break
        if max_stall is not None and drawn - last_improvement >= max_stall:
            status = "stalled"
            break
    if math.isfinite(best_cost):
        inliers = np.abs(residuals(cls, best_theta, cloud)) < threshold
    else:
        inliers = np.zeros(n, dtype=bool)
    return {
        "theta": best_theta,
        "cost": best_cost,
        "num_inliers": int(best_count),
        "inliers": inliers,
        "num_hypotheses": drawn,
        "status": status,
    }
