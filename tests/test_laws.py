"""Laws every primitive in ``jaxfit.shapes.REGISTRY`` obeys, checked the same way for all.

Each test is parametrized over the registry and reads whatever is particular to a shape
from its class (``num_params``, ``estimators``, ``sample``, ``theta_residual``, ...),
never from its name: a new primitive is tested by these laws as soon as it is
registered. Each law is checked on ``DRAWS`` random models (``synthetic.random_model``)
with points on, near and far from them; every random draw comes from the ``getkey``
fixture.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SHAPES, estimate, numpy_rng, x64

from jaxfit.evaluation.synthetic import random_model
from jaxfit.shapes import REGISTRY, Model

#: Random models per law and shape.
DRAWS = 3
#: Points per model: fixed, so each eager JAX operation is compiled once per shape.
COUNT = 256
#: Inlier threshold for ``from_theta`` (the random models have unit-order sizes), and
#: inliers per model there: bounds along an axis are the main run of bins 5 thresholds
#: wide holding a fifth of the fullest bin's count (``_geometry.main_interval``), which
#: splits a uniform run once bins hold only a few points (at this threshold, 256 points on
#: a cylinder's side lost over a tenth of its height in 65 % of 200 draws, 500 in 15 %).
THRESHOLD = 0.01
DENSE = 2048


def models(name, getkey, count=DRAWS):
    """``count`` random models of the named primitive, each with its own NumPy generator."""
    for _ in range(count):
        rng = numpy_rng(getkey())
        yield random_model(name, rng), rng


def near_and_far(model, rng, count=COUNT):
    """Points (count, 3) pushed off the model's sampled surface along its outward normals:
    half of them within 1 % of the unit size either side, half up to 1 outside (never
    across a centre or axis, where residuals are not smooth), and those normals."""
    surface, normals = model.sample(count, rng)
    offset = np.where(np.arange(count) % 2 == 0, rng.uniform(-0.01, 0.01, count),
                      rng.uniform(0.0, 1.0, count))
    return surface + offset[:, None] * normals, normals


def coordinates(points, xp=np):
    """The (x, y, z) sequence ``theta_residual`` takes, as NumPy or JAX arrays."""
    return tuple(xp.asarray(points[:, i]) for i in range(3))


def assert_same_model(a, b, atol, rtol=0.0):
    """Same primitive, same fields (None where the other is None), within tolerance."""
    assert type(a) is type(b)
    da, db = a.to_dict(), b.to_dict()
    assert da.keys() == db.keys()
    for field in da.keys() - {"type"}:
        assert (da[field] is None) == (db[field] is None), field
        if da[field] is not None:
            np.testing.assert_allclose(da[field], db[field], atol=atol, rtol=rtol, err_msg=field)


# ----- the hypothesis vector ---------------------------------------------------------------

@pytest.mark.parametrize("name", SHAPES)
def test_canonicalize_is_idempotent_and_fixes_a_models_theta(name, getkey):
    cls = REGISTRY[name]
    for model, _ in models(name, getkey):
        theta = jnp.asarray(model.theta(), jnp.float32)
        assert theta.shape == (cls.num_params,)
        np.testing.assert_allclose(cls.canonicalize(theta), theta, atol=1e-6)
        for _ in range(4):  # a refinement step's worth of perturbation
            moved = theta + 0.05 * jax.random.normal(getkey(), theta.shape)
            once = cls.canonicalize(moved)
            assert np.all(np.isfinite(once))
            np.testing.assert_allclose(cls.canonicalize(once), once, atol=1e-6)


@pytest.mark.parametrize("name", SHAPES)
def test_numpy_and_jax_residuals_agree(name, getkey):
    cls = REGISTRY[name]
    for model, rng in models(name, getkey):
        theta = model.theta()
        points = np.vstack([near_and_far(model, rng)[0], rng.uniform(-3, 3, (COUNT, 3))])
        expected = cls.theta_residual(theta, coordinates(points), np)
        assert expected.shape == (2 * COUNT,) and expected.dtype == np.float64
        with x64():
            got = cls.theta_residual(jnp.asarray(theta), coordinates(points, jnp), jnp)
            assert got.dtype == jnp.float64
            np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)
        # and in the engine's float32, to its precision
        got = cls.theta_residual(jnp.asarray(theta, jnp.float32),
                                 coordinates(points.astype(np.float32), jnp), jnp)
        np.testing.assert_allclose(got, expected, atol=1e-5)


@pytest.mark.parametrize("name", SHAPES)
def test_from_theta_round_trips_a_model(name, getkey):
    """From its own theta, points densely on its sampled surface and outliers around
    them, a model is rebuilt: the same unbounded surface exactly, and bounds that
    come from the inliers (heights, patches) within a tenth of the unit size."""
    cls = REGISTRY[name]
    for model, rng in models(name, getkey):
        theta = model.theta()
        points = np.vstack([model.sample(DENSE, rng)[0], rng.uniform(-3, 3, (COUNT, 3))])
        # the engine's inliers: within the threshold of the unbounded surface
        inliers = np.abs(cls.theta_residual(theta, coordinates(points), np)) < THRESHOLD
        again = cls.from_theta(theta, points, inliers, THRESHOLD)
        assert_same_model(again, model, atol=0.1)
        probe = coordinates(rng.uniform(-3, 3, (COUNT, 3)))
        np.testing.assert_allclose(cls.theta_residual(again.theta(), probe, np),
                                   cls.theta_residual(theta, probe, np), atol=1e-12)


@pytest.mark.parametrize("name", SHAPES)
def test_residual_slope_is_a_cosine_in_numpy_and_jax(name, getkey):
    """Model.residual_slope by central differences (NumPy) and by a JVP (JAX) agree, and
    the slope is the cosine between the direction and the surface's normal."""
    cls = REGISTRY[name]
    for model, rng in models(name, getkey):
        theta = model.theta()
        points, _ = near_and_far(model, rng)
        directions = np.asarray(jax.random.normal(getkey(), (COUNT, 3)), np.float64)
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        p, m = coordinates(points), coordinates(directions)
        residual, slope = cls.residual_slope(theta, p, m, np)
        np.testing.assert_allclose(residual, cls.theta_residual(theta, p, np), atol=0)
        assert np.all(np.abs(slope) <= 1 + 1e-6)
        with x64():
            jax_residual, jax_slope = cls.residual_slope(
                jnp.asarray(theta), coordinates(points, jnp), coordinates(directions, jnp), jnp)
            np.testing.assert_allclose(jax_residual, residual, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(jax_slope, slope, atol=1e-6)


@pytest.mark.parametrize("name", SHAPES)
def test_surface_normal_is_the_unit_gradient_of_the_residual(name, getkey):
    """``surface_normal`` is the gradient of the model's own ``residual`` (a box's six
    faces, where ``residual_slope`` reads the hypothesis' three)."""
    for model, rng in models(name, getkey):
        points, _ = near_and_far(model, rng)
        normal = model.surface_normal(points)
        assert normal.shape == points.shape
        np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-9)
        # the residual climbs at rate 1 along it...
        step = 1e-5
        slope = (model.residual(points + step * normal)
                 - model.residual(points - step * normal)) / (2 * step)
        np.testing.assert_allclose(slope, 1.0, atol=1e-5)
        # ...and on the sampled surface it is the surface's normal (either sign)
        surface, true = model.sample(COUNT, rng)
        cos = np.einsum("ij,ij->i", model.surface_normal(surface), true)
        assert np.mean(np.abs(np.abs(cos) - 1.0) < 1e-6) > 0.97


