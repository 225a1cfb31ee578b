"""``fit.results_many`` (fit_batch's results in array code over blocks of clouds) gives
exactly what ``fit.result`` gives cloud by cloud, and its segment helpers
(``_geometry.segment_medians``, ``main_intervals``, ``Plane.from_theta_many``) what their
one-array twins give. No kernel runs here: the hypotheses are the true models'
parameters, moved a little, in each cloud's normalised frame."""

import importlib

import numpy as np
import pytest

from jaxfit._checks import FitError
from jaxfit.engine.cloud import prepare_many
from jaxfit.engine.options import FitOptions
from jaxfit.engine.stopping import Status
from jaxfit.evaluation.synthetic import demo_cloud
from jaxfit.shapes import REGISTRY, Plane, Sphere
from jaxfit.shapes import _geometry as g

fit_module = importlib.import_module("jaxfit.engine.fit")  # (jaxfit.engine.fit is the function)


def _segments(rng, count):
    """A few kinds of 1-D samples: spread, one-sided, a main run with strays, ties, one
    value."""
    kinds = [lambda n: rng.normal(size=n),
             lambda n: np.abs(rng.normal(size=n)) * rng.uniform(0.01, 3),
             lambda n: np.concatenate([rng.uniform(0, 1, n - n // 5),
                                       rng.uniform(2, 5, n // 5)]),
             lambda n: np.round(rng.uniform(0, 3, n), 1)]
    sizes = rng.integers(1, 400, count)
    sizes[0] = 1
    return [kinds[i % len(kinds)](int(n)) for i, n in enumerate(sizes)]


def test_segment_helpers_are_their_one_array_twins_bit_for_bit(rng):
    segments = _segments(rng, 40)
    values, counts = np.concatenate(segments), [len(s) for s in segments]
    gaps = np.where(np.arange(40) % 3 == 0, 1e-9, rng.uniform(1e-3, 0.3, 40))  # (tiny
    # gaps: the bins np.unique counts in main_interval)
    lo, hi = g.main_intervals(values, counts, gaps)
    medians = g.segment_medians(values, counts)
    for i, s in enumerate(segments):
        assert (lo[i], hi[i]) == g.main_interval(s, gaps[i])
        assert medians[i] == g.median(s)
    # The medians both ways: segments of similar lengths share one padded partition,
    # very unequal ones (mostly padding) are taken one by one.
    for sizes in (rng.integers(300, 400, 50), [1, 2, 3, 2000]):
        segments = [np.round(rng.normal(size=n), 2) for n in sizes]  # (ties)
        medians = g.segment_medians(np.concatenate(segments), sizes)
        assert [float(m) for m in medians] == [float(g.median(s)) for s in segments]
    # Strays far from the main run are cut, not spanned.
    run = np.concatenate([rng.uniform(0, 1, 500), [3.0, 3.5]])
    assert g.main_intervals(run, [len(run)], [0.01])[1][0] < 1.0


def _prepared(shape, count, seed=0):
    """count demo clouds of ``shape`` (prepare_many's Clouds) and thetas (count, P) in
    their normalised frames: the true models', moved by 1 % of their size."""
    made = [demo_cloud(shape, count=int(n), seed=seed + i, outlier_ratio=0.3)
            for i, n in enumerate(np.linspace(60, 700, count))]
    cls = REGISTRY[shape]
    clouds = prepare_many([m[0] for m in made], cls, [None] * count,
                          FitOptions().check(cls).bounds)
    moved = np.random.default_rng(seed)
    thetas = np.stack([m[1].rescaled(1 / c.scale, -c.center / c.scale).theta()
                       + 0.01 * moved.normal(size=cls.num_params)
                       for m, c in zip(made, clouds, strict=True)])
    return cls, clouds, thetas


def _same(a, b):
    return (a.model == b.model and np.array_equal(a.inliers, b.inliers)
            and (a.num_inliers, a.cost, a.num_hypotheses, a.status, a.threshold)
            == (b.num_inliers, b.cost, b.num_hypotheses, b.status, b.threshold))


@pytest.mark.parametrize("shape", ["plane", "sphere"])
def test_results_many_is_result_bit_for_bit(shape, monkeypatch):
    cls, clouds, thetas = _prepared(shape, 24)
    drawn = np.arange(24) * 256
    status = [Status.CONVERGED] * 24
    # Blocks of a few clouds, so that several blocks (and a cloud alone in one) run.
    monkeypatch.setattr(fit_module, "RESULTS_BLOCK", 1500)
    thetas[3] = np.nan  # no valid hypothesis
    thetas[7, -1] += 50.0  # (a plane's offset, a sphere's radius) far from every point
    many = fit_module.results_many(cls, clouds, thetas, drawn, status)
    assert len(many) == len(clouds)
    for j, (cloud, found) in enumerate(zip(clouds, many, strict=True)):
        if j in (3, 7):
            assert found is None  # left to ``result``, which raises the why
            with pytest.raises(FitError):
                fit_module.result(cls, cloud, thetas[j], drawn[j], status[j])
            continue
        assert _same(found, fit_module.result(cls, cloud, thetas[j], drawn[j], status[j]))


def test_plane_from_theta_many_is_from_theta(rng):
    _, clouds, thetas = _prepared("plane", 12, seed=5)
    thresholds = np.asarray([c.threshold / c.scale for c in clouds])
    masks = [np.abs(Plane.theta_residual(t, tuple(c.unit.T), np)) < u
             for t, c, u in zip(thetas, clouds, thresholds, strict=True)]
    many = Plane.from_theta_many(thetas, [c.unit for c in clouds], np.concatenate(masks),
                                 thresholds)
    for t, c, m, u, model in zip(thetas, clouds, masks, thresholds, many, strict=True):
        assert model == Plane.from_theta(t, c.unit, m, float(u))
    # With the clouds' frames: each model rescaled into its cloud's coordinates.
    scales, shifts = rng.uniform(0.1, 10, 12), rng.normal(size=(12, 3)) * 5
    moved = Plane.from_theta_many(thetas, [c.unit for c in clouds], np.concatenate(masks),
                                  thresholds, scales, shifts)
    for model, back, s, c in zip(many, moved, scales, shifts, strict=True):
        assert back == model.rescaled(s, c)


def test_sphere_from_theta_many_is_from_theta_rescaled(rng):
    thetas = rng.normal(size=(9, 4))
    scales, shifts = rng.uniform(0.1, 10, 9), rng.normal(size=(9, 3)) * 5
    many = Sphere.from_theta_many(thetas, [None] * 9, None, None, scales, shifts)
    for t, s, c, model in zip(thetas, scales, shifts, many, strict=True):
        assert model == Sphere.from_theta(t, None, None, None).rescaled(s, c)


def test_results_many_leaves_other_shapes_and_gated_clouds_to_result():
    cls, clouds, thetas = _prepared("cylinder", 4)
    assert not cls.pointwise_theta
    assert fit_module.results_many(cls, clouds, thetas, np.zeros(4, int),
                                   [Status.CONVERGED] * 4) == [None] * 4
    _, spheres, thetas = _prepared("sphere", 4)
    gated = FitOptions(normal_angle=30.0).check(Sphere).bounds
    for c in spheres:
        c.bounds = gated
        c.__dict__.pop("gated", None)
    assert fit_module.results_many(Sphere, spheres, thetas, np.zeros(4, int),
                                   [Status.CONVERGED] * 4) == [None] * 4


def test_plane_rescaled_is_the_field_rule_bit_for_bit(rng):
    # Plane.rescaled writes out Model.rescaled's rule (points p * scale + shift, lengths
    # * scale) and moves the offset; the generic rule and the offset, composed, agree.
    from jaxfit.shapes._base import Model

    for _ in range(50):
        normal = g.unit(rng.normal(size=3))
        plane = Plane(normal, np.float64(rng.normal()), rng.normal(size=3),
                      np.float64(rng.uniform(0.1, 3)))
        scale, shift = float(rng.uniform(0.01, 100)), rng.normal(size=3) * 50
        generic = Model.rescaled(plane, scale, shift)
        offset = np.float64(plane.offset) * scale - (normal[0] * shift[0] + normal[1] * shift[1]
                                                     + normal[2] * shift[2])
        assert plane.rescaled(scale, shift) == Plane(normal, offset, generic.center,
                                                     generic.radius)
    bare = Plane(normal, np.float64(0.5))
    assert bare.rescaled(2.0, np.ones(3)).center is None


def test_sphere_rescaled_is_the_field_rule_bit_for_bit(rng):
    from jaxfit.shapes._base import Model

    for _ in range(50):
        sphere = Sphere(rng.normal(size=3), np.float64(rng.uniform(0.1, 3)))
        scale, shift = float(rng.uniform(0.01, 100)), rng.normal(size=3) * 50
        assert sphere.rescaled(scale, shift) == Model.rescaled(sphere, scale, shift)
