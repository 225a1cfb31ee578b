"""Validation of user input, done in NumPy before any JAX call so that every mistake
gets a ValueError naming it instead of a failure deep inside a traced function."""

from __future__ import annotations

import functools
import numbers

import jax
import jax.numpy as jnp
import numpy as np

from .shapes import REGISTRY, Model


class FitError(ValueError):
    """The input is well-formed but no model could be fitted to it (e.g. every sample
    of a degenerate cloud was invalid)."""


def model_class(shape) -> type[Model]:
    """The model class for a name ("cylinder") or a class (jaxfit.Cylinder)."""
    if isinstance(shape, type) and issubclass(shape, Model) and shape in REGISTRY.values():
        return shape
    if isinstance(shape, str) and shape.strip().lower() in REGISTRY:
        return REGISTRY[shape.strip().lower()]
    raise ValueError(f"unknown shape {shape!r}; expected one of {sorted(REGISTRY)} or its class")


def cloud(points, name: str = "points") -> np.ndarray:
    """An (N, 3) float64 copy of ``points``; raises on wrong shape or non-finite values."""
    try:
        if np.iscomplexobj(points):  # (float64 would drop the imaginary part, with a warning)
            raise TypeError(f"complex values ({np.asarray(points).dtype})")
        arr = np.array(points, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} must be numeric, of shape (N, 3): {err}") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {arr.shape}")
    if not np.isfinite(arr).all():  # (the row-wise test is 20x slower: only on failure)
        rows = np.flatnonzero(~np.isfinite(arr).all(axis=1))
        raise ValueError(
            f"{name} contain {rows.size} row(s) with NaN or inf values, e.g. row {rows[0]}"
        )
    return arr


def points_for(points, cls: type[Model]) -> np.ndarray:
    arr = cloud(points)
    if arr.shape[0] < cls.sample_size:
        raise ValueError(
            f"too few points: a {cls.name} needs at least {cls.sample_size}, got {arr.shape[0]}"
        )
    return arr


def normals_for(normals, points: np.ndarray):
    if normals is None:
        return None
    arr = cloud(normals, "normals")
    if arr.shape != points.shape:
        raise ValueError(f"normals must match points' shape {points.shape}, got {arr.shape}")
    if np.any(np.linalg.norm(arr, axis=1) == 0):
        raise ValueError("normals contain zero vectors")
    return arr / np.linalg.norm(arr, axis=1, keepdims=True)


def positive(value, name: str, *, integer: bool = False):
    if isinstance(value, np.ndarray) and value.ndim == 0:  # np.array(0.01) is a number
        value = value.item()
    kind = numbers.Integral if integer else numbers.Real
    wrong_type = isinstance(value, bool) or not isinstance(value, kind)
    if wrong_type or not np.isfinite(value) or value <= 0:
        what = "a positive integer" if integer else "a positive finite number"
        raise ValueError(f"{name} must be {what}, got {value!r}")
    return int(value) if integer else float(value)


def probability(value, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not 0 < value < 1:
        raise ValueError(f"{name} must be strictly between 0 and 1, got {value!r}")
    return float(value)


@functools.lru_cache(maxsize=256)
def _seed_key(seed: int, impl: str):
    """jax.random.key(seed), kept: making one is a JAX dispatch of ~0.3 ms, a twentieth of
    a small fit. Keys are immutable; ``impl`` keys the cache on JAX's PRNG setting."""
    return jax.random.key(seed)


def seed_of(key) -> int | None:
    """The int seed ``key`` is (reduced to 32 bits), or None for a JAX key."""
    if isinstance(key, numbers.Integral) and not isinstance(key, bool):
        return int(key) % (2**32)
    return None


def numpy_seed(key) -> int:
    """A NumPy seed for the host-side random choices made under ``key``: a non-negative int
    seed itself (NumPy integers too), otherwise one drawn from the key's data (a JAX key,
    or a negative int reduced to 32 bits), so every key gives its own choices."""
    seed = seed_of(key)
    if seed is not None:
        return int(key) if key >= 0 else seed
    data = np.asarray(jax.random.key_data(prng_key(key)))
    return int(np.random.SeedSequence(data.ravel().tolist()).generate_state(1)[0])


def prng_key(key):
    """A JAX PRNG key from an int seed or a key (typed, or a raw uint32 pair)."""
    if (seed := seed_of(key)) is not None:
        return _seed_key(seed, jax.config.jax_default_prng_impl)
    if isinstance(key, jax.Array):
        if jnp.issubdtype(key.dtype, jax.dtypes.prng_key) and key.shape == ():
            return key
        if key.dtype == jnp.uint32 and key.shape == (2,):
            return jax.random.wrap_key_data(key)
    raise ValueError(f"key must be an int or a single JAX PRNG key, got {key!r}")
