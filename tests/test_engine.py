"""The engine's seams: one checked options object, the bounds pytree, and stages that can
be swapped (a sampler, a scorer, a stopping rule and a local optimiser written here, in
the test, each one small class)."""

import dataclasses

import jax.monitoring
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfit
from jaxfit.engine import (
    MSAC,
    AdaptiveStopping,
    Bounds,
    FitOptions,
    LevenbergMarquardt,
    Sampler,
    Scorer,
    Status,
    StoppingRule,
    UniformSampler,
    loop,
)
from jaxfit.engine.refine import LocalOptimizer
from jaxfit.engine.scoring import score_one
from jaxfit.evaluation.synthetic import demo_cloud
from jaxfit.shapes import REGISTRY, Cylinder, Plane, Sphere

POINTS, TRUE, _ = demo_cloud("sphere", count=600, outlier_ratio=0.4, seed=5)


def same(a, b):
    """Whether two FitResults are identical, bit for bit."""
    return (a.model.to_dict() == b.model.to_dict() and np.array_equal(a.inliers, b.inliers)
            and a.cost == b.cost and a.num_hypotheses == b.num_hypotheses
            and a.status == b.status)


def test_options_object_and_keywords_give_the_same_fit():
    by_keywords = jaxfit.fit(POINTS, "sphere", confidence=0.995, max_stall=5000, key=3)
    options = FitOptions(confidence=0.995, max_stall=5000)
    assert same(jaxfit.fit(POINTS, "sphere", options=options, key=3), by_keywords)
    # Keywords replace the object's values.
    loose = FitOptions(confidence=0.5)
    assert same(jaxfit.fit(POINTS, "sphere", options=loose, confidence=0.995, max_stall=5000,
                           key=3), by_keywords)
    # The default stages, given explicitly, are the defaults.
    explicit = FitOptions(sampler=UniformSampler(), scorer=MSAC(), stopping=AdaptiveStopping(),
                          refiner=LevenbergMarquardt())
    assert same(jaxfit.fit(POINTS, "sphere", options=explicit, key=3),
                jaxfit.fit(POINTS, "sphere", key=3))


def test_unknown_or_wrong_options_are_named():
    with pytest.raises(TypeError, match="unknown fit option.*'confidnce'.*confidence"):
        jaxfit.fit(POINTS, "sphere", confidnce=0.9)
    with pytest.raises(TypeError, match="options must be a jaxfit.FitOptions"):
        jaxfit.fit(POINTS, "sphere", options={"confidence": 0.9})
    with pytest.raises(TypeError, match="scorer must be a jaxfit Scorer"):
        jaxfit.fit(POINTS, "sphere", scorer="msac")
    with pytest.raises(TypeError, match="must be hashable"):
        jaxfit.fit(POINTS, "sphere", scorer=MutableScorer())
    with pytest.raises(ValueError, match="unknown estimator"):
        FitOptions(estimator="magic").check(Sphere)
    with pytest.raises(ValueError, match="min_hypotheses must be a non-negative integer"):
        FitOptions(min_hypotheses=True).check(Sphere)


def test_a_kept_check_does_not_pass_equal_values_of_another_type():
    """Checks are kept per options; 256.0 == 256 and True == 1, but only one of each is
    valid, whichever was checked first."""
    assert FitOptions(batch_size=256, min_hypotheses=1).check(Sphere).batch_size == 256
    with pytest.raises(ValueError, match="batch_size must be a positive integer"):
        FitOptions(batch_size=256.0, min_hypotheses=1).check(Sphere)
    with pytest.raises(ValueError, match="min_hypotheses must be a non-negative integer"):
        FitOptions(batch_size=256, min_hypotheses=True).check(Sphere)