# ----- the bounded model -------------------------------------------------------------------

@pytest.mark.parametrize("name", SHAPES)
def test_residual_is_zero_on_surface_and_measures_offsets(name, getkey):
    for model, rng in models(name, getkey):
        pts, normals = model.sample(COUNT, rng)
        assert np.abs(model.residual(pts)).max() < 1e-9
        assert np.abs(model.distance(pts)).max() < 1e-9
        # A small step along the normal is the distance, away from edges and rims.
        step = 0.01
        d = model.distance(pts + step * normals)
        assert np.median(np.abs(d - step)) < 1e-9
        assert np.all(d <= step + 1e-9)


@pytest.mark.parametrize("name", SHAPES)
def test_rescaling_inverts_and_scales_distances(name, getkey):
    for model, rng in models(name, getkey):
        scale = 10.0 ** rng.uniform(-2, 3)
        shift = rng.normal(size=3) * 10.0 ** rng.uniform(0, 4)
        moved = model.rescaled(scale, shift)
        assert type(moved) is type(model)
        assert_same_model(moved.rescaled(1 / scale, -shift / scale), model, atol=1e-9,
                          rtol=1e-9)
        points = rng.uniform(-2, 2, (COUNT, 3))
        np.testing.assert_allclose(moved.distance(points * scale + shift),
                                   scale * model.distance(points),
                                   atol=1e-12 * np.abs(shift).max() + 1e-9 * scale)


