"""The final refit on all inliers (``refine.final_refit``, issue 18): it reaches the
noise's own accuracy, never raises the MSAC cost, keeps the user's bounds and the normal
gate, and is deterministic; ``fit`` returns its stationary point.

Distances between parameter vectors are measured in the noise's units: for a hypothesis
error d (P,), d^T (J^T J) d / sigma^2 with J the residuals' Jacobian on the true surface
points, the squared Mahalanobis distance whose expectation for the least-squares
estimate is its count of identifiable parameters (3 for a plane, up to 6 for a cone).
Most tests call the NumPy refit directly (no kernel compiles); the ``fit`` ones use
3000-point clouds (bucket 4096, as tests/test_fit.py's cylinder).
"""

import importlib

import numpy as np
import pytest

import jaxfit
from jaxfit.engine import refine
from jaxfit.engine.options import Bounds
from jaxfit.evaluation.synthetic import random_rotation
from jaxfit.shapes import REGISTRY

SIGMA = 0.002
SHAPES = ("plane", "sphere", "cylinder", "cone")


def noisy(shape, n, seed, outliers=0.3):
    """points (n, 3) near the unit ball: a random ``shape`` of size 0.5-ish with Gaussian
    noise SIGMA along the normal and uniform outliers in [-1, 1]^3; the true theta and
    the surface points."""
    rng = np.random.default_rng(seed)
    model = REGISTRY[shape].random(random_rotation(rng), rng.uniform(-0.1, 0.1, 3), 0.5, rng)
    n_out = int(outliers * n)
    surface, normals = model.sample(n - n_out, rng)
    surface = surface + normals * rng.normal(0.0, SIGMA, (len(surface), 1))
    points = np.vstack([surface, rng.uniform(-1, 1, (n_out, 3))])
    return points, model.theta(), surface


def information(shape, theta, surface):
    """J^T J / sigma^2 (P, P) at theta over the surface points."""
    cls = REGISTRY[shape]
    _, jtj, _ = refine._evaluate(cls, theta, np.ascontiguousarray(surface.T), np.inf, None, None,
                                 canonical=refine.host_canonical(cls))
    return jtj / SIGMA**2


def noise_distance(info, a, b) -> float:
    d = np.asarray(a) - np.asarray(b)
    return float(d @ info @ d)


def perturbed(info, theta, distance, rng, canonical):
    """theta moved by ``distance`` noise units (squared: distance**2) in a random
    identifiable direction, projected back onto valid parameters."""
    values, vectors = np.linalg.eigh(info)
    live = values > 1e-9 * values.max()
    direction = vectors[:, live] @ (rng.normal(size=live.sum()) / np.sqrt(values[live]))
    direction *= distance / np.sqrt(direction @ info @ direction)
    return canonical(theta + direction)


@pytest.mark.parametrize("shape", SHAPES)
def test_refit_reaches_the_noise_floor(shape):
    # Started 20 noise units out (what LO on a 2048-point subset leaves is ~3-5 at this
    # size), the refit must come within 5 (its own estimate: ~sqrt(P) units away).
    cls = REGISTRY[shape]
    points, truth, surface = noisy(shape, 20_000, seed=3)
    info = information(shape, truth, surface)
    start = perturbed(info, truth, 20.0, np.random.default_rng(0), refine.host_canonical(cls))
    theta, cost, start_cost = refine.final_refit(cls, start, points, 3 * SIGMA)
    assert noise_distance(info, start, truth) == pytest.approx(400.0, rel=0.05)
    assert noise_distance(info, theta, truth) < 25.0
    assert cost < start_cost


@pytest.mark.parametrize("shape", [*SHAPES, "box"])
def test_refit_never_raises_the_msac_cost(shape):
    cls = REGISTRY[shape]
    canonical = refine.host_canonical(cls)
    rng = np.random.default_rng(5)
    for seed in range(4):
        points, truth, surface = noisy(shape, 3000, seed, outliers=0.5)
        # far starts too: a few hundred noise units, or a whole percent of the size
        start = canonical(truth + rng.normal(0.0, [1e-4, 1e-3, 1e-2, 3e-2][seed], truth.size))
        theta, cost, start_cost = refine.final_refit(cls, start, points, 3 * SIGMA)
        columns = np.ascontiguousarray(points.T)  # (the (3, N) layout final_refit passes)
        before, _, _ = refine._evaluate(cls, canonical(start), columns, 3 * SIGMA, None, None)
        after, _, _ = refine._evaluate(cls, theta, columns, 3 * SIGMA, None, None)
        assert start_cost == before and cost == after
        assert after <= before


