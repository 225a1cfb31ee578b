"""What keeps a first fit's compile and a warm process small (issue 18, item 1): the
refinement's LAPACK-free pieces (``refine.solve_spd``, ``_geometry.smallest_eigenvector``,
``_geometry.inverse_transpose3``), no LAPACK call in any program a fit runs (so a warm
process does not start LAPACK, which imports scipy), and ``import jaxfit`` leaving the
modules a fit does not need unimported. Figures: docs/engine.md, "Compile cost, this
round"."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import run_with_cache

from jaxfit import _cache
from jaxfit.engine import kernel
from jaxfit.engine.options import Bounds
from jaxfit.engine.refine import lo_rows, solve_spd
from jaxfit.shapes import REGISTRY
from jaxfit.shapes import _geometry as g

SHAPES = sorted(REGISTRY)


def spd(rng, size: int, condition: float) -> np.ndarray:
    """A symmetric positive definite (size, size) matrix of about this condition number."""
    basis = np.linalg.qr(rng.normal(size=(size, size)))[0]
    return (basis * np.geomspace(1.0, 1.0 / condition, size)) @ basis.T


@pytest.mark.parametrize("size", [4, 7, 12])
def test_solve_spd_solves_damped_normal_equations(size, rng):
    for condition in (1e1, 1e3, 1e5):
        a, b = spd(rng, size, condition), rng.normal(size=size)
        x = np.asarray(jax.jit(solve_spd)(jnp.asarray(a, jnp.float32), jnp.asarray(b, jnp.float32)))
        exact = np.linalg.solve(a, b)
        # float32 with no pivoting: the backward error of Cholesky, relative error within
        # the condition number times a few float32 epsilons
        assert np.linalg.norm(x - exact) <= 30 * condition * 6e-8 * np.linalg.norm(exact)


def test_solve_spd_of_a_singular_matrix_is_refused_not_wrong():
    """A zero pivot gives a non-finite step, which the LM step's test refuses."""
    x = np.asarray(solve_spd(jnp.zeros((3, 3)), jnp.ones(3)))
    assert not np.all(np.isfinite(x))


def test_smallest_eigenvector_matches_numpy(rng):
    scatters = []
    for _ in range(200):
        points = rng.normal(size=(300, 3)) * rng.uniform(1e-3, 1.0, 3)
        points = points @ np.linalg.qr(rng.normal(size=(3, 3)))[0].T
        scatters.append(points.T @ points)
    scatters = np.array(scatters)
    found = np.asarray(jax.jit(jax.vmap(g.smallest_eigenvector))(
        jnp.asarray(scatters, jnp.float32)), np.float64)
    exact = np.linalg.eigh(scatters)[1][:, :, 0]
    np.testing.assert_allclose(np.linalg.norm(found, axis=1), 1.0, atol=1e-6)
    sines = np.linalg.norm(np.cross(found, exact), axis=1)
    assert np.median(sines) < 1e-6 and sines.max() < 1e-4


def test_smallest_eigenvector_of_diagonal_and_zero_matrices():
    vectors = jax.jit(jax.vmap(g.smallest_eigenvector))(
        jnp.stack([jnp.diag(jnp.array([3.0, 2.0, 1.0])), jnp.zeros((3, 3))]))
    np.testing.assert_allclose(np.abs(vectors[0]), [0.0, 0.0, 1.0])
    assert np.all(np.isfinite(vectors[1]))


def test_inverse_transpose3_is_the_inverse_transpose(rng):
    for _ in range(20):
        m = rng.normal(size=(3, 3))
        np.testing.assert_allclose(g.inverse_transpose3(m, np), np.linalg.inv(m).T, atol=1e-10)
        np.testing.assert_allclose(g.inverse_transpose3(jnp.asarray(m, jnp.float32)),
                                   np.linalg.inv(m).T, rtol=1e-4, atol=1e-4)