@pytest.mark.parametrize("name", SHAPES)
def test_dict_round_trip_is_exact_and_mesh_lies_on_the_surface(name, getkey):
    for model, _ in models(name, getkey):
        data = model.to_dict()
        again = Model.from_dict(data)
        assert type(again) is type(model)
        assert again.to_dict() == data  # bit for bit
        assert REGISTRY[name].from_dict(data).to_dict() == data
        mesh = model.to_mesh()
        assert len(mesh.faces) > 0
        assert np.abs(model.distance(mesh.vertices)).max() < 1e-6


@pytest.mark.parametrize("name", SHAPES)
def test_models_are_frozen_pytrees_of_their_fields(name, getkey):
    for model, _ in models(name, getkey, count=1):
        leaves, tree = jax.tree_util.tree_flatten(model)
        fields = [getattr(model, f.name) for f in dataclasses.fields(model)]
        assert len(leaves) == sum(value is not None for value in fields)
        doubled = jax.tree_util.tree_map(lambda x: x * 2, model)
        assert type(doubled) is type(model)
        for leaf, twice in zip(leaves, jax.tree_util.tree_leaves(doubled), strict=True):
            np.testing.assert_array_equal(twice, np.asarray(leaf) * 2)
        assert jax.tree_util.tree_unflatten(tree, leaves).to_dict() == model.to_dict()
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(model, dataclasses.fields(model)[0].name, None)


# ----- the estimators ----------------------------------------------------------------------

def degenerate_samples(estimator, rng):
    """Samples (S, k, 3) and normals (S, k, 3) that no estimator can turn into a
    hypothesis: one point k times (with one normal), a repeated point (with its normal),
    all at the origin; collinear points for estimators without normals, parallel normals
    for those with."""
    k = estimator.sample_size
    p = rng.uniform(-0.5, 0.5, (k, 3))
    n = rng.normal(size=(k, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    repeated = np.r_[0, np.arange(k - 1)]
    up = np.tile([0.0, 0.0, 1.0], (k, 1))
    cases = [(p[np.zeros(k, int)], n[np.zeros(k, int)]), (p[repeated], n[repeated]),
             (np.zeros((k, 3)), up)]
    if estimator.uses_normals:
        cases.append((p, up))
    else:
        cases.append((np.outer(np.linspace(0, 1, k), p[1] - p[0]) + p[0], n))
    return tuple(jnp.asarray(np.stack(c), jnp.float32) for c in zip(*cases, strict=True))


@pytest.mark.parametrize("name", SHAPES)
def test_every_estimator_masks_degenerate_samples_without_nan(name, getkey):
    for estimator in REGISTRY[name].estimators.values():
        rng = numpy_rng(getkey())
        samples, normals = degenerate_samples(estimator, rng)
        support = jnp.asarray(rng.uniform(-1, 1, (64, 3)), jnp.float32)  # the unit ball's scale
        thetas, valid = estimate(REGISTRY[name], samples, support, normals, estimator.name)
        assert thetas.shape == (len(samples), REGISTRY[name].num_params)
        assert not np.any(np.asarray(valid)), (estimator.name, np.asarray(valid))
        assert np.all(np.isfinite(np.asarray(thetas))), estimator.name
