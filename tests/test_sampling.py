"""The kernel's random words (``sampling.words``, ``sampling.fold_in``): uniform, keyed,
reproducible, one stream per key, and the samples drawn from them uniform over the
valid points."""

import jax
import numpy as np

from jaxfit.engine import sampling

N_WORDS = 1 << 16


def _words(key, count=N_WORDS, offset=0):
    return np.asarray(jax.jit(sampling.words, static_argnums=(1, 2))(key, count, offset))


def test_words_are_uniform_and_their_bits_balanced():
    words = _words(sampling.fold_in(jax.random.key(3), 7))
    # 64 bins of the top 6 bits: chi-square with 63 degrees of freedom (p ~ 1e-6 at 130).
    counts = np.bincount(words >> 26, minlength=64)
    expected = N_WORDS / 64
    assert ((counts - expected) ** 2 / expected).sum() < 130
    bits = (words[:, None] >> np.arange(32, dtype=np.uint32)) & 1
    assert np.all(np.abs(bits.mean(0) - 0.5) < 0.01)  # 5 sigma at 65k words is 0.0098
    # successive words uncorrelated (a counter hashed: neighbours must not follow)
    unit = words / 2.0**32
    assert abs(np.corrcoef(unit[:-1], unit[1:])[0, 1]) < 0.02
    # and the low bits too, which a weak mix leaves the most regular
    low = np.bincount(words & 63, minlength=64)
    assert ((low - expected) ** 2 / expected).sum() < 130


def test_same_key_same_words_and_every_fold_a_new_stream():
    key = jax.random.key(11)
    np.testing.assert_array_equal(_words(key, 64), _words(jax.random.key(11), 64))
    streams = [_words(sampling.fold_in(key, b), 64) for b in range(50)]
    streams += [_words(sampling.fold_in(jax.random.key(s), 0), 64) for s in range(100, 150)]
    firsts = {tuple(s[:4]) for s in streams}
    assert len(firsts) == len(streams)
    # two streams share no more words than chance (64^2 / 2^32 ~ 1e-6 expected)
    assert len(set(streams[0]) & set(streams[1])) == 0


def test_an_offset_continues_the_stream():
    # The kernel draws a batch's samples from the first H x k words of its key and the
    # box's support from the words after them: one stream, no word used twice.
    key = sampling.fold_in(jax.random.key(2), 5)
    whole = _words(key, 96)
    np.testing.assert_array_equal(np.concatenate([_words(key, 40), _words(key, 56, 40)]),
                                  whole)
    assert len(set(whole.tolist())) == whole.size


def test_fold_in_keeps_the_key_type_and_is_reproducible():
    key = jax.random.key(5)
    folded = sampling.fold_in(key, 3)
    assert jax.random.key_impl(folded) == jax.random.key_impl(key)
    np.testing.assert_array_equal(jax.random.key_data(folded),
                                  jax.random.key_data(sampling.fold_in(key, 3)))
    assert not np.array_equal(jax.random.key_data(folded),
                              jax.random.key_data(sampling.fold_in(key, 4)))
    rbg = jax.random.key(5, impl="rbg")  # four words: each one folded
    folded = sampling.fold_in(rbg, 3)
    assert jax.random.key_impl(folded) == jax.random.key_impl(rbg)
    assert np.all(jax.random.key_data(folded) != jax.random.key_data(rbg))


def test_samples_uniform_over_the_valid_points_with_the_expected_repeats():
    n_valid, batch, k = 1000, 4096, 4
    idx, distinct = jax.jit(sampling.draw_samples, static_argnums=(2, 3))(
        jax.random.key(0), n_valid, batch, k)
    idx, distinct = np.asarray(idx), np.asarray(distinct)
    assert idx.min() >= 0 and idx.max() < n_valid
    counts = np.bincount(idx.ravel() // 10, minlength=100)  # 100 bins of 10 points
    expected = idx.size / 100
    assert ((counts - expected) ** 2 / expected).sum() < 170  # chi2(99), p ~ 1e-5
    # P(some pair repeats) = 1 - prod(1 - i/n) for i < k: 0.006 at n=1000, k=4
    repeat = 1 - np.prod(1 - np.arange(k) / n_valid)
    sigma = np.sqrt(repeat * (1 - repeat) / batch)
    assert abs((1 - distinct.mean()) - repeat) < 5 * sigma
    np.testing.assert_array_equal(
        distinct, [len(set(row)) == k for row in idx.tolist()])
