"""Bad input raises a ValueError naming the problem, before any JAX work; random and
degenerate clouds give a clear error or a finite model, never a crash or NaN."""

import jax
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import jaxfit

GOOD = np.random.default_rng(0).normal(size=(50, 3))


@pytest.mark.parametrize(
    "points, kwargs, message",
    [
        (GOOD[:, :2], {}, r"shape \(N, 3\)"),
        (GOOD[None], {}, r"shape \(N, 3\)"),
        ([["a", "b", "c"]], {}, "numeric"),
        (np.vstack([GOOD, [np.nan, 0, 0]]), {}, "NaN or inf"),
        (np.vstack([GOOD, [np.inf, 0, 0]]), {}, "NaN or inf"),
        (GOOD[:2], {}, "too few points"),
        (GOOD, {"shape": "torus"}, "unknown shape 'torus'"),
        (GOOD, {"shape": 3}, "unknown shape"),
        (GOOD, {"threshold": 0.0}, "threshold must be a positive"),
        (GOOD, {"threshold": -1.0}, "threshold must be a positive"),
        (GOOD, {"threshold": float("nan")}, "threshold must be a positive"),
        (GOOD, {"confidence": 1.0}, "confidence"),
        (GOOD, {"max_hypotheses": 0}, "max_hypotheses"),
        (GOOD, {"batch_size": 2.5}, "batch_size"),
        (GOOD, {"max_stall": -3}, "max_stall"),
        (GOOD, {"min_hypotheses": -1}, "min_hypotheses"),
        (GOOD, {"radius_range": (2.0, 1.0)}, "radius_range"),
        (GOOD, {"shape": "cylinder", "axis_prior": ((0, 0, 0), 10)}, "axis_prior direction"),
        (GOOD, {"shape": "plane", "axis_prior": ((0, 0, 1), 120)}, "axis_prior angle"),
        (GOOD, {"axis_prior": ((0, 0, 1), 10)}, "axis_prior does not apply to a sphere"),
        (GOOD, {"normal_angle": 0}, "normal_angle must be in"),
        (GOOD, {"normals": GOOD[:10]}, "normals must match"),
        (GOOD, {"normals": np.zeros_like(GOOD)}, "zero vectors"),
        (GOOD, {"normals": np.full_like(GOOD, np.nan)}, "normals contain"),
        (GOOD, {"key": "seven"}, "key must be"),
        (GOOD, {"key": jax.random.split(jax.random.key(0), 3)}, "key must be"),
        (np.ones((20, 3)), {}, "all points coincide"),
        (GOOD + 1j, {}, "numeric.*complex"),
        (GOOD, {"threshold": "0.1"}, "threshold must be a positive finite number, got '0.1'"),
        (GOOD, {"refine": "no"}, "refine must be True or False"),
    ],
)
def test_bad_input_is_named(points, kwargs, message):
    shape = kwargs.pop("shape", "sphere")
    with pytest.raises(ValueError, match=message):
        jaxfit.fit(points, shape, **kwargs)


def test_numbers_in_numpy_form_are_numbers():
    threshold = jaxfit.fit(GOOD, "sphere", threshold=np.array(0.5), max_hypotheses=256).threshold
    assert threshold == 0.5
    fixed = jaxfit.fit(GOOD, "sphere", min_hypotheses=np.int64(512), max_hypotheses=512,
                       max_stall=10**6)
    assert fixed.num_hypotheses == 512


def test_a_batch_skips_and_names_its_failed_clouds():
    """skip_failures gives None for a cloud whose points all coincide (it raised); without
    it the error names the cloud. The other clouds keep their keys fold_in(key, i)."""
    clouds = [GOOD, np.ones((20, 3)), GOOD[::-1].copy()]
    skipped = jaxfit.fit_batch(clouds, "sphere", key=4, skip_failures=True)
    assert skipped[1] is None and skipped[0] is not None and skipped[2] is not None
    whole = jaxfit.fit_batch([GOOD, GOOD, GOOD[::-1].copy()], "sphere", key=4)
    np.testing.assert_allclose(skipped[2].model.center, whole[2].model.center, atol=1e-5)
    with pytest.raises(jaxfit.FitError, match="cloud 1: all points coincide"):
        jaxfit.fit_batch(clouds, "sphere", key=4)


def test_unreachable_bounds_are_named():
    with pytest.raises(jaxfit.FitError, match="none within the bounds radius_range"):
        jaxfit.fit(GOOD, "sphere", radius_range=(50, 60), max_hypotheses=512)


def test_too_few_points_names_the_shape():
    with pytest.raises(ValueError, match="box needs at least 5, got 4"):
        jaxfit.fit(GOOD[:4], "box")


def test_collinear_cloud_gives_a_fit_error():
    line = np.outer(np.linspace(0, 1, 100), [1.0, 2.0, 3.0])
    with pytest.raises(jaxfit.FitError, match="degenerate"):
        jaxfit.fit(line, "plane", max_hypotheses=1024)


finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False, width=32)


def _clouds():
    random = arrays(np.float64, st.tuples(st.integers(5, 300), st.just(3)), elements=finite)
    few_values = st.integers(5, 300).flatmap(
        lambda n: arrays(np.float64, (n, 3), elements=st.sampled_from([0.0, 1.0, -2.5]))
    )
    flat = st.integers(5, 300).map(
        lambda n: np.c_[np.random.default_rng(n).normal(size=(n, 2)), np.zeros(n)]
    )
    return st.one_of(random, few_values, flat)


# (derandomized: CI runs the same 40 cases; explore with a larger max_examples by hand)
@settings(max_examples=40, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(cloud=_clouds(), shape=st.sampled_from(["plane", "sphere", "cylinder", "cone", "box"]))
# (found by this test: every box inlier on one face left no others to bound that axis)
@example(cloud=np.r_[[[0.0, 1.0, 1.0]], np.ones((123, 3))], shape="box")
def test_random_and_degenerate_clouds_give_a_model_or_a_clear_error(cloud, shape):
    try:
        result = jaxfit.fit(cloud, shape, max_hypotheses=1024, key=1)
    except ValueError as err:
        assert str(err)  # a message, not a bare exception
        return
    params = result.model.to_dict()
    for name, value in params.items():
        if name != "type" and value is not None:
            assert np.all(np.isfinite(value)), (name, value)
    assert result.inliers.shape == (len(cloud),)
    assert 0 <= result.num_inliers <= len(cloud)
