"""fit_batch groups its clouds by point bucket (issue 14, bounded memory): tiny clouds are
never padded to a big one's bucket, clouds of similar sizes still share one loop, and a
cloud's result is the one it gets in a call of its own group alone."""

import numpy as np
import pytest

import jaxfit
from jaxfit.engine import bucket_size, loop
from jaxfit.engine.backend import slots
from jaxfit.evaluation.synthetic import demo_cloud


def padded_points(sizes, devices=1):
    """A loop's padded points: slots x the largest bucket."""
    return slots(len(sizes), devices) * max(bucket_size(n) for n in sizes)


def test_tiny_clouds_and_one_big_run_apart():
    assert loop.call_groups([100] * 127 + [10**6]) == [list(range(127)), [127]]
    assert loop.call_groups([100] * 511 + [10**6]) == [list(range(511)), [511]]
    # Groups go by increasing bucket; within one, the clouds keep their call order.
    assert loop.call_groups([10**6, 100, 90]) == [[1, 2], [0]]


def test_similar_clouds_share_one_loop():
    assert loop.call_groups([2000, 700, 1500]) == [[0, 1, 2]]  # the suite's batches
    assert loop.call_groups([5000] * 300) == [list(range(300))]  # one bucket: one loop
    # Within SHARE_POINTS padded points, any mix shares (a few PSDA parts).
    assert loop.call_groups([100, 10000, 200, 4000]) == [[0, 1, 2, 3]]
    # Above it, while the merged loop pads at most SHARE_FACTOR x the separate ones:
    # 64 x 2048 against 2 x (64 x 1024 + 2 x 2048).
    assert loop.call_groups([1000] * 62 + [2000] * 2) == [list(range(64))]
    # ... and not beyond: 64 x 2048 against 2 x (32 x 1024 + 1 x 2048).
    assert loop.call_groups([1000] * 32 + [2000]) == [list(range(32)), [32]]


@pytest.mark.parametrize("devices", [1, 8])
def test_groups_partition_the_clouds_within_the_rule(devices):
    rng = np.random.default_rng(7)
    for _ in range(50):
        sizes = [int(n) for n in np.exp(rng.uniform(np.log(10), np.log(3e6), rng.integers(1, 300)))]
        groups = loop.call_groups(sizes, devices)
        assert sorted(i for g in groups for i in g) == list(range(len(sizes)))
        assert all(g == sorted(g) for g in groups)
        buckets = [[bucket_size(sizes[i]) for i in g] for g in groups]
        assert all(max(a) < min(b) for a, b in zip(buckets, buckets[1:], strict=False))
        for g in groups:
            separate = sum(padded_points([sizes[i] for i in g if bucket_size(sizes[i]) == b],
                                         devices) for b in {bucket_size(sizes[i]) for i in g})
            assert padded_points([sizes[i] for i in g], devices) <= max(
                loop.SHARE_FACTOR * separate, loop.SHARE_POINTS)


def clouds_and_kernel_shapes(monkeypatch):
    """32 small spheres and one of 2000 points (two loops: see the first assert), and the
    list the (slots, bucket) of every kernel call goes to."""
    clouds = [demo_cloud("sphere", count=2000, seed=40)[0]]
    clouds += [demo_cloud("sphere", count=300, seed=i)[0] for i in range(32)]
    assert loop.call_groups([len(c) for c in clouds]) == [list(range(1, 33)), [0]]
    shapes = []
    kernel = loop.batch_best_many
    monkeypatch.setattr(loop, "batch_best_many",
                        lambda *a, **k: shapes.append(a[3].shape[:2]) or kernel(*a, **k))
    return clouds, shapes


def test_small_clouds_are_not_padded_to_a_larger_bucket(monkeypatch):
    clouds, shapes = clouds_and_kernel_shapes(monkeypatch)
    jaxfit.fit_batch(clouds, "sphere", key=3)
    # The 32 small clouds ran at bucket 1024 (then 2 of their 32 rows: subset_rows),
    # the large one alone at 2048; before, all 33 were padded to 64 x 2048.
    assert set(shapes) <= {(32, 1024), (2, 1024), (1, 2048)}
    assert (32, 1024) in shapes and (1, 2048) in shapes