def test_check_resolves_for_the_shape_and_is_idempotent():
    checked = FitOptions(batch_size=np.int64(128), radius_range=(0.5, 2)).check(Cylinder)
    assert checked.batch_size == 128 and type(checked.batch_size) is int
    assert checked.estimator == Cylinder.default_estimator
    assert checked.min_hypotheses == Cylinder.estimator().min_hypotheses
    assert checked.check(Cylinder) == checked
    assert (checked.bounds.radius_low, checked.bounds.radius_high) == (0.5, 2.0)
    # A plane asked for the oriented estimator uses its thesis one.
    assert FitOptions(estimator="oriented").check(Plane).estimator == "thesis"
    assert FitOptions(estimator="thesis").check(Cylinder).min_hypotheses == 8192
    with pytest.raises(dataclasses.FrozenInstanceError):
        checked.batch_size = 3


def test_bounds_admit_exactly_the_bounded_hypotheses():
    bounds = Bounds.of(Cylinder, radius_range=(0.2, 0.5), axis_prior=((0, 0, 2), 30))
    assert np.allclose(bounds.axis, [0, 0, 1]) and np.isclose(bounds.axis_cos, np.cos(np.pi / 6))
    assert not bounds.gated and Bounds.of(Cylinder, normal_angle=20).gated

    def cylinder(radius, tilt_deg):
        axis = [np.sin(np.radians(tilt_deg)), 0.0, np.cos(np.radians(tilt_deg))]
        return Cylinder(np.zeros(3), np.asarray(axis), radius, 1.0).theta()

    cases = [(0.3, 0, True), (0.3, 29, True), (0.3, 31, False), (0.3, 151, True),
             (0.1, 0, False), (0.6, 0, False), (0.5, 10, True)]
    for radius, tilt, expected in cases:
        assert bool(bounds.admits(Cylinder, jnp.asarray(cylinder(radius, tilt)))) is expected
    # Scaling moves radii, not directions; stacking gives one row per cloud.
    half = bounds.scaled(2.0)
    assert (half.radius_low, half.radius_high, half.axis_cos) == (0.1, 0.25, bounds.axis_cos)
    rows = Bounds.stack([bounds, half], np.float32)
    assert rows.axis.shape == (2, 3) and rows.radius_low.dtype == np.float32
    with pytest.raises(ValueError, match="radius_range does not apply to a plane"):
        Bounds.of(Plane, radius_range=(0, 1))


# ----- stages written here: each one small class ----------------------------------------

@dataclasses.dataclass(frozen=True)
class RansacScorer(Scorer):
    """Plain RANSAC: an inlier costs nothing, an outlier t^2 (counts inliers only)."""

    def loss(self, r2, t2):
        return jnp.where(r2 < t2, 0.0, t2)

    def inlier(self, r2, t2):
        return r2 < t2


@dataclasses.dataclass
class MutableScorer(Scorer):
    """Not frozen: unhashable, so it cannot be a static argument."""

    scale: float = 1.0

    def loss(self, r2, t2):
        return jnp.minimum(r2, t2) * self.scale

    def inlier(self, r2, t2):
        return r2 < t2


@dataclasses.dataclass(frozen=True)
class RepeatingSampler(Sampler):
    """Every sample is the first point k times: always degenerate."""

    def draw(self, key, n_valid, batch_size, sample_size):
        idx = jnp.zeros((batch_size, sample_size), jnp.int32)
        return idx, jnp.zeros(batch_size, bool)


@dataclasses.dataclass(frozen=True)
class FixedCount(StoppingRule):
    """Stop after a fixed number of hypotheses."""

    count: int = 512

    def status(self, inliers, points, drawn, since_best, sample_size, options):
        return Status.CONVERGED if drawn >= self.count else None


@dataclasses.dataclass(frozen=True)
class KeepAsIs(LocalOptimizer):
    """No change: the hypothesis and its cost as they are."""

    def refine(self, cls, theta, points, n_valid, threshold, bounds, normals, n_chunks, rows,
               scorer):
        gate = None if normals is None else (normals, bounds.normal_cos)
        return (theta, *score_one(cls, theta, points, n_valid, threshold, gate, n_chunks,
                                  scorer))


def test_a_scorer_is_one_class():
    plain = jaxfit.fit(POINTS, "sphere", scorer=RansacScorer(), key=1)
    assert np.linalg.norm(plain.model.center - TRUE.center) < 0.02 * TRUE.radius
    assert abs(plain.model.radius / TRUE.radius - 1) < 0.02