def test_refit_keeps_the_radius_and_axis_bounds():
    cls = REGISTRY["cylinder"]
    points, truth, surface = noisy("cylinder", 20_000, seed=4)
    radius, axis = truth[6], truth[3:6]
    start = truth.copy()
    start[6] = radius * 0.99  # the least-squares radius (~truth) lies above the bound
    bounds = Bounds.make(0.0, radius * 0.995)
    theta, _, _ = refine.final_refit(cls, start, points, 3 * SIGMA, bounds)
    assert theta[6] <= radius * 0.995
    free, _, _ = refine.final_refit(cls, start, points, 3 * SIGMA)
    assert free[6] > radius * 0.995  # (the bound is what held it)
    # axis prior: the start tilted 0.5 deg off the truth, the prior allowing 0.6 deg
    # around a direction 1 deg the other way; the refit may not reach the truth
    tilt = np.cross(axis, [1.0, 0.0, 0.0])
    tilt /= np.linalg.norm(tilt)
    rotate = lambda deg: np.cos(np.radians(deg)) * axis + np.sin(np.radians(deg)) * tilt  # noqa: E731
    start = np.concatenate([truth[:3], rotate(0.5), truth[6:]])
    bounds = Bounds.make(axis=rotate(1.0), axis_cos=np.cos(np.radians(0.6)))
    theta, _, _ = refine.final_refit(cls, start, points, 3 * SIGMA, bounds)
    assert abs(theta[3:6] @ rotate(1.0)) >= np.cos(np.radians(0.6))
    free, _, _ = refine.final_refit(cls, start, points, 3 * SIGMA)
    assert abs(free[3:6] @ rotate(1.0)) < np.cos(np.radians(0.6))


def test_refit_honours_the_normal_gate():
    # Points inside the plane's band at +0.8 threshold, with normals along the plane:
    # gated out they must not pull the offset; without the gate they do.
    cls = REGISTRY["plane"]
    rng = np.random.default_rng(2)
    n = 20_000
    xy = rng.uniform(-0.5, 0.5, (n, 2))
    points = np.column_stack([xy, rng.normal(0.0, SIGMA, n)])
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    stray = np.column_stack([rng.uniform(-0.5, 0.5, (4000, 2)), np.full(4000, 2.4 * SIGMA)])
    points, normals = np.vstack([points, stray]), np.vstack([normals, np.tile([1.0, 0, 0],
                                                                               (4000, 1))])
    start = np.array([0.0, 0.0, 1.0, -0.5 * SIGMA])
    gated = Bounds.make(normal_cos=np.cos(np.radians(30.0)))
    theta, _, _ = refine.final_refit(cls, start, points, 3 * SIGMA, gated, normals)
    free, _, _ = refine.final_refit(cls, start, points, 3 * SIGMA)
    # offset noise: SIGMA / sqrt(n); the strays pull the ungated fit by ~0.4 SIGMA
    assert abs(theta[3]) < 5 * SIGMA / np.sqrt(n)
    assert -free[3] > 0.2 * SIGMA


def test_refit_is_deterministic_and_leaves_what_it_cannot_fit():
    cls = REGISTRY["sphere"]
    points, truth, _ = noisy("sphere", 20_000, seed=6)
    start = truth + 1e-3
    first = refine.final_refit(cls, start, points, 3 * SIGMA)
    second = refine.final_refit(cls, start.copy(), points.copy(), 3 * SIGMA)
    assert np.array_equal(first[0], second[0]) and first[1:] == second[1:]
    nan = np.full(4, np.nan)
    assert np.array_equal(refine.final_refit(cls, nan, points, 3 * SIGMA)[0], nan,
                          equal_nan=True)


