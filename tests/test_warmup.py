"""jaxfit.warmup: the programs a default fit runs are compiled ahead of it."""

import jax.monitoring
import numpy as np
import pytest

from jaxfit.engine import fit
from jaxfit.evaluation.synthetic import demo_cloud
from jaxfit.warmup import warmup

_compiles: list | None = None  # while a list, the compilations JAX reports go in it


def _record(name, seconds, **_):
    if _compiles is not None and name.endswith("backend_compile_duration"):
        _compiles.append(seconds)


jax.monitoring.register_event_duration_secs_listener(_record)


def test_after_warmup_a_fit_of_the_bucket_compiles_nothing():
    global _compiles
    # 2,000 points: the 2048 bucket the suite's default fits use (tests/conftest.py)
    seconds = warmup(["sphere"], buckets=[2048], workers=1)
    assert list(seconds) == ["sphere/2048"] and seconds["sphere/2048"] > 0
    points, model, _ = demo_cloud("sphere", count=2000, outlier_ratio=0.2, seed=7)
    _compiles = []
    try:
        result = fit(points, "sphere", key=3)
    finally:
        found, _compiles = _compiles, None
    assert found == []
    assert np.linalg.norm(result.model.center - model.center) < 0.05 * model.radius


@pytest.mark.parametrize("buckets", [[1000], [512], [True], ["1024"]])
def test_buckets_must_be_powers_of_two_of_a_bucket_size(buckets):
    with pytest.raises(ValueError, match="buckets must be powers of two"):
        warmup(["sphere"], buckets=buckets)


def test_an_unknown_shape_or_bad_worker_count_is_named():
    with pytest.raises(ValueError, match="unknown shape 'torus'"):
        warmup(["torus"], buckets=[1024])
    with pytest.raises(ValueError, match="workers must be a positive integer"):
        warmup(["sphere"], buckets=[1024], workers=0)