def test_a_sampler_is_one_class_and_is_used():
    with pytest.raises(jaxfit.FitError, match="no valid sphere hypothesis"):
        jaxfit.fit(POINTS, "sphere", sampler=RepeatingSampler(), max_hypotheses=512, key=1)


def test_a_stopping_rule_is_one_class():
    result = jaxfit.fit(POINTS, "sphere", stopping=FixedCount(768), key=1)
    assert result.num_hypotheses == 768 and result.status is Status.CONVERGED


def test_a_local_optimiser_is_one_class():
    kept = jaxfit.fit(POINTS, "sphere", refiner=KeepAsIs(), key=1)
    raw = jaxfit.fit(POINTS, "sphere", refine=False, key=1)
    assert kept.num_hypotheses == raw.num_hypotheses
    np.testing.assert_allclose(kept.model.center, raw.model.center, atol=1e-6)


def test_every_registered_shape_takes_the_same_options():
    options = FitOptions(max_hypotheses=256, refine=False)
    for cls in REGISTRY.values():
        checked = options.check(cls)
        assert checked.estimator in cls.estimators and checked.bounds is not None


_lowerings: list | None = None  # while a list, JAX's lowerings to MLIR go in it


def _record_lowering(name, seconds, **_):
    if _lowerings is not None and name.endswith("jaxpr_to_mlir_module_duration"):
        _lowerings.append(seconds)


jax.monitoring.register_event_duration_secs_listener(_record_lowering)


def _lowered_fitting(refiner, ahead, monkeypatch):
    """(the fit of POINTS with ``refiner``, JAX's lowerings during it)."""
    global _lowerings
    monkeypatch.setattr(loop, "COMPILE_AHEAD", ahead)
    _lowerings = []
    try:
        result = jaxfit.fit(POINTS, "sphere", refiner=refiner, key=3)
    finally:
        found, _lowerings = _lowerings, None
    return result, len(found)


def test_refinement_compiled_ahead_is_the_program_the_loop_runs(monkeypatch):
    # Refiners no other test uses: their refinement compiles here, the kernel does not.
    jaxfit.fit(POINTS, "sphere", key=3)  # (the kernel and the keys, as other tests do)
    ahead, lowered_ahead = _lowered_fitting(LevenbergMarquardt(max_rounds=17), True,
                                            monkeypatch)
    _, lowered_after = _lowered_fitting(LevenbergMarquardt(max_rounds=18), False,
                                        monkeypatch)
    # The call made ahead (zeros of the kernel's output shapes) lowers the same program
    # as the loop's call: no second lowering (an uncommitted array had made one).
    assert lowered_ahead == lowered_after > 0
    again, lowered_again = _lowered_fitting(LevenbergMarquardt(max_rounds=17), False,
                                            monkeypatch)
    assert lowered_again == 0 and same(again, ahead)


def _plane_cloud(n: int, outliers: float, seed: int = 0):
    """(n, 3) float32 points in the unit ball: a noisy plane patch with a share of
    uniform outliers, and the inlier threshold."""
    rng = np.random.default_rng(seed)
    m = int(n * (1 - outliers))
    on = np.column_stack([rng.uniform(-0.5, 0.5, (m, 2)), rng.normal(0, 0.002, m)])
    off = rng.uniform(-0.5, 0.5, (n - m, 3))
    return np.vstack([on, off]).astype(np.float32), 0.006


def test_wide_scan_steps_score_as_the_plain_sum():
    # Over a bucket of more than SCREEN_POINTS points a scan step of few hypotheses spans
    # several chunks (``scan_chunk``): the same costs (float32 rounding) and counts as
    # the sums in float64, and small buckets keep CHUNK.
    from jaxfit.engine import scoring

    assert scoring.scan_chunk(1024, 1) == scoring.CHUNK
    assert scoring.scan_chunk(1 << 17, 256) == scoring.CHUNK
    assert scoring.scan_chunk(1 << 17, 16) == scoring.STEP_PAIRS // 16
    assert scoring.scan_chunk(8192, 1) == 8192  # (at most the bucket)
    points, threshold = _plane_cloud(7000, 0.3)
    padded = np.zeros((8192, 3), np.float32)
    padded[:7000] = points
    thetas = np.array([[0, 0, 1, 0], [0, 0, 1, 0.1], [0.6, 0, 0.8, 0]], np.float32)
    cost, count = scoring.score(Plane, jnp.asarray(thetas), jnp.ones(3, bool),
                                jnp.asarray(padded), 7000, threshold)
    r2 = (points.astype(np.float64) @ thetas[:, :3].T.astype(np.float64) + thetas[:, 3]) ** 2
    np.testing.assert_allclose(np.asarray(cost), np.minimum(r2, threshold**2).sum(axis=0),
                               rtol=1e-4)
    np.testing.assert_array_equal(np.asarray(count), (r2 < threshold**2).sum(axis=0))