@pytest.mark.parametrize("shape", ["plane", "sphere", "cylinder"])
def test_fit_returns_the_least_squares_fit_of_all_its_inliers(shape, monkeypatch):
    # 3000 points: LO saw 2048 of them, the final refit all. Its result is stationary: a
    # further refit moves it by under 0.01 noise units (LO's own fit sat ~0.3 P units
    # from it: about a third of the points were unseen). Without the refit it fails.
    cls = REGISTRY[shape]
    points, truth, surface = noisy(shape, 3000, seed=11)
    info = information(shape, truth, surface)
    result = jaxfit.fit(points, shape, threshold=3 * SIGMA, key=0)
    theta = result.model.theta()
    again, _, _ = refine.final_refit(cls, theta, points, 3 * SIGMA)
    assert noise_distance(info, again, theta) < 0.01
    assert noise_distance(info, theta, truth) < 25.0
    fit_module = importlib.import_module("jaxfit.engine.fit")
    monkeypatch.setattr(fit_module, "FINAL_MIN_POINTS", 10**9)  # the refit off
    lo = jaxfit.fit(points, shape, threshold=3 * SIGMA, key=0).model.theta()
    moved, _, _ = refine.final_refit(cls, lo, points, 3 * SIGMA)
    assert noise_distance(info, moved, lo) > 0.01
    monkeypatch.undo()  # the option turns it off alike
    off = jaxfit.fit(points, shape, threshold=3 * SIGMA, key=0, final_refit=False)
    assert np.array_equal(off.model.theta(), lo)


def test_pseudo_solve_is_numpys_pseudo_inverse():
    """The final refit's step, pinv(a) @ b for symmetric a by one eigendecomposition:
    NumPy's hermitian pseudo-inverse to rounding, gauge directions (a repeated row of
    the Jacobian) given no step."""
    rng = np.random.default_rng(4)
    for size in (4, 7, 12):
        for trial in range(20):
            jac = rng.normal(size=(size, 60)) * rng.uniform(0.01, 10.0, (size, 1))
            if trial % 2:
                jac[-1] = 2.0 * jac[0]
            a, b = jac @ jac.T, rng.normal(size=size)
            want = np.linalg.pinv(a, rcond=1e-12, hermitian=True) @ b
            np.testing.assert_allclose(refine.pseudo_solve(a, b), want, rtol=1e-9,
                                       atol=1e-12 * np.abs(want).max())


def test_final_refit_option_is_checked():
    with pytest.raises(ValueError, match="final_refit must be True or False"):
        jaxfit.fit(np.random.default_rng(0).normal(size=(100, 3)), "sphere", final_refit=1)


