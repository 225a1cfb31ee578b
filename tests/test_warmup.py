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


def test_a_decomposition_runs_the_programs_that_warmup_compiles(monkeypatch):
    """Every kernel and refinement a decomposition's fits call (one cloud a loop, padded
    as the 2,048 bucket: ``fit_batch(separate=True)``) is one that ``warmup`` of that
    bucket called: after ``jaxfit warmup``, a decomposition compiles none of its fits'."""
    from jaxfit import _cache
    from jaxfit.decomposition import decompose
    from jaxfit.evaluation.synthetic import composite

    if _cache._enabled_dir is None:  # (Stored keys its programs only in jaxfit's folder)
        pytest.skip("jaxfit's cache is off (JAXFIT_CACHE=0, or JAX's own cache configured): "
                    "no program signatures to read")
    phase = {"now": None}
    calls: dict[str, set] = {"warmup": set(), "decompose": set()}
    original = _cache.Stored._signature

    def recording(self, *args):
        signature = original(self, *args)
        if phase["now"] and self.name.endswith(("_batch_best_many", "_refine_many")):
            calls[phase["now"]].add((self.name, signature))
        return signature

    monkeypatch.setattr(_cache.Stored, "_signature", recording)
    phase["now"] = "warmup"
    warmup(["sphere"], buckets=[2048], workers=1)
    points, _, _ = composite("mallet", seed=0)
    phase["now"] = "decompose"
    result = decompose(points, shapes=["sphere"], key=0)
    phase["now"] = None
    assert len(result.parts) >= 1 and calls["decompose"]
    assert {name for name, _ in calls["decompose"]} == {name for name, _ in calls["warmup"]}
    assert calls["decompose"] <= calls["warmup"]