def test_screened_kernel_returns_the_all_points_cost_of_the_batch_best(monkeypatch):
    # In a bucket over SCREEN_POINTS only the SCREEN_KEEP best on a spread subset are
    # scored on all points: what the kernel returns is its pick's cost and inlier count
    # over every point, and the pick is as good as the best of the whole batch scored
    # on all points (the screen's premise: the ranking is settled on a few thousand).
    import jax

    from jaxfit.engine import kernel, scoring

    points, threshold = _plane_cloud(3000, 0.5, seed=1)
    padded = np.zeros((4096, 3), np.float32)
    padded[:3000] = points
    args = (jnp.asarray(padded), 3000, jax.random.key(7), jnp.float32(threshold))
    assert padded.shape[0] > scoring.SCREEN_POINTS
    theta, cost, count, _ = kernel.batch_best(Plane, 64, *args)
    full_cost, full_count = score_one(Plane, theta, args[0], 3000, threshold)
    np.testing.assert_allclose(float(cost), float(full_cost), rtol=1e-6)
    assert int(count) == int(full_count) > 1000
    monkeypatch.setattr(kernel, "SCREEN_POINTS", 1 << 20)  # (traced anew: unscreened)
    unscreened = jax.jit(kernel._batch_best, static_argnums=(0, 1))(Plane, 64, *args)
    assert float(cost) <= float(unscreened[1]) * (1 + 1e-6)


def test_kernel_without_counts_picks_and_costs_the_same():
    # A search with LO reads LO's inlier counts, so its kernel skips theirs
    # (counts=False): the same best hypotheses and costs, screened (a bucket over
    # SCREEN_POINTS) or not, and counts of -1.
    import jax

    from jaxfit.engine import kernel, scoring

    points, threshold = _plane_cloud(3000, 0.5, seed=2)
    for size in (scoring.SCREEN_POINTS, 2 * scoring.SCREEN_POINTS):
        padded = np.zeros((size, 3), np.float32)
        n = min(3000, size)
        padded[:n] = points[:n]
        args = (jnp.asarray(padded), n, jax.random.key(8), jnp.float32(threshold))
        run = jax.jit(kernel._batch_best, static_argnums=(0, 1),
                      static_argnames=("top", "counts"))
        with_counts = run(Plane, 64, *args, top=4)
        without = run(Plane, 64, *args, top=4, counts=False)
        for a, b in zip(with_counts[:2] + with_counts[3:], without[:2] + without[3:],
                        strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        assert np.all(np.asarray(with_counts[2]) > 0)
        np.testing.assert_array_equal(np.asarray(without[2]), -1)


def test_map_leading_equals_lax_map_at_every_count():
    # The loop-free cases (one row: called directly; as many rows as the batch: vmapped)
    # give what lax.map gives, None leaves included.
    import jax

    from jaxfit.engine.backend import map_leading

    def fn(args):
        x, none, y = args
        assert none is None
        return jnp.sum(x * y), x[::-1]

    for count, batch in ((1, 4), (4, 4), (8, 4), (6, None)):
        xs = jnp.arange(count * 3, dtype=jnp.float32).reshape(count, 3)
        ys = jnp.linspace(0.5, 2.0, count)
        got = jax.jit(lambda a, b, n=batch: map_leading(fn, (a, None, b), n))(xs, ys)
        want = jax.lax.map(fn, (xs, None, ys), batch_size=batch)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