@pytest.mark.parametrize("shape", [s for s in REGISTRY if REGISTRY[s].theta_jacobian])
def test_theta_jacobian_is_the_residuals_derivative(shape):
    # The analytic rows the refit's Jacobian is made of, against central differences of
    # theta_residual at a valid theta and at one off the valid set (a non-unit axis).
    cls = REGISTRY[shape]
    points, theta, _ = noisy(shape, 200, seed=3)
    q = tuple(points.T)
    for at in (theta, theta * 1.02):
        rows = cls.theta_jacobian(at, q, np)
        assert rows.shape == (cls.num_params, len(points))
        for k, e in enumerate(np.eye(cls.num_params) * 1e-6):
            central = (cls.theta_residual(at + e, q, np) - cls.theta_residual(at - e, q, np)) / 2e-6
            np.testing.assert_allclose(rows[k], central, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("shape", [s for s in REGISTRY if REGISTRY[s].theta_jacobian])
def test_analytic_jacobian_refits_as_the_differences(shape, monkeypatch):
    # The final refit with the shape's theta_jacobian lands where the forward differences
    # land (their step's error, ~1e-7 of the Jacobian, is far below the noise).
    cls = REGISTRY[shape]
    points, theta, _ = noisy(shape, 5000, seed=4)
    start = theta + np.random.default_rng(5).normal(0, 1e-3, theta.shape)
    analytic = refine.final_refit(cls, start, points, 3 * SIGMA)
    monkeypatch.setattr(cls, "theta_jacobian", None)
    differences = refine.final_refit(cls, start, points, 3 * SIGMA)
    np.testing.assert_allclose(analytic[0], differences[0], atol=1e-8)
    np.testing.assert_allclose(analytic[1], differences[1], rtol=1e-9)
    assert analytic[1] < analytic[2]  # (it moved)


def test_plane_refit_in_closed_form_is_its_inliers_least_squares_plane(monkeypatch):
    # The plane's final refit takes its closed-form fit (``host_least_squares``, from the
    # moments in J^T J) for Gauss-Newton's steps: each step is the least-squares plane of
    # the last one's inliers, so where the inliers stop changing it is that of its own
    # (an SVD of them); in its two steps it lands where Gauss-Newton's two land.
    cls = REGISTRY["plane"]
    for seed in range(3):
        points, theta, _ = noisy("plane", 5000, seed=8 + seed)
        start = theta + np.random.default_rng(seed).normal(0, 1e-3, theta.shape)
        closed, cost, first = refine.final_refit(cls, start, points, 3 * SIGMA)
        assert cost < first  # (it moved)
        with monkeypatch.context() as m:
            m.setattr(cls, "host_least_squares", None)
            steps = refine.final_refit(cls, start, points, 3 * SIGMA)
        np.testing.assert_allclose(closed, steps[0], atol=1e-8)
        assert abs(cost - steps[1]) <= 1e-8 * cost and cost <= steps[1] * (1 + 1e-12)
        settled = refine.final_refit(cls, start, points, 3 * SIGMA, steps=20, min_gain=0.0)[0]
        inliers = points[np.abs(points @ settled[:3] + settled[3]) < 3 * SIGMA]
        centre = inliers.mean(axis=0)
        normal = np.linalg.svd(inliers - centre)[2][-1]
        normal *= np.sign(normal @ settled[:3])
        np.testing.assert_allclose(settled[:3], normal, atol=1e-12)
        np.testing.assert_allclose(settled[3], -normal @ centre, atol=1e-12)
    # too few points for a plane: no candidate, the start stays
    assert np.isnan(cls.host_least_squares(np.zeros((4, 4)), theta)).all()


def test_lo_steps_with_the_analytic_jacobian_land_where_the_jvps_do(monkeypatch):
    # LO's LM steps take the shape's theta_jacobian (``lm_analytic``) in place of JVPs of
    # theta_residual: the same step up to float32 rounding (one round of one step, which
    # a wrong Jacobian would change; converged, both land on the least-squares fit).
    import jax

    cls = REGISTRY["cylinder"]
    assert cls.lm_analytic and cls.theta_jacobian is not None
    points, theta, _ = noisy("cylinder", 2048, seed=6)
    start = theta + np.random.default_rng(7).normal(0, 1e-2, theta.shape)
    args = (np.asarray(start, np.float32), np.asarray(points, np.float32), 2048,
            np.float32(3 * SIGMA))

    def refined():  # (a new function each time: JAX would reuse the first one's trace)
        return [np.asarray(x) for x in jax.jit(
            lambda *a: refine._refine_theta(cls, *a, max_rounds=2, steps=1))(*args)]

    analytic = refined()
    monkeypatch.setattr(cls, "lm_analytic", False)
    jvps = refined()
    np.testing.assert_allclose(analytic[0], jvps[0], atol=2e-5)
    np.testing.assert_allclose(analytic[1], jvps[1], rtol=1e-4)
    assert analytic[2] == jvps[2]
    assert analytic[1] < float(refine._evaluate(cls, start, points.T, 3 * SIGMA, None, None)[0])


def test_lo_in_a_large_bucket_is_judged_on_all_points(monkeypatch):
    # In a bucket of at least LO_SUBSET_BUCKET points a round of LO is accepted on the
    # rows its steps see, and the result is judged against its start on all points: its
    # cost and inlier count are those over all points, never above the start's, and it
    # lands where rounds measured on all points land. (The bucket is lowered to 8192
    # here: a small program to compile.)
    import jax

    from jaxfit.engine.scoring import score_one

    cls = REGISTRY["plane"]
    points, theta, _ = noisy("plane", 5000, seed=8)
    bucket = np.zeros((8192, 3), np.float32)
    bucket[:5000] = points
    start = np.asarray(theta + np.random.default_rng(9).normal(0, 2e-2, theta.shape), np.float32)
    threshold = np.float32(3 * SIGMA)

    def refined():  # (a new function each time: JAX would reuse the first one's trace)
        return [np.asarray(x) for x in jax.jit(lambda *a: refine._refine_theta(cls, *a))(
            start, bucket, 5000, threshold)]

    def scored(t):
        return [np.asarray(x) for x in jax.jit(
            lambda t: score_one(cls, t, bucket, 5000, threshold))(np.asarray(t, np.float32))]

    monkeypatch.setattr(refine, "LO_SUBSET_BUCKET", 8192)
    assert refine.lo_subset(8192) and not refine.lo_subset(4096)
    judged = refined()
    monkeypatch.setattr(refine, "LO_SUBSET_BUCKET", 1 << 30)
    every = refined()
    cost, count = scored(judged[0])
    assert (judged[1], judged[2]) == (cost, count)
    assert judged[1] < scored(start)[0]
    normal = judged[0][:3] / np.linalg.norm(judged[0][:3])
    assert np.degrees(np.arccos(min(1.0, abs(normal @ every[0][:3]) / np.linalg.norm(
        every[0][:3])))) < 0.02
    np.testing.assert_allclose(judged[1], every[1], rtol=1e-3)
    # A result worse than its start on all points gives the start back, with its score.
    worse = np.asarray(start + np.float32(0.05), np.float32)
    back = [np.asarray(x) for x in jax.jit(lambda s, t: refine.lo_judged(
        cls, s, t, bucket, 5000, threshold))(np.asarray(theta, np.float32), worse)]
    np.testing.assert_array_equal(back[0], np.asarray(theta, np.float32))
    assert (back[1], back[2]) == tuple(scored(theta))


@pytest.mark.parametrize("shape", ["plane", "sphere", "cylinder"])
def test_polish_fits_as_lo_does_without_its_program(shape, monkeypatch):
    # FitOptions.polish: LO's refit on the host after the search. The refinement's
    # program is never called, the result is the host refit's own stationary point, and
    # it lies far closer to the truth than the raw minimal-sample fit it starts from.
    cls = REGISTRY[shape]
    points, truth, surface = noisy(shape, 3000, seed=11)
    info = information(shape, truth, surface)
    raw = jaxfit.fit(points, shape, threshold=3 * SIGMA, key=0, refine=False)
    loop = importlib.import_module("jaxfit.engine.loop")

    def no_refinement(*args, **kwargs):
        raise AssertionError("polish must not call the refinement's program")

    monkeypatch.setattr(loop, "refine_many", no_refinement)
    result = jaxfit.fit(points, shape, threshold=3 * SIGMA, key=0, refine=False, polish=True)
    theta = result.model.theta()
    again, _, _ = refine.final_refit(cls, theta, points, 3 * SIGMA)
    assert noise_distance(info, again, theta) < 0.01
    assert noise_distance(info, theta, truth) < 25.0
    assert noise_distance(info, theta, truth) < 0.25 * noise_distance(info, raw.model.theta(),
                                                                    truth)
    assert result.cost < raw.cost and result.num_hypotheses == raw.num_hypotheses


def test_host_lo_takes_the_wide_band_and_never_raises_the_cost():
    # From a start a few noise widths off, LO's band (LO_WIDEN thresholds) lets the fit
    # move; the cost returned is never above the start's.
    cls = REGISTRY["cylinder"]
    points, truth, surface = noisy("cylinder", 2000, seed=3)
    info = information("cylinder", truth, surface)
    rng = np.random.default_rng(0)
    canonical = refine.host_canonical(cls)
    for _ in range(5):
        start = perturbed(info, truth, 30.0, rng, canonical)
        theta, cost, first = refine.host_lo(cls, start, points, 3 * SIGMA)
        assert cost <= first
        assert noise_distance(info, theta, truth) < noise_distance(info, start, truth)


def test_polish_option_is_checked():
    points = np.random.default_rng(0).normal(size=(100, 3))
    with pytest.raises(ValueError, match="polish must be True or False"):
        jaxfit.fit(points, "sphere", refine=False, polish="yes")
    with pytest.raises(ValueError, match="set refine=False"):
        jaxfit.fit(points, "sphere", polish=True)
