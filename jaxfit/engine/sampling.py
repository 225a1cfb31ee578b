"""Samplers: which points form each hypothesis's minimal sample, and the kernel's random
words.

A sampler is a frozen, hashable object (a static argument of the kernel) whose ``draw``
is traced into the fused kernel. A new sampler (PROSAC, NAPSAC, ...) is one new class
with a ``draw`` of the same contract.

The kernel's random words come from ``words`` and ``fold_in`` here: a counter hashed
with the key's words, where threefry (``jax.random``) is a rolled loop that took a fifth
to a third of each kernel's XLA compile (docs/engine.md, "Session 39"). Batch b of a cloud
draws from ``fold_in(cloud_key, b)``: its samples take the stream's first H x k words,
the box's support the words after them.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp


class Sampler:
    """Interface: ``draw(key, n_valid, batch_size, sample_size)`` -> indices (H, k) int32
    into the first ``n_valid`` rows of the points, and whether each sample is usable (H,)
    bool (a sample with repeated indices is masked, never raised). It reads at most the
    first H x k ``words`` of key's stream (the kernel draws the box's support after
    them)."""

    def draw(self, key, n_valid, batch_size: int, sample_size: int):  # pragma: no cover
        raise NotImplementedError


@dataclasses.dataclass(frozen=True)
class UniformSampler(Sampler):
    """k indices drawn uniformly, with replacement, in O(k) per sample; samples with a
    repeated index are marked unusable (``jax.random.choice`` without replacement would
    permute all N points per hypothesis)."""

    def draw(self, key, n_valid, batch_size: int, sample_size: int):
        return draw_samples(key, n_valid, batch_size, sample_size)


#: The default sampler.
DEFAULT_SAMPLER = UniformSampler()


def draw_samples(key, n_valid, batch_size: int, sample_size: int):
    """Indices (H, k) of H minimal samples among the first n_valid points, drawn in O(k)
    each (with replacement) from the first H x k ``words`` of key, and whether each
    sample's indices are distinct (H,)."""
    idx = uniform_indices(words(key, batch_size * sample_size), n_valid)
    idx = idx.reshape(batch_size, sample_size)
    distinct = jnp.ones(batch_size, bool)
    for i in range(sample_size):
        for j in range(i + 1, sample_size):
            distinct &= idx[:, i] != idx[:, j]
    return idx, distinct


def mix32(x):
    """Wellons' ``lowbias32`` of uint32 x (any shape), elementwise: a bijective 32-bit
    hash with full avalanche (xor-shift-multiply)."""
    x = (x ^ (x >> 16)) * jnp.uint32(0x7FEB352D)
    x = (x ^ (x >> 15)) * jnp.uint32(0x846CA68B)
    return x ^ (x >> 16)


def words(key, count: int, offset: int = 0):
    """(count,) uniform uint32 words of the stream of key (one typed key, shape (): map
    or vmap over many), counters offset .. offset + count - 1: each counter hashed twice
    with the key's first two data words (counter-based, as threefry is, in a few integer
    operations)."""
    k = jax.random.key_data(key).astype(jnp.uint32)
    counters = jnp.arange(offset, offset + count, dtype=jnp.uint32)
    return mix32(mix32(counters ^ k[0]) + k[1])


def fold_in(key, data):
    """The key of ``data`` (an integer scalar) under key (one typed key, shape ()), a key
    of the same implementation: ``jax.random.fold_in``'s contract for one key, with
    ``mix32``. Every word of the key's data is mixed with ``data`` (threefry keys have 2,
    rbg keys 4)."""
    k = jax.random.key_data(key).astype(jnp.uint32)
    d = mix32(jnp.asarray(data).astype(jnp.uint32) + jnp.uint32(0x9E3779B9))
    salts = jnp.arange(k.shape[-1] - 1, dtype=jnp.uint32) * jnp.uint32(0x85EBCA6B)
    mixed = jnp.concatenate([mix32(k[:1] ^ d), mix32(k[1:] + mix32((d ^ k[0]) + salts))])
    return jax.random.wrap_key_data(mixed, impl=jax.random.key_impl(key))


def uniform_indices(bits, n):
    """Indices in [0, n) from uniform 32-bit words ``bits`` (any shape): exactly
    floor(bits * n / 2^32), by 16-bit halves in uint32 arithmetic (no 64-bit integers
    without x64). One word per index, where ``jax.random.randint`` draws two: the bias
    is below n / 2^32, and the generator was a quarter of the kernel at 1e3 points."""
    n = jnp.asarray(n).astype(jnp.uint32)
    hi, lo = bits >> 16, bits & 0xFFFF
    n_hi, n_lo = n >> 16, n & 0xFFFF
    cross_a, cross_b = hi * n_lo, lo * n_hi
    carry = ((cross_a & 0xFFFF) + (cross_b & 0xFFFF) + ((lo * n_lo) >> 16)) >> 16
    return (hi * n_hi + (cross_a >> 16) + (cross_b >> 16) + carry).astype(jnp.int32)