@pytest.mark.parametrize("key", [3, "jax"])
def test_grouped_clouds_get_their_results_of_separate_calls(monkeypatch, key):
    import jax

    key = jax.random.key(11) if key == "jax" else key
    clouds, _ = clouds_and_kernel_shapes(monkeypatch)
    together = jaxfit.fit_batch(clouds, "sphere", key=key)
    # The same clouds in calls of their own, under the same keys fold_in(key, i): the
    # large one is cloud 0 of fit; the small ones are clouds 1.. after a skipped one.
    coincident = np.zeros((10, 3))
    small = jaxfit.fit_batch([coincident] + clouds[1:], "sphere", key=key,
                             skip_failures=True)
    assert small[0] is None
    separate = [jaxfit.fit(clouds[0], "sphere", key=key)] + small[1:]
    for a, b in zip(together, separate, strict=True):
        assert a.model.to_dict() == b.model.to_dict()
        np.testing.assert_array_equal(a.inliers, b.inliers)
        assert (a.cost, a.num_hypotheses, a.status) == (b.cost, b.num_hypotheses, b.status)


def test_separate_loops_give_the_batchs_results_with_one_program(monkeypatch):
    """``separate=True``: every cloud in a loop of one slot, padded as the largest (one
    program whatever the count and sizes), the batch's results up to float rounding (the
    padding differs), a skipped cloud's place kept."""
    clouds, shapes = clouds_and_kernel_shapes(monkeypatch)
    clouds = [np.zeros((10, 3))] + clouds[1:6] + [clouds[0]]
    together = jaxfit.fit_batch(clouds, "sphere", key=3, skip_failures=True)
    assert all(slots_count > 1 for slots_count, _ in shapes)
    shapes.clear()
    apart = jaxfit.fit_batch(clouds, "sphere", key=3, skip_failures=True, separate=True)
    assert set(shapes) == {(1, 2048)} and len(shapes) >= len(clouds) - 1
    assert together[0] is None and apart[0] is None
    for a, b in zip(together[1:], apart[1:], strict=True):
        np.testing.assert_allclose(_flat(a.model), _flat(b.model), rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(a.cost, b.cost, rtol=1e-5)
        np.testing.assert_array_equal(a.inliers, b.inliers)
        assert (a.num_hypotheses, a.status) == (b.num_hypotheses, b.status)


def _flat(model) -> np.ndarray:
    """A model's parameters (``to_dict``'s numbers) as one float vector."""
    return np.concatenate([np.ravel(v) for k, v in model.to_dict().items() if k != "type"])


@pytest.mark.parametrize("shape", ["sphere", "plane"])
def test_regrouping_the_refinement_between_rounds_changes_no_result(shape):
    """``refine.compacted`` (the default refiner's batched path once a call has several
    groups of clouds) against the plain map over groups: the same fits, on 32 clouds (two
    groups of 16) of which some need more LO rounds than others. The same inliers and
    hypotheses; parameters and costs equal to float32 rounding, not bit for bit: XLA
    vectorises the two programs' LM steps differently on some CPUs (an AVX2 machine gave
    19 of the 32 spheres centres 1 ulp apart; AVX-512 ones had matched bit for bit)."""
    import dataclasses

    from jaxfit.engine.refine import LevenbergMarquardt, LocalOptimizer

    @dataclasses.dataclass(frozen=True)
    class Plain(LevenbergMarquardt):
        refine_batch = LocalOptimizer.refine_batch

    clouds = [demo_cloud(shape, count=300, seed=i, outlier_ratio=0.3 + 0.4 * (i % 5 == 0))[0]
              for i in range(32)]
    regrouped = jaxfit.fit_batch(clouds, shape, key=5)
    plain = jaxfit.fit_batch(clouds, shape, key=5, refiner=Plain())
    for a, b in zip(regrouped, plain, strict=True):
        np.testing.assert_allclose(_flat(a.model), _flat(b.model), rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(a.cost, b.cost, rtol=1e-5)
        np.testing.assert_array_equal(a.inliers, b.inliers)
        assert (a.num_inliers, a.num_hypotheses) == (b.num_inliers, b.num_hypotheses)


def test_large_groups_are_cut_into_parts_of_their_bucket():
    # A group of many clouds runs in parts of at most PART_CLOUDS, or one per core of at
    # least PART_LEAST; every part keeps its group's bucket, and a part stays whole on
    # a GPU (cores 0).
    sizes = [300] * 600 + [1500] * 100 + [10**5] * 3
    groups = loop.call_groups(sizes)
    assert [len(g) for g in groups] == [700, 3]
    cut = loop.parts(sizes, groups, cores=2)
    assert [len(p) for p, _, _ in cut] == [234, 233, 233, 3]
    assert [(b, s) for _, b, s in cut] == [(2048, 256)] * 3 + [(131072, None)]
    assert sorted(i for p, _, _ in cut for i in p) == list(range(len(sizes)))
    # Parts of one group share one slot count (one program), the first a cloud longer.
    for count, cores, lengths, rows in ((256, 1, [256], None), (256, 2, [128, 128], 128),
                                        (255, 2, [255], None), (257, 2, [129, 128], 256),
                                        (300, 1, [150, 150], 256)):
        found = loop.parts([300] * count, [list(range(count))], cores=cores)
        assert [len(p) for p, _, _ in found] == lengths
        assert {s for _, _, s in found} == {rows}
    assert loop.parts(sizes, groups, cores=0) == [(groups[0], 2048, None),
                                                  (groups[1], 131072, None)]


def test_clouds_searched_in_parts_get_the_results_of_one_loop(monkeypatch):
    # The 32 small clouds cut into two parts of 16 (searched at once in two threads):
    # every result the same as in one loop of 32: the same inliers, hypotheses and
    # status; parameters and costs to float32 rounding, not bit for bit. The loop of 32
    # refines its two groups of 16 regrouped (``refine.compacted``), each part of 16 as
    # one group, which on some AVX2 CPUs round an LM step apart (session 29's: one
    # sphere's centre 1.3e-9 apart; session 28's had matched bit for bit).
    clouds, shapes = clouds_and_kernel_shapes(monkeypatch)
    monkeypatch.setattr(loop, "cores", lambda: 0)
    together = jaxfit.fit_batch(clouds, "sphere", key=3)
    assert (32, 1024) in shapes and (16, 1024) not in shapes
    monkeypatch.setattr(loop, "cores", lambda: 2)
    monkeypatch.setattr(loop, "PART_LEAST", 16)
    parts = jaxfit.fit_batch(clouds, "sphere", key=3)
    assert (16, 1024) in shapes
    for a, b in zip(together, parts, strict=True):
        np.testing.assert_allclose(_flat(a.model), _flat(b.model), rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(a.cost, b.cost, rtol=1e-5)
        np.testing.assert_array_equal(a.inliers, b.inliers)
        assert (a.num_hypotheses, a.status) == (b.num_hypotheses, b.status)


def test_a_cloud_alone_in_its_loop_is_named_in_the_error():
    # The large cloud runs in a loop of its own; its error (a threshold nothing lies
    # within) still names it, since the call has 33 clouds.
    clouds = [demo_cloud("sphere", count=2000, seed=40)[0]]
    clouds += [demo_cloud("sphere", count=300, seed=i)[0] for i in range(32)]
    with pytest.raises(jaxfit.FitError, match=r"^cloud 0: the best sphere hypothesis has "
                                              r"no inliers"):
        jaxfit.fit_batch(clouds, "sphere", thresholds=[1e-12] + [None] * 32, key=3)


@pytest.mark.parametrize("cut", [False, True])
def test_a_started_batch_finished_with_a_lower_count_is_fit_batch_with_it(monkeypatch, cut):
    # started_batch(start=True) dispatches every loop's first batch at once (detect's
    # shapes of a round); finished with max_hypotheses=300 (min_hypotheses would take
    # every cloud to 1024) it gives fit_batch's results with that count, bit for bit, in
    # one loop per group and in parts run in threads (where nothing starts early).
    from jaxfit.engine.fit import started_batch

    clouds, shapes = clouds_and_kernel_shapes(monkeypatch)
    monkeypatch.setattr(loop, "cores", lambda: 2 if cut else 0)
    monkeypatch.setattr(loop, "PART_LEAST", 16)
    expected = jaxfit.fit_batch(clouds, "sphere", key=3, min_hypotheses=1024,
                                max_hypotheses=300)
    before = len(shapes)
    finish = started_batch(clouds, "sphere", key=3, min_hypotheses=1024, start=True)
    assert len(shapes) - before == (0 if cut else 2)  # the two loops' first batches
    found = finish(300)
    assert {r.num_hypotheses for r in found} == {512}  # two batches of 256, then the cap
    for a, b in zip(expected, found, strict=True):
        assert a.model.to_dict() == b.model.to_dict()
        np.testing.assert_array_equal(a.inliers, b.inliers)
        assert (a.cost, a.num_hypotheses, a.status) == (b.cost, b.num_hypotheses, b.status)
