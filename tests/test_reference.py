"""The NumPy reference (jaxfit.evaluation.reference) against the JAX engine: the same validity flags
and parameters from the same minimal samples, the same MSAC costs and inlier counts, the
same degenerate cases; and the reference's own RANSAC loop on a noisy sphere.

Every engine call uses H = 256 hypotheses and exactly 1024 points, so each jitted
function compiles once per shape."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SHAPES

from jaxfit.engine import backend, kernel, scoring
from jaxfit.engine.cloud import padded as pad
from jaxfit.evaluation import reference
from jaxfit.evaluation.synthetic import demo_cloud, random_model
from jaxfit.shapes import REGISTRY
from jaxfit.shapes._geometry import LEN_TOL, MAX_EXTENT, SIN_TOL
from jaxfit.shapes.box import HISTOGRAM_BINS
from jaxfit.shapes.cone import MIN_ANGLE

H = 256
N = 1024
THRESHOLD = 0.01

jax_estimate = jax.jit(kernel.estimate_batch, static_argnums=0)
jax_score = jax.jit(scoring.score, static_argnums=0)


def unit_cloud(shape, seed=0):
    """The first N points of a demo cloud (50 % outliers) normalised into the unit ball,
    and their ground-truth inlier mask."""
    points, _, truth = demo_cloud(shape, seed=seed)
    center = 0.5 * (points.min(axis=0) + points.max(axis=0))
    scale = np.linalg.norm(points - center, axis=1).max()
    return (points - center)[:N] / scale, truth[:N]


#: Ways each estimator degenerates: ``squeeze`` moves one sample point toward them.
DEGENERACIES = {
    "plane": ("coincident", "collinear"),
    "sphere": ("coincident", "collinear", "in_plane"),
    "cylinder": ("coincident", "collinear"),
    "cone": ("collinear", "in_plane", "on_axis", "on_cylinder"),
    "box": ("collinear", "in_plane", "along_n1"),
}


def squeeze(sample, kind, s):
    """A copy of sample (k, 3) with one point moved to the fraction s of its distance from
    a degenerate configuration of the given kind (s = 0 is degenerate)."""
    p = sample.copy()
    a, b, c = p[:3]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    if kind == "coincident":  # p2 toward p1
        p[1] = a + s * (b - a)
    elif kind == "collinear":  # p3 toward the line (p1, p2)
        foot = a + (c - a) @ (b - a) / ((b - a) @ (b - a)) * (b - a)
        p[2] = foot + s * (c - foot)
    elif kind == "in_plane":  # p4 toward the plane of p1..p3
        p[3] = p[3] - (1 - s) * ((p[3] - a) @ n) * n
    elif kind == "along_n1":  # p5 toward the line through p4 along n
        d = p[4] - p[3]
        p[4] = p[3] + (d @ n) * n + s * (d - (d @ n) * n)
    else:  # on_axis / on_cylinder: p4's distance from the axis toward 0 / the radius
        circle = reference._circle(a, b, c)
        if circle is None:
            return p
        center, n, r = circle
        h = (p[3] - center) @ n
        radial = p[3] - center - h * n
        rho = np.linalg.norm(radial)
        target = s * rho if kind == "on_axis" else r + s * (rho - r)
        p[3] = center + h * n + target / rho * radial
    return p


def draw_samples(shape, seed=0):
    """Minimal samples (H, k, 3) float32 of a unit cloud, its points (N, 3) float32 as the
    support, and the squeeze factors (H,): 3/8 of the samples on the surface, 3/8
    anywhere (factor 1), 1/4 squeezed toward a degenerate configuration by a log-uniform
    factor in [1e-7, 1], so that the validity tests' tolerances are crossed."""
    rng = np.random.default_rng(seed)
    cloud, truth = unit_cloud(shape, seed)
    k = REGISTRY[shape].sample_size
    surface = np.flatnonzero(truth)
    idx = [rng.choice(surface, k, replace=False) for _ in range(3 * H // 8)]
    idx += [rng.choice(N, k, replace=False) for _ in range(H - len(idx))]
    samples, factors = cloud[np.array(idx)], np.ones(H)
    kinds = DEGENERACIES[shape]
    for h in range(3 * H // 4, H):
        factors[h] = 10.0 ** rng.uniform(-7, 0)
        samples[h] = squeeze(samples[h], kinds[h % len(kinds)], factors[h])
    return samples.astype(np.float32), cloud.astype(np.float32), factors


def both_estimates(shape, samples, support):
    """(thetas, valid) of the engine (float32) and of the reference (float64), from the
    same float32 samples and support."""
    thetas, valid = jax_estimate(REGISTRY[shape], jnp.asarray(samples), jnp.asarray(support))
    ref = reference.estimate_batch(shape, samples.astype(np.float64), support.astype(np.float64))
    return (np.asarray(thetas, np.float64), np.asarray(valid)), ref


def borderline(shape, samples, support, monkeypatch, margin=0.01):
    """(H,) True for samples whose reference flag changes when every tolerance is moved
    by ``margin`` (relative) either way: float32 may legitimately decide them otherwise."""
    flags = []
    for factor in (1 + margin, 1 / (1 + margin)):
        with monkeypatch.context() as m:
            m.setattr(reference, "SIN_TOL", SIN_TOL * factor)
            m.setattr(reference, "LEN_TOL", LEN_TOL * factor)
            m.setattr(reference, "MIN_ANGLE", MIN_ANGLE * factor)
            m.setattr(reference, "MAX_EXTENT", MAX_EXTENT / factor)
            flags.append(reference.estimate_batch(shape, samples, support)[1])
    return flags[0] != flags[1]


def uncertain_mode(thetas, moved, support):
    """(H,) True for box hypotheses thetas (H, 12) whose histogram modes could change if
    each projection moved by up to ``moved`` (H,): some other bin could then hold as many
    points as the mode surely does (more, for a bin after the mode: ties go to the first
    bin). Elsewhere the engine and the reference pick the same bins."""
    out = np.zeros(len(thetas), dtype=bool)
    scale = HISTOGRAM_BINS / 2
    for h, theta in enumerate(thetas):
        if not np.all(np.isfinite(theta)):
            continue
        for proj in (support @ theta[:9].reshape(3, 3).T).T:  # (M,) per normal
            lo, mid, hi = (np.clip(np.floor((proj + 1.0 + d) * scale), 0, HISTOGRAM_BINS - 1)
                           .astype(int) for d in (-moved[h], 0.0, moved[h]))
            sure = np.bincount(lo[lo == hi], minlength=HISTOGRAM_BINS)
            possible = np.bincount(lo, minlength=HISTOGRAM_BINS)
            possible += np.bincount(hi[lo != hi], minlength=HISTOGRAM_BINS)
            mode = np.argmax(np.bincount(mid, minlength=HISTOGRAM_BINS))
            out[h] |= (possible[:mode] >= sure[mode]).any()
            out[h] |= (possible[mode + 1:] > sure[mode]).any()
    return out


@pytest.mark.parametrize("shape", SHAPES)
def test_estimators_agree_with_engine(shape, monkeypatch):
    samples, support, factors = draw_samples(shape)
    (jax_thetas, jax_valid), (ref_thetas, ref_valid) = both_estimates(shape, samples, support)
    # Validity: exactly the same flags, except within 1 % of a tolerance.
    skip = borderline(shape, samples.astype(np.float64), support.astype(np.float64), monkeypatch)
    assert skip.sum() <= H // 20, f"{skip.sum()} borderline samples: the check lost its teeth"
    np.testing.assert_array_equal(jax_valid[~skip], ref_valid[~skip])
    assert (~ref_valid[factors < 1]).sum() >= 8  # the squeezed samples reach degeneracy
    assert np.all(np.isnan(ref_thetas[~ref_valid]))
    # Parameters, where float32 can resolve them: not for the samples squeezed close to a
    # degeneracy (the engine's float32 arithmetic loses digits there).
    both = jax_valid & ref_valid & (factors > 1e-2)
    if shape == "box":
        # The offsets are histogram modes: skip hypotheses whose fullest bin could change
        # by the normals' float32 error (support in the unit ball: |d proj| <= |d n|).
        moved = np.abs(jax_thetas[:, :9] - ref_thetas[:, :9]).max(axis=1) * 3 + 1e-6
        mode_skip = uncertain_mode(ref_thetas, moved, support.astype(np.float64))
        assert (mode_skip & both).sum() <= H // 10
        both &= ~mode_skip
    assert both.sum() >= H // 2  # enough valid hypotheses to compare
    np.testing.assert_allclose(jax_thetas[both], ref_thetas[both], rtol=1e-3, atol=1e-3)


@pytest.mark.parametrize("shape", SHAPES)
def test_scores_agree_with_engine(shape):
    samples, support, _ = draw_samples(shape, seed=1)
    cloud = jnp.asarray(support)  # exactly N = 1024 points: no padding needed
    thetas, valid = jax_estimate(REGISTRY[shape], jnp.asarray(samples), cloud)
    costs, counts = jax_score(REGISTRY[shape], thetas, valid, cloud, N, jnp.float32(THRESHOLD))
    ref_costs, ref_counts = reference.score_batch(
        shape, np.asarray(thetas, np.float64), np.asarray(valid), support.astype(np.float64),
        THRESHOLD)
    valid = np.asarray(valid)
    assert valid.sum() >= H // 4
    np.testing.assert_array_equal(np.isinf(ref_costs), ~valid)
    np.testing.assert_array_equal(np.isinf(np.asarray(costs)), ~valid)
    np.testing.assert_allclose(np.asarray(costs)[valid], ref_costs[valid], rtol=1e-4)
    assert np.abs(np.asarray(counts)[valid] - ref_counts[valid]).max() <= 2
    assert np.all(ref_counts[~valid] == 0)


@pytest.mark.parametrize("shape", SHAPES)
def test_msac_cost_matches_score_batch(shape):
    cloud, _ = unit_cloud(shape)
    samples, support, _ = draw_samples(shape)
    thetas, valid = reference.estimate_batch(shape, samples[:8], support)
    costs, counts = reference.score_batch(shape, thetas, valid, cloud, THRESHOLD)
    for h in np.flatnonzero(valid):
        cost, count = reference.msac_cost(shape, thetas[h], cloud, THRESHOLD)
        assert cost == pytest.approx(costs[h], rel=1e-12) and count == counts[h]


def degenerate_samples(shape, rng):
    """Named degenerate minimal samples (k, 3) of a shape, in the unit ball."""
    k = REGISTRY[shape].sample_size
    p = rng.uniform(-0.5, 0.5, (k, 3))
    a, b = p[0], p[1]
    out = {
        "repeated": np.vstack([p[:1], p[:1], p[2:]]),
        "repeated_last": np.vstack([p[:-1], p[-2:-1]]),
        "collinear": np.vstack([a, b, 0.3 * a + 0.7 * b, p[3:]]),
    }
    if shape == "sphere":
        out["coplanar"] = np.vstack([p[:3], p[0] + 0.4 * (p[1] - p[0]) + 0.5 * (p[2] - p[0])])
    if shape in ("cone", "box"):
        u, v = p[1] - p[0], p[2] - p[0]
        out["p4_in_plane"] = np.vstack([p[:3], p[0] + 0.2 * u + 0.6 * v, p[4:]])
    if shape == "cone":
        center, normal, radius = reference._circle(*p[:3])
        out["p4_on_axis"] = np.vstack([p[:3], center + 0.3 * normal])
        side = p[0] - center
        out["p4_on_cylinder"] = np.vstack([p[:3], center + side + 0.3 * normal])
        # half-angle ~ atan(0.005 / 0.3), but the apex ~ 60 r away
        shrink = 1.0 - 0.005 / np.linalg.norm(side)
        out["far_apex"] = np.vstack([p[:3], center + shrink * side + 0.3 * normal])
    if shape == "box":
        n1 = np.cross(p[1] - p[0], p[2] - p[0])
        out["p5_above_p4"] = np.vstack([p[:4], p[3] + 0.2 * n1])
    return out


@pytest.mark.parametrize("shape", SHAPES)
def test_degenerate_samples_are_invalid_in_both(shape):
    rng = np.random.default_rng(7)
    cases = degenerate_samples(shape, rng)
    names = list(cases)
    samples = np.stack([cases[name] for name in names])
    samples = np.resize(samples, (H, *samples.shape[1:])).astype(np.float32)  # one compile
    support = unit_cloud(shape)[0].astype(np.float32)
    (_, jax_valid), (ref_thetas, ref_valid) = both_estimates(shape, samples, support)
    for i, name in enumerate(names):
        assert not jax_valid[i], f"engine: {shape} sample '{name}' should be invalid"
        assert not ref_valid[i], f"reference: {shape} sample '{name}' should be invalid"
        assert np.all(np.isnan(ref_thetas[i]))
        theta, ok = reference.estimate(shape, cases[name], support)
        assert not ok and np.all(np.isnan(theta))


def ring(origin, axis, radius, angles):
    """Points (len(angles), 3) on the circle of the given centre, unit normal and radius."""
    basis = np.linalg.svd(np.eye(3) - np.outer(axis, axis))[0][:, :2]  # (3, 2) orthonormal
    return origin + radius * np.stack([np.cos(angles), np.sin(angles)], 1) @ basis.T


def test_reference_is_exact_on_clean_samples():
    """Noise-free minimal samples give the true parameters (float64, no engine)."""
    rng = np.random.default_rng(3)
    sphere = random_model("sphere", rng)
    theta, ok = reference.estimate("sphere", sphere.sample(4, rng)[0])
    assert ok
    np.testing.assert_allclose(theta, sphere.theta(), atol=1e-9)

    plane = random_model("plane", rng)
    theta, ok = reference.estimate("plane", plane.sample(3, rng)[0])
    sign = np.sign(theta[:3] @ plane.normal)
    assert ok
    np.testing.assert_allclose(sign * theta, plane.theta(), atol=1e-9)

    cylinder = random_model("cylinder", rng)
    points = ring(cylinder.center, cylinder.axis, cylinder.radius, rng.uniform(0, 6.3, 3))
    theta, ok = reference.estimate("cylinder", points)
    sign = np.sign(theta[3:6] @ cylinder.axis)
    assert ok
    np.testing.assert_allclose(theta[:3], cylinder.center, atol=1e-9)
    np.testing.assert_allclose(sign * theta[3:6], cylinder.axis, atol=1e-9)
    assert theta[6] == pytest.approx(cylinder.radius, abs=1e-9)

    cone = random_model("cone", rng)
    tan = math.tan(cone.half_angle)
    points = np.vstack([
        ring(cone.apex + 0.8 * cone.height * cone.axis, cone.axis, 0.8 * cone.height * tan,
             rng.uniform(0, 6.3, 3)),
        ring(cone.apex + 0.3 * cone.height * cone.axis, cone.axis, 0.3 * cone.height * tan,
             rng.uniform(0, 6.3, 1)),
    ])
    theta, ok = reference.estimate("cone", points)
    assert ok
    np.testing.assert_allclose(theta, cone.theta(), atol=1e-9)


def test_reference_box_on_clean_sample():
    """p1..p3 on one face and p4, p5 on an adjacent one give the box's axes; the offsets
    are the faces' offsets (nearly: the mode bin also holds a few points of the faces
    across it)."""
    rng = np.random.default_rng(4)
    box = random_model("box", rng)
    support = box.sample(N, rng)[0]
    center = 0.5 * (support.min(axis=0) + support.max(axis=0))
    scale = np.linalg.norm(support - center, axis=1).max()
    box = box.rescaled(1 / scale, -center / scale)
    support = (support - center) / scale
    rot, half = box.rotation, box.extents / 2
    local = rng.uniform(-0.9, 0.9, (5, 3)) * half
    local[:3, 0], local[3:, 1] = half[0], half[1]
    theta, ok = reference.estimate("box", local @ rot.T + box.center, support)
    assert ok
    normals = theta[:9].reshape(3, 3)
    np.testing.assert_allclose(np.abs(normals @ rot), np.eye(3), atol=1e-9)
    faces = np.abs(theta[9:] - normals @ box.center)
    np.testing.assert_allclose(faces, half, atol=2e-3)


def test_ransac_finds_noisy_sphere():
    points, model, _ = demo_cloud("sphere", seed=5)
    center = 0.5 * (points.min(axis=0) + points.max(axis=0))
    scale = np.linalg.norm(points - center, axis=1).max()
    unit = (points - center) / scale
    truth = model.rescaled(1 / scale, -center / scale)
    out = reference.ransac(unit, "sphere", threshold=THRESHOLD, seed=0)
    assert out["status"] == "converged"  # T ~ 70 for w ~ 0.5, k = 4
    assert np.linalg.norm(out["theta"][:3] - truth.center) < 0.02 * truth.radius
    assert abs(out["theta"][3] - truth.radius) < 0.02 * truth.radius
    assert out["inliers"].sum() == out["num_inliers"] >= 0.4 * len(unit)
    assert out["num_hypotheses"] <= 10_000
    again = reference.ransac(unit, "sphere", threshold=THRESHOLD, seed=0)
    assert again["num_hypotheses"] == out["num_hypotheses"] and again["cost"] == out["cost"]
    np.testing.assert_array_equal(again["theta"], out["theta"])
    np.testing.assert_array_equal(again["inliers"], out["inliers"])


def test_ransac_statuses():
    unit, _ = unit_cloud("sphere")
    out = reference.ransac(unit, "sphere", threshold=THRESHOLD, max_hypotheses=3)
    assert out["status"] == "max_hypotheses" and out["num_hypotheses"] == 3
    out = reference.ransac(unit, "sphere", threshold=THRESHOLD, max_stall=1)
    assert out["status"] == "stalled"
    # Every sample degenerate: no model, and the loop still ends.
    line = np.outer(np.linspace(-0.5, 0.5, 50), [1.0, 2.0, 3.0]) / 4
    out = reference.ransac(line, "sphere", threshold=THRESHOLD, max_hypotheses=20)
    assert out["status"] == "max_hypotheses" and out["num_inliers"] == 0
    assert math.isinf(out["cost"]) and np.all(np.isnan(out["theta"]))
    with pytest.raises(ValueError):
        reference.estimate("box", np.zeros((5, 3)))  # the box needs its support


@pytest.mark.parametrize("shape", ["sphere", "cylinder", "box"])
def test_tuned_kernel_equals_plain_kernel(shape):
    # The per-function XLA CPU options (fast min/max, vector width) must not change what
    # the kernel picks: same best hypothesis, cost and inlier count as a plain jax.jit.
    cls = REGISTRY[shape]
    cloud, _ = unit_cloud(shape)
    padded = jnp.asarray(pad(cloud, np.float32))
    args = (padded, cloud.shape[0], jax.random.key(3), jnp.float32(THRESHOLD))
    tuned = kernel.batch_best(cls, 256, *args)
    plain = jax.jit(kernel.batch_best.__wrapped__, static_argnums=(0, 1))(cls, 256, *args)
    np.testing.assert_allclose(np.asarray(tuned[0]), np.asarray(plain[0]), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(float(tuned[1]), float(plain[1]), rtol=1e-5)
    assert int(tuned[2]) == int(plain[2]) and int(tuned[3]) == int(plain[3])


def test_refused_xla_options_fall_back_with_a_warning(monkeypatch):
    # A jax version that drops an experimental option must not break fitting.
    monkeypatch.setattr(backend, "CPU_OPTIONS", {"xla_cpu_no_such_option_for_jaxfit": True})
    double = backend.jit_tuned(lambda x: 2 * x)
    if jax.default_backend() != "cpu":
        pytest.skip("the options apply to the CPU backend only")
    with pytest.warns(RuntimeWarning, match="XLA CPU options refused"):
        out = double(jnp.arange(3.0))
    np.testing.assert_array_equal(np.asarray(out), [0.0, 2.0, 4.0])
    np.testing.assert_array_equal(np.asarray(double(jnp.arange(2.0))), [0.0, 2.0])
