"""The host path's array versions (issue 18, items 2 and 5) give exactly what their
cloud-by-cloud twins give: ``prepare_many`` the Clouds of ``prepare``, ``stacked`` and
``unit_bounds`` the padded per-slot arrays, ``AdaptiveStopping.status_many`` the answers
of ``status``; and where a cloud is bad, ``fit_batch`` still names it. No kernel runs
here but one small batch (the suite's 1024 bucket)."""

import importlib
import math

import numpy as np
import pytest

import jaxfit
from jaxfit.engine import loop
from jaxfit.engine.cloud import (
    MIN_BUCKET,
    default_threshold,
    for_shape,
    padded,
    prepare,
    prepare_many,
    shared,
)
from jaxfit.engine.options import Bounds, FitOptions
from jaxfit.engine.stopping import AdaptiveStopping, required_hypotheses
from jaxfit.evaluation.synthetic import demo_cloud
from jaxfit.shapes import Cone, Cylinder, Plane, Sphere

fit_module = importlib.import_module("jaxfit.engine.fit")  # (jaxfit.engine.fit is the function)


def _clouds(rng, sizes, dtype=np.float64):
    return [(rng.normal(size=(n, 3)) * rng.uniform(0.1, 50) + rng.uniform(-1e3, 1e3, 3))
            .astype(dtype) for n in sizes]


def _same(a, b):
    return (np.array_equal(a.points, b.points) and np.array_equal(a.center, b.center)
            and a.scale == b.scale and a.threshold == b.threshold
            and np.array_equal(a.unit, b.unit) and a.unit.strides == b.unit.strides
            and a.bounds is b.bounds
            and a.normals is None and a.pool is None and a.wanted is None)


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int32])
def test_prepare_many_is_prepare_bit_for_bit(rng, dtype):
    bounds = FitOptions(radius_range=(0.5, 90.0)).check(Sphere).bounds
    clouds = _clouds(rng, [4, 500, 37, 2048, 3000, 999], dtype)
    thresholds = [None, 0.02, None, 1, None, np.float32(0.5)]
    many = prepare_many(clouds, Sphere, thresholds, bounds)
    one = [prepare(c, Sphere, None, t, False, 0, i, bounds)
           for i, (c, t) in enumerate(zip(clouds, thresholds, strict=True))]
    assert len(many) == len(one)
    assert all(_same(a, b) for a, b in zip(many, one, strict=True))


def test_prepare_many_default_thresholds_are_default_threshold_bit_for_bit(rng):
    # (computed for all clouds at once by stacked matmul, which must sum as the dot of
    # default_threshold does: checked over many extents, as that depends on the BLAS)
    clouds = [c[:4] * rng.choice([1e-3, 1.0, 1e3]) for c in _clouds(rng, [4] * 3000)]
    many = prepare_many(clouds, Sphere, [None] * len(clouds), FitOptions().check(Sphere).bounds)
    assert [c.threshold for c in many] == [default_threshold(c.max(axis=0) - c.min(axis=0))
                                           for c in clouds]


def test_prepare_many_in_halves_is_prepare_bit_for_bit(rng, monkeypatch):
    # A call of at least SPLIT_POINTS points is prepared in two halves side by side
    # (lowered here, and two cores pretended, so that these few clouds take that path).
    cloud_module = importlib.import_module("jaxfit.engine.cloud")
    monkeypatch.setattr(cloud_module, "SPLIT_POINTS", 1000)
    monkeypatch.setattr(cloud_module, "cores", lambda: 2)
    bounds = FitOptions().check(Sphere).bounds
    clouds = _clouds(rng, [500, 37, 2048, 3000, 999])
    thresholds = [0.02, None, 1, None, np.float32(0.5)]
    many = prepare_many(clouds, Sphere, thresholds, bounds)
    one = [prepare(c, Sphere, None, t, False, 0, i, bounds)
           for i, (c, t) in enumerate(zip(clouds, thresholds, strict=True))]
    assert len(many) == len(one)
    assert all(_same(a, b) for a, b in zip(many, one, strict=True))
    for bad in (0, 4):  # a bad cloud in either half sends the call to prepare
        broken = list(clouds)
        broken[bad] = broken[bad].copy()
        broken[bad][1, 1] = np.nan
        assert prepare_many(broken, Sphere, thresholds, bounds) is None


