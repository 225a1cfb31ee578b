"""Where every random choice of a fit comes from: one key per call, cloud i's key
``fold_in(key, i)``, its batch b ``sampling.fold_in(fold_in(key, i), b)`` (in the
kernel, a keyed hash), and its normal pool a stream apart (``normals_key``). Results do
not depend on call order or on the cache.

With JAX's default PRNG (threefry2x32) the cloud keys of an int seed, kept per seed, are
computed in NumPy (``fold_in_data``: the same bits as ``jax.random.fold_in``), since the
small program that made them compiled for ~0.1 s in a fresh process; so is an int
seed's normal-pool key (``seed_normals_data``). Other PRNGs, and the keys made on every
call (a JAX key's), take the jitted path (one dispatch of ~20 us against ~0.12-0.18 ms
in NumPy)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._cache import stored_jit

#: The fold_in tag of a cloud's normal-pool stream.
NORMALS_STREAM = 0x6E6F726D
#: The PRNG whose keys are derived in NumPy (``fold_in_data``).
THREEFRY = "threefry2x32"
_ROTATIONS = ((13, 15, 26, 6), (17, 29, 16, 24))


def _threefry2x32(key, x1, x2):
    """Threefry-2x32 of the counts (x1 (S,), x2 (S,)) under key (2,), all uint32 (20
    rounds, the key injected every 4): JAX's ``threefry2x32_p``, bit for bit."""
    k1, k2 = np.uint32(key[0]), np.uint32(key[1])
    ks = (k1, k2, k1 ^ k2 ^ np.uint32(0x1BD11BDA))
    x1, x2 = x1 + ks[0], x2 + ks[1]
    for i in range(5):
        for r in _ROTATIONS[i % 2]:
            x1 = x1 + x2
            x2 = x1 ^ ((x2 << np.uint32(r)) | (x2 >> np.uint32(32 - r)))
        x1 = x1 + ks[(i + 1) % 3]
        x2 = x2 + ks[(i + 2) % 3] + np.uint32(i + 1)
    return x1, x2


def fold_in_data(data, indices) -> np.ndarray:
    """(S, 2) uint32: ``key_data(fold_in(k, i))`` for each i of indices (S,), where k is
    the threefry key with data (2,) (fold_in hashes the count (0, i))."""
    indices = np.asarray(indices, np.uint32).reshape(-1)
    return np.stack(_threefry2x32(np.asarray(data, np.uint32), np.zeros_like(indices),
                                  indices), axis=1)


def seed_data(seed: int) -> np.ndarray:
    """(2,) uint32: ``key_data(jax.random.key(seed))`` of a threefry key, for a seed in
    [0, 2**32) (the high word is 0)."""
    return np.array([0, seed], np.uint32)


def _wrapped(data):
    """Threefry keys (S,) from their data (S, 2), committed to the default device as the
    jitted path's outputs were (``loop.refine_ahead`` compiles for the kernel's outputs,
    which are committed exactly when its keys are)."""
    return jax.device_put(jax.random.wrap_key_data(data, impl=THREEFRY), jax.local_devices()[0])


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
    """(S,) keys fold_in(key, i) for the cloud indices i of ``indices`` (S,), in one
    dispatch of a stored program: a JAX key's are made on every call, where this costs
    ~20 us and the NumPy path (``fold_in_data``, wrapped and placed) ~180 us."""
    return _keys_of_key(key, np.asarray(indices, np.int32))


@functools.lru_cache(maxsize=256)
def seed_cloud_keys(seed: int, impl: str, slots: int):
    """``cloud_keys`` of ``jax.random.key(seed)``, kept per seed (keys are immutable;
    ``impl`` keys the cache on JAX's PRNG setting)."""
    if impl != THREEFRY:
        return _keys_of_seed(np.uint32(seed), slots)
    return seed_keys_at(seed, tuple(range(slots)))


@functools.lru_cache(maxsize=256)
def seed_keys_at(seed: int, indices: tuple[int, ...]):
    """``keys_at`` of the threefry key ``jax.random.key(seed)``, in NumPy and kept per
    (seed, indices): the clouds of a call that are not its first ones (``fit_batch``'s
    ``separate`` loops) get their keys without compiling ``keys_at``'s program (~0.15 s
    in a fresh process)."""
    return _wrapped(fold_in_data(seed_data(seed), np.asarray(indices)))


def normals_key(key, cloud: int):
    """The key choosing cloud i's normal pool: a stream apart from its batches' keys."""
    return jax.random.fold_in(jax.random.fold_in(key, cloud), NORMALS_STREAM)


def _normals_key_data(key, cloud):
    return jax.random.key_data(normals_key(key, cloud))


_normals_data = stored_jit(_normals_key_data)


def normals_key_data(key, cloud: int) -> np.ndarray:
    """``key_data(normals_key(key, cloud))`` as a NumPy array, in one dispatch of a stored
    program (the two eager fold_ins and key_data cost ~0.3 ms, a tenth of a 1e3-point
    cylinder fit's host time); the same bits. An int seed's: ``seed_normals_data``."""
    return np.asarray(_normals_data(key, np.int32(cloud)))


def seed_normals_data(seed: int, cloud: int) -> np.ndarray:
    """``normals_key_data`` of the key of an int seed (in [0, 2**32)): with JAX's default
    PRNG in NumPy (``fold_in_data``, the same bits, kept per seed and cloud, read-only),
    since the stored program compiled for ~0.2 s of a fresh process's first oriented fit
    of a cloud larger than its pool; with another PRNG through its key."""
    if jax.config.jax_default_prng_impl != THREEFRY:
        return normals_key_data(jax.random.key(seed), cloud)
    return _seed_normals_data(seed, int(cloud))


@functools.lru_cache(maxsize=1024)
def _seed_normals_data(seed: int, cloud: int) -> np.ndarray:
    data = fold_in_data(fold_in_data(seed_data(seed), [cloud])[0], [NORMALS_STREAM])[0]
    data.setflags(write=False)
    return data
