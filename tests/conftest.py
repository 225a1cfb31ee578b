"""Shared fixtures. Kernels compile once per (shape, batch size, point bucket): tests use
the default batch size and clouds of 2000 points (bucket 2048) or fewer than 1024
points (bucket 1024), so the whole suite compiles each kernel at most twice.

Randomness: ``getkey()`` gives a fresh JAX key each call (as optimistix's tests do) and
``numpy_rng(key)`` a NumPy generator from one, for the NumPy side (models, points)."""

import functools
import itertools
import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from jaxfit import _cache
from jaxfit.engine.cloud import normalise as unit_ball  # noqa: F401 - the engine's frame
from jaxfit.engine.kernel import estimate_batch as estimate  # noqa: F401 - as the engine calls it
from jaxfit.shapes import REGISTRY

SHAPES = sorted(REGISTRY)
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def run_with_cache(script: str, folder) -> tuple[dict, str]:
    """Run ``script`` in a fresh interpreter caching in ``folder`` (no other cache
    setting of the environment kept): the JSON of its last stdout line, and its stderr."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("JAXFIT_CACHE", "JAX_COMPILATION_CACHE", "JAX_ENABLE_COMP"))}
    env[_cache.ENV_DIR] = str(folder)
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1]), proc.stderr


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def getkey():
    """A function returning a fresh JAX PRNG key each call: the i-th call gives
    ``fold_in(key(0), i)``, so a test's keys are the same on every run and in any order of
    tests, and no two calls within a test share one."""
    base, calls = jax.random.key(0), itertools.count()
    return lambda: jax.random.fold_in(base, next(calls))


def numpy_rng(key) -> np.random.Generator:
    """A NumPy generator seeded from a JAX key (for the NumPy side of a test)."""
    return np.random.default_rng(np.asarray(jax.random.key_data(key)))


def x64():
    """Context manager: float64 JAX inside (``jax.enable_x64`` where JAX has it, else
    ``jax.experimental.enable_x64``), leaving the rest of the suite in float32."""
    if callable(getattr(jax, "enable_x64", None)):
        return jax.enable_x64(True)
    from jax.experimental import enable_x64

    return enable_x64()


@pytest.fixture
def data_dir():
    if not DATA.is_dir():
        pytest.skip(f"shared data not found at {DATA} (it sits beside the checkout)")
    return DATA


@functools.cache
def benchmark_decomposition(name: str):
    """The decomposition of benchmark mesh ``name`` (``benchmarks.grasping.MODELS``, its
    ``NUM_POINTS`` surface points, key 0), computed once for every test that reads it."""
    from benchmarks.grasping import MODELS, NUM_POINTS
    from jaxfit import decompose
    from jaxfit.decomposition.psda import load_source

    return decompose(load_source(DATA / MODELS[name][0], num_points=NUM_POINTS, seed=0),
                     key=0)


def axis_angle_deg(a, b):
    """Angle in degrees between two lines (signs ignored)."""
    c = abs(float(np.dot(a, b))) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(min(1.0, c))))


def matches(fitted, true, tolerance):
    """Whether a fitted primitive is within ``tolerance`` of the true one: every relative
    size error, and every direction error in radians."""
    from jaxfit.evaluation.measures import errors

    if type(fitted) is not type(true):
        return False
    e = errors(true, fitted)
    rel = [v for k, v in e.items() if k.endswith("_rel") or k == "side_rel_max"]
    angles = [np.radians(v) for k, v in e.items() if k.endswith("_deg")]
    return all(v <= tolerance for v in rel + angles)