@pytest.mark.parametrize("cls", [Plane, Sphere, Cylinder, Cone])
@pytest.mark.parametrize("gate", [None, 20.0])
def test_a_shared_cloud_is_what_prepare_makes_for_each_shape(rng, cls, gate):
    # detect prepares each group once for every shape (``shared``), and ``for_shape``
    # must give each shape the Cloud ``prepare`` gives it: normals kept only where the
    # estimator or the gate reads them, the shape's bounds.
    points = _clouds(rng, [300])[0]
    normals = rng.normal(size=(300, 3)) * 5.0
    checked = FitOptions(normal_angle=gate).check(cls)
    uses = cls.estimator(checked.estimator).uses_normals
    base = shared(points, normals, 0.05)
    made = for_shape(base, cls, uses, checked.bounds)
    want = prepare(points, cls, normals, 0.05, uses, 0, 0, checked.bounds)
    for name in ("points", "center", "unit", "columns", "normals"):
        assert np.array_equal(getattr(made, name), getattr(want, name)), name
    assert (made.normals is None) == (want.normals is None)
    assert (made.scale, made.threshold, made.bounds, made.pool, made.wanted) == \
        (want.scale, want.threshold, want.bounds, want.pool, want.wanted)
    assert made.gated == want.gated and base.bounds is None  # (the base is left as it was)
    with pytest.raises(ValueError, match="too few points: a sphere needs at least 4, got 3"):
        for_shape(shared(points[:3], normals[:3], 0.05), Sphere, True, checked.bounds)
    with pytest.raises(ValueError, match="needs its normals"):
        shared(points, None, 0.05)


def test_started_shared_gives_what_started_batch_gives():
    clouds = [demo_cloud("cylinder", count=n, seed=n) for n in (400, 900)]
    points = [c[0] for c in clouds]
    normals = [np.asarray(jaxfit.estimate_normals(p, orient=None)) for p in points]
    flat = np.zeros((30, 3))  # coincident: shared raises, and the call skips it
    with pytest.raises(jaxfit.FitError):
        shared(flat, np.ones((30, 3)), 0.05)
    kw = dict(key=5, skip_failures=True, separate=True, refine=False)
    for shape in ("plane", "cylinder"):
        a = fit_module.started_batch(points[:1] + [flat] + points[1:], shape,
                                     normals=normals[:1] + [np.ones((30, 3))] + normals[1:],
                                     thresholds=0.05, **kw)()
        b = fit_module.started_shared([shared(points[0], normals[0], 0.05), None,
                                       shared(points[1], normals[1], 0.05)], shape, **kw)()
        assert a[1] is None and b[1] is None
        for x, y in ((a[0], b[0]), (a[2], b[2])):
            assert x.model == y.model and np.array_equal(x.inliers, y.inliers)
            assert (x.cost, x.num_hypotheses, x.status) == (y.cost, y.num_hypotheses, y.status)


@pytest.mark.parametrize("shape", ["plane", "sphere"])
def test_fit_batch_gives_what_the_cloud_by_cloud_path_gives(shape):
    # Lists are not arrays: they take prepare's path, arrays prepare_many's (a plane's
    # patch had moved by ulps when the unit points were laid out in columns).
    clouds = [demo_cloud(shape, count=n, seed=n)[0] for n in (300, 1000, 640, 90)]
    assert len(clouds) >= fit_module.MANY_MIN
    fast = jaxfit.fit_batch(clouds, shape, key=3)
    slow = jaxfit.fit_batch([c.tolist() for c in clouds], shape, key=3)
    for a, b in zip(fast, slow, strict=True):
        assert a.model == b.model and np.array_equal(a.inliers, b.inliers)
        assert (a.cost, a.num_hypotheses, a.status) == (b.cost, b.num_hypotheses, b.status)


def test_prepare_many_leaves_bad_clouds_to_prepare(rng):
    bounds = FitOptions().check(Sphere).bounds
    good = _clouds(rng, [50, 60])
    nan, inf, big = good[0].copy(), good[0].copy(), good[0].copy()
    nan[3, 1], inf[7, 2], big[0, 0] = np.nan, -np.inf, 1e200
    flat = np.zeros((20, 3))  # coincident points
    tiny = good[0] * 1e-150  # spans less than MIN_EXTENT
    for bad in (nan, inf, big, flat, tiny, good[0][:3], good[0].astype(complex),
                good[0].T.copy(), good[0].tolist()):
        assert prepare_many([good[1], bad], Sphere, [None, None], bounds) is None
    assert prepare_many(good, Sphere, [None, -1.0], bounds) is None  # a bad threshold
    assert prepare_many(good, Sphere, [None, "x"], bounds) is None