def _refinement_arguments(cls):
    """refine_many's arguments for one cloud of 2000 points (bucket 2048), as the loop
    passes them."""
    starts = cls.lo_starts
    return (np.zeros((1, starts, cls.num_params), np.float32), np.zeros((1, starts), np.float32),
            np.zeros((1, 2048, 3), np.float32), np.full(1, 2000, np.int32),
            np.full(1, 0.01, np.float32), Bounds(np.zeros((1, 7), np.float32)))


@pytest.mark.parametrize("name", SHAPES)
def test_the_refinement_makes_no_lapack_call(name):
    """Its program is lowered, not compiled: a LAPACK call in it would make every process
    that runs it start LAPACK (and import scipy)."""
    cls = REGISTRY[name]
    lowered = jax.jit(kernel._refine_many, static_argnames=("cls", "rows")).trace(
        cls, *_refinement_arguments(cls), rows=lo_rows(2000)).lower()
    assert "lapack" not in lowered.as_text()


def test_calls_linear_algebra_tells_programs_apart():
    # (A program's source locations name its functions: this test's name must not
    # contain the word it looks for.)
    from jax import export

    x = jnp.eye(3, dtype=jnp.float32)
    solve = export.export(jax.jit(lambda a, b: jnp.linalg.solve(a, b)))(x, x[0])
    plain = export.export(jax.jit(lambda a: jnp.sin(a) @ a))(x)
    assert _cache.calls_lapack(solve) and not _cache.calls_lapack(plain)


def test_without_lapack_skips_lapacks_start_in_its_block_only(monkeypatch):
    from jax._src.export import _export
    from jax._src.lax import linalg

    started = []
    monkeypatch.setattr(linalg, "initialize_lapack", lambda: started.append(1))
    assert _cache._hook_lapack_start()
    with _cache.without_lapack():
        _export._ensure_backends_initialized(("cpu",))
    assert started == []
    _export._ensure_backends_initialized(("cpu",))
    assert started == [1]


# What a process imports: with the cache folder of a first process, a second one that
# fits one plane (default options: kernel, refinement, final refit) must not start LAPACK.
FIT_SCRIPT = """
import json, sys
import numpy as np
import jaxfit
imported = sorted(m for m in sys.modules if m.startswith(("jaxfit.", "scipy", "trimesh")))
from jaxfit.evaluation.synthetic import demo_cloud
points, _, _ = demo_cloud("plane", count=2000, outlier_ratio=0.2, seed=0)
result = jaxfit.fit(points, "plane", key=0)
print(json.dumps({"on_import": imported, "scipy": "scipy.linalg" in sys.modules,
                  "inliers": result.num_inliers}))
"""


@pytest.mark.slow
def test_a_warm_process_imports_neither_scipy_nor_what_a_fit_does_not_need(tmp_path):
    first = run_with_cache(FIT_SCRIPT, tmp_path)[0]
    second = run_with_cache(FIT_SCRIPT, tmp_path)[0]
    assert second["inliers"] == first["inliers"]
    assert not second["scipy"]  # its stored programs were called without LAPACK
    for lazy in ("jaxfit.decomposition", "jaxfit.detect", "jaxfit.grasping", "jaxfit.batch",
                 "jaxfit.normals", "jaxfit.warmup", "scipy", "trimesh"):
        assert not any(m == lazy or m.startswith(lazy + ".") for m in second["on_import"]), lazy


def test_every_public_name_resolves_and_decompose_stays_the_function():
    import importlib

    import jaxfit

    for name in jaxfit.__all__:
        assert getattr(jaxfit, name) is not None, name
    importlib.import_module("jaxfit.decompose")  # the old module name
    assert callable(jaxfit.decompose) and jaxfit.decompose.__name__ == "decompose"
    assert callable(jaxfit.detect) and callable(jaxfit.warmup)
    assert jaxfit.grasping.__name__ == "jaxfit.grasping"
    assert {"decompose", "grasps", "io"} <= set(dir(jaxfit))
