"""Validation of user input, done in NumPy before any JAX call so that every mistake
gets a ValueError naming it instead of a failure deep inside a traced function."""

from __future__ import annotations

import functools
import math
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


#: Largest coordinate magnitude accepted in a cloud: distances are squared in float64
#: (the largest float is ~1.8e308), so beyond ~1e154 they overflow; 1e150 leaves room for
#: sums of squares.
MAX_COORDINATE = 1e150
#: Smallest extent of a cloud jaxfit fits: below ~1e-154 squared distances underflow (a
#: sphere 1e-200 across was fitted with no inliers).
MIN_EXTENT = 1e-140


def spanning(lo, hi) -> None:
    """Raise a ValueError if a cloud with bounds lo, hi (3,) spans more than nothing but
    less than ``MIN_EXTENT`` (coincident points are the caller's to report)."""
    extent = float(np.max(np.asarray(hi) - np.asarray(lo)))
    if 0 < extent < MIN_EXTENT:
        raise ValueError(f"the cloud spans only {extent:.3g}: its squared distances "
                         f"underflow float64; rescale the points (to at least "
                         f"{MIN_EXTENT:.0e} across)")


def cloud(points, name: str = "points", limit: float | None = MAX_COORDINATE) -> np.ndarray:
    """An (N, 3) float64 copy of ``points``; raises on wrong shape, non-numeric or
    non-finite values, or (unless ``limit`` is None) coordinates beyond ``limit``."""
    kind = getattr(getattr(points, "dtype", None), "kind", None)
    if kind in ("M", "m", "V"):  # (NumPy casts datetimes and one-field records to float)
        raise ValueError(f"{name} must be numeric, of shape (N, 3): got dtype {points.dtype}")
    try:
        if np.iscomplexobj(points):  # (float64 would drop the imaginary part, with a warning)
            raise TypeError(f"complex values ({np.asarray(points).dtype})")
        arr = np.array(points, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as err:
        raise ValueError(f"{name} must be numeric, of shape (N, 3): {err}") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {arr.shape}")
    if not np.isfinite(arr).all():  # (the row-wise test is 20x slower: only on failure)
        rows = np.flatnonzero(~np.isfinite(arr).all(axis=1))
        raise ValueError(
            f"{name} contain {rows.size} row(s) with NaN or inf values, e.g. row {rows[0]}"
        )
    if limit is not None and arr.size and not -limit <= arr.min() <= arr.max() <= limit:
        row = int(np.argmax(np.abs(arr).max(axis=1)))
        raise ValueError(
            f"{name} have coordinates up to {np.abs(arr[row]).max():.3g} in magnitude (row "
            f"{row}); at most {limit:.0e} are accepted, since squared distances overflow "
            "float64 beyond ~1e154: rescale the cloud")
    return arr


def points_for(points, cls: type[Model]) -> np.ndarray:
    arr = cloud(points)
    enough_points(arr.shape[0], cls)
    return arr


def enough_points(count: int, cls: type[Model]):
    """Raises where ``count`` points are fewer than a minimal sample of cls."""
    if count < cls.sample_size:
        raise ValueError(
            f"too few points: a {cls.name} needs at least {cls.sample_size}, got {count}")


def normals_for(normals, points: np.ndarray):
    if normals is None:
        return None
    arr = cloud(normals, "normals", limit=None)
    if arr.shape != points.shape:
        raise ValueError(f"normals must match points' shape {points.shape}, got {arr.shape}")
    # Each row divided by its largest entry first: the norm of (1e200, 0, 0) overflowed
    # (giving a zero normal) and that of (1e-200, 0, 0) underflowed (rejected as zero).
    largest = np.abs(arr).max(axis=1, keepdims=True)
    if np.any(largest == 0):
        raise ValueError("normals contain zero vectors")
    arr = arr / largest
    return arr / np.linalg.norm(arr, axis=1, keepdims=True)


def positive(value, name: str, *, integer: bool = False):
    """``value`` as a positive int (``integer``) or a positive finite float of at most
    ``MAX_COORDINATE`` (a distance beyond it overflows when squared: a threshold of 1e300
    made a fit raise OverflowError); raises a ValueError naming ``name`` for anything
    else (bools, strings, NaN, 0, ...)."""
    if isinstance(value, np.ndarray | jax.Array) and value.ndim == 0:
        value = value.item()  # np.array(0.01) is a number
    kind = numbers.Integral if integer else numbers.Real
    valid = not isinstance(value, bool) and isinstance(value, kind)
    if valid and not integer:
        try:
            value = float(value)  # (Fractions and NumPy floats too; 10**400 overflows)
        except (OverflowError, TypeError, ValueError):
            valid = False
        valid = valid and math.isfinite(value)
    if not valid or value <= 0:
        what = "a positive integer" if integer else "a positive finite number"
        raise ValueError(f"{name} must be {what}, got {value!r}")
    if not integer and value > MAX_COORDINATE:
        raise ValueError(f"{name} must be at most {MAX_COORDINATE:.0e} (squared, larger "
                         f"values overflow float64), got {value!r}")
    return int(value) if integer else value


def non_negative(value, name: str) -> float:
    """``value`` as a float >= 0 (inf allowed); raises a ValueError naming ``name`` for
    NaN, negatives, bools and non-numbers."""
    if isinstance(value, np.ndarray | jax.Array) and value.ndim == 0:
        value = value.item()
    try:
        number = float(value) if isinstance(value, numbers.Real) else math.nan
    except OverflowError:
        number = math.inf if value > 0 else -math.inf
    if isinstance(value, bool) or not number >= 0:
        raise ValueError(f"{name} must be a non-negative number, got {value!r}")
    return number


def probability(value, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not 0 < value < 1:
        raise ValueError(f"{name} must be strictly between 0 and 1, got {value!r}")
    return float(value)


@functools.lru_cache(maxsize=256)
def _seed_key(seed: int, impl: str):
    """jax.random.key(seed), kept: making one is a JAX dispatch of ~0.3 ms, a twentieth of
    a small fit (and ~0.1 s of compiling in a fresh process: a threefry key is wrapped
    from its data instead). Keys are immutable; ``impl`` keys the cache on JAX's PRNG
    setting."""
    from .engine.keys import THREEFRY, seed_data

    if impl == THREEFRY:
        return jax.random.wrap_key_data(seed_data(seed), impl=THREEFRY)
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