def test_fit_batch_still_names_the_bad_cloud(rng):
    clouds = _clouds(rng, [200] * fit_module.MANY_MIN)
    clouds[1][5, 0] = np.nan
    with pytest.raises(ValueError, match="cloud 1: points contain 1 row"):
        jaxfit.fit_batch(clouds, "sphere")
    clouds[1] = np.zeros((30, 3))  # coincident: skipped with skip_failures, else named
    with pytest.raises(jaxfit.FitError, match="cloud 1: all points coincide"):
        jaxfit.fit_batch(clouds, "sphere")
    with pytest.raises(ValueError, match="cloud 2: threshold must be a positive"):
        jaxfit.fit_batch(_clouds(rng, [200] * 4), "sphere", thresholds=[0.1, 0.1, 0.0, 0.1])


def test_fit_batch_skips_a_coincident_cloud_as_before(rng):
    points, truth, _ = demo_cloud("sphere", count=500, seed=3)
    results = jaxfit.fit_batch([points, np.ones((30, 3)), points, points], "sphere",
                               skip_failures=True)
    assert results[1] is None
    for r in (results[0], results[2], results[3]):
        assert np.linalg.norm(r.model.center - truth.center) < 0.02 * truth.radius


def test_default_threshold_is_the_norm_of_the_sides(rng):
    sides = rng.uniform(0, 10, (2000, 3)) * 10.0 ** rng.integers(-60, 60, (2000, 1))
    assert all(default_threshold(s) == 0.005 * float(np.linalg.norm(s)) for s in sides)


def test_stacked_and_unit_bounds_are_the_padded_stack(rng):
    bounds = FitOptions(axis_prior=((0, 0, 1), 30)).check(Cylinder).bounds
    clouds = prepare_many(_clouds(rng, [300, 1000, 20]), Cylinder, [None] * 3, bounds)
    order = [0, 1, 2, 0]  # a padding slot repeats cloud 0
    rows = [clouds[i].unit for i in order]
    expected = np.stack([padded(r, np.float32, MIN_BUCKET) for r in rows])
    got = loop.stacked([c.unit for c in clouds], len(order), np.float32, MIN_BUCKET)
    assert got.dtype == np.float32 and np.array_equal(got, expected)
    stack = Bounds.stack([clouds[i].unit_bounds() for i in order], np.float32)
    assert np.array_equal(loop.unit_bounds([clouds[i] for i in order], np.float32).values,
                          stack.values)
    own = prepare(clouds[2].points, Cylinder, None, None, False, 0, 2, Bounds.make(0.0, 5.0))
    mixed = [clouds[0], own]  # clouds of other bounds: each its own
    assert np.array_equal(loop.unit_bounds(mixed, np.float64).values,
                          Bounds.stack([c.unit_bounds() for c in mixed], np.float64).values)


def test_status_many_answers_as_status(rng):
    rule = AdaptiveStopping()
    for confidence, min_hypotheses, sample_size in ((0.99, 0, 4), (0.999, 256, 3),
                                                    (0.9, 8192, 2), (0.5, 0, 6)):
        options = FitOptions(confidence=confidence, min_hypotheses=min_hypotheses,
                             max_stall=3000).check(Sphere)
        count = 20000
        points = rng.integers(5, 5000, count)
        inliers = np.minimum(points, rng.integers(0, 5000, count)).astype(np.float64)
        inliers[:50], inliers[50:100] = 0, points[50:100]  # none, and all, inliers
        drawn = rng.integers(1, 200, count) * 256
        # T itself, and one either side of it, as drawn: the rule's edge
        edge = np.asarray([min(required_hypotheses(i / p, sample_size, confidence), 1e9)
                           for i, p in zip(inliers[100:3000], points[100:3000], strict=True)])
        drawn[100:3000] = np.maximum(edge, 1).astype(np.int64) + rng.integers(-1, 2, 2900)
        since = np.minimum(drawn, rng.integers(0, 6000, count))
        many = rule.status_many(inliers, points, drawn, since, sample_size, options)
        one = [rule.status(*v, sample_size, options)
               for v in zip(inliers, points, drawn, since, strict=True)]
        assert many == one


def test_status_many_default_asks_status():
    class Every512(AdaptiveStopping):
        def status(self, inliers, points, drawn, since_best, sample_size, options):
            return jaxfit.Status.CONVERGED if drawn >= 512 and math.isfinite(inliers) else None

    drawn = np.array([256, 512, 768])
    answers = super(AdaptiveStopping, Every512()).status_many(
        np.ones(3), np.full(3, 10), drawn, drawn, 4, None)
    assert answers == [None, jaxfit.Status.CONVERGED, jaxfit.Status.CONVERGED]
