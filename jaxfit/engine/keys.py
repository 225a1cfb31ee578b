"""Where every random choice of a fit comes from: one key per call, cloud i's key
``fold_in(key, i)``, its batch b ``fold_in(fold_in(key, i), b)``, and its normal pool a
stream apart (``normals_key``). Results do not depend on call order or on the cache."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._cache import stored_jit

#: The fold_in tag of a cloud's normal-pool stream.
NORMALS_STREAM = 0x6E6F726D


def _fold_in_each(key, indices):
    """fold_in(key, i) for each i of indices (S,)."""
    return jax.vmap(jax.random.fold_in, in_axes=(None, 0))(key, indices)


def _seed_keys(seed, slots: int):
    """``_fold_in_each`` of jax.random.key(seed) (a uint32 seed) over range(slots)."""
    return _fold_in_each(jax.random.key(seed), jnp.arange(slots, dtype=jnp.int32))


_keys_of_key = stored_jit(_fold_in_each)
_keys_of_seed = stored_jit(_seed_keys, ("slots",))


def cloud_keys(key, slots: int):
    """(slots,) keys fold_in(key, i) for the clouds i < slots."""
    return keys_at(key, np.arange(slots))


def keys_at(key, indices):
    """(S,) keys fold_in(key, i) for the cloud indices i of ``indices`` (S,)."""
    return _keys_of_key(key, np.asarray(indices, np.int32))


@functools.lru_cache(maxsize=256)
def seed_cloud_keys(seed: int, impl: str, slots: int):
    """``cloud_keys`` of ``jax.random.key(seed)`` in one dispatch, kept per seed (keys
    are immutable; ``impl`` keys the cache on JAX's PRNG setting)."""
    return _keys_of_seed(np.uint32(seed), slots)


def normals_key(key, cloud: int):
    """The key choosing cloud i's normal pool: a stream apart from its batches' keys."""
    return jax.random.fold_in(jax.random.fold_in(key, cloud), NORMALS_STREAM)


def _normals_key_data(key, cloud):
    return jax.random.key_data(normals_key(key, cloud))


_normals_data = stored_jit(_normals_key_data)


def normals_key_data(key, cloud: int) -> np.ndarray:
    """``key_data(normals_key(key, cloud))`` as a NumPy array, in one dispatch of a stored
    program (the two eager fold_ins and key_data cost ~0.3 ms, a tenth of a 1e3-point
    cylinder fit's host time); the same bits."""
    return np.asarray(_normals_data(key, np.int32(cloud)))
