"""Samplers: which points form each hypothesis's minimal sample.

A sampler is a frozen, hashable object (a static argument of the kernel) whose ``draw``
is traced into the fused kernel. A new sampler (PROSAC, NAPSAC, ...) is one new class
with a ``draw`` of the same contract.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from .keys import THREEFRY


class Sampler:
    """Interface: ``draw(key, n_valid, batch_size, sample_size)`` -> indices (H, k) int32
    into the first ``n_valid`` rows of the points, and whether each sample is usable (H,)
    bool (a sample with repeated indices is masked, never raised)."""

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
    each (with replacement), and whether each sample's indices are distinct (H,)."""
    idx = uniform_indices(words(key, (batch_size, sample_size)), n_valid)
    distinct = jnp.ones(batch_size, bool)
    for i in range(sample_size):
        for j in range(i + 1, sample_size):
            distinct &= idx[:, i] != idx[:, j]
    return idx, distinct


def words(key, shape: tuple):
    """``jax.random.bits(key, shape, jnp.uint32)``, drawn as one flat array and reshaped
    for a threefry key (the same values: it numbers its words by their flat index), where
    a 2-d draw's index arithmetic had doubled the compile of the kernel's draws
    (docs/engine.md, "Session 34"). Other PRNGs draw ``shape`` itself."""
    if len(shape) < 2 or jax.random.key_impl(key) != THREEFRY:
        return jax.random.bits(key, shape, jnp.uint32)
    return jax.random.bits(key, (math.prod(shape),), jnp.uint32).reshape(shape)


def randint_indices(key, shape: tuple, n):
    """``jax.random.randint(key, shape, 0, n, jnp.int32)`` (n >= 1, traced) for a threefry
    key, the ``words`` of both halves of ``split(key)`` drawn by one threefry (``vmap``)
    where randint runs two: the same values for a smaller program. (With x64 enabled,
    randint's default int64 draws other words: these stay the int32 ones.) Other PRNGs
    call randint."""
    if jax.random.key_impl(key) != THREEFRY:
        return jax.random.randint(key, shape, 0, n)
    high, low = jax.vmap(lambda k: words(k, shape))(jax.random.split(key))
    # randint's reduction of the two words modulo n, as jax.random writes it
    span = jnp.maximum(jnp.asarray(n, jnp.int32), 1).astype(jnp.uint32)
    multiplier = jax.lax.rem(jnp.uint32(1 << 16), span)
    multiplier = jax.lax.rem(multiplier * multiplier, span)
    offset = jax.lax.rem(jax.lax.rem(high, span) * multiplier + jax.lax.rem(low, span), span)
    return offset.astype(jnp.int32)


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
