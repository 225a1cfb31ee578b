"""detect's neighbour structure (``RadiusGraph``) and the normals it gives
(``normals.pair_normals``): the same pairs, spacing, components and assignment as the
direct computations they replaced. NumPy and scipy only: nothing compiles."""

import sys

import numpy as np
import pytest
from scipy.spatial import cKDTree

from jaxfit.detect import (
    RadiusGraph,
    _spacing,
    components,
    hooked_labels,
    median_spacing,
    pair_bound,
)
from jaxfit.detect import estimate_normals as graph_normals
from jaxfit.normals import distinct_inverse, estimate_normals, pair_normals
from jaxfit.shapes import Cylinder, Sphere


def _cloud(seed=0, outliers=200):
    """A sphere and a cylinder side by side with uniform outliers: (N, 3)."""
    rng = np.random.default_rng(seed)
    sphere = Sphere(np.zeros(3), 1.0).sample(1500, rng)[0]
    cylinder = Cylinder(np.array([3.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), 0.7,
                        2.0).sample(1500, rng)[0]
    return np.vstack([sphere, cylinder, rng.uniform(-1.5, 4.0, (outliers, 3))])


def test_distinct_inverse_is_numpys_unique():
    points = _cloud()
    points = np.vstack([points, points[:300], -0.0 * points[:5]])
    distinct, inverse = distinct_inverse(points)
    expected, expected_inverse = np.unique(points, axis=0, return_inverse=True)
    np.testing.assert_array_equal(distinct, expected)
    np.testing.assert_array_equal(inverse, expected_inverse.reshape(-1))
    np.testing.assert_array_equal(distinct[inverse], points)


def test_the_graph_lists_the_pairs_and_spacing_of_a_direct_query():
    points = _cloud()
    graph = RadiusGraph.of(points, connect=4.0)
    distinct = np.unique(points, axis=0)
    tree = cKDTree(distinct)
    nearest = tree.query(distinct, k=2)[0][:, 1]
    assert graph.spacing == pytest.approx(float(np.median(nearest)), rel=1e-12)
    assert graph.spacing == median_spacing(points) == _spacing(tree, distinct)
    assert graph.radius == pytest.approx(4.0 * graph.spacing)
    expected = tree.query_pairs(graph.radius, output_type="ndarray")
    assert {tuple(p) for p in graph.pairs.tolist()} == {tuple(p) for p in expected.tolist()}
    assert np.all(graph.pairs[:, 0] < graph.pairs[:, 1])
    # The bound used to skip an exact count is an upper bound.
    assert pair_bound(distinct, graph.radius) >= len(expected)


def test_pair_bound_is_the_same_on_a_dense_grid_and_bounds_the_pairs(monkeypatch):
    """pair_bound counts on a dense grid of cells where the cloud fills its box, on its
    sorted cells otherwise: the same sum, and never below the true count."""
    import sys

    detect_module = sys.modules["jaxfit.detect"]
    points = _cloud()
    tree = cKDTree(points)
    for radius in (0.02, 0.1, 0.5):
        cells = np.prod(np.floor(np.ptp(points, axis=0) / radius) + 3) / len(points)
        dense = pair_bound(points, radius)
        monkeypatch.setattr(detect_module, "DENSE_CELLS", -1)  # (the sorted cells)
        assert pair_bound(points, radius) == dense
        monkeypatch.undo()
        assert dense >= len(tree.query_pairs(radius)), radius
        if radius == 0.5:
            assert cells <= detect_module.DENSE_CELLS  # (the dense grid was taken)


def test_a_guess_far_off_still_gives_the_exact_spacing(monkeypatch):
    """The pairs are listed at 1.1x the radius a subsample's spacing gives; when the
    subsample was far off, the listing is redone at the true radius."""
    import sys

    detect_module = sys.modules["jaxfit.detect"]  # (jaxfit.detect is the function)
    points = _cloud(outliers=0)
    exact = median_spacing(points)
    for factor in (0.2, 5.0):
        monkeypatch.setattr(detect_module, "_subsample_spacing",
                            lambda tree, distinct, f=factor: f * exact)
        graph = RadiusGraph.of(points, connect=4.0)
        assert graph.spacing == pytest.approx(exact, rel=1e-12)
        expected = cKDTree(graph.distinct).query_pairs(graph.radius, output_type="ndarray")
        assert len(graph.pairs) == len(expected)


def test_components_of_members_match_their_own_graph():
    points = _cloud()
    graph = RadiusGraph.of(points, connect=4.0)
    rng = np.random.default_rng(1)
    members = np.flatnonzero(rng.random(len(points)) < 0.4)
    labels = graph.components(members)
    alone = components(points[members], graph.radius)
    np.testing.assert_array_equal(labels, alone)
    sizes = np.bincount(labels)
    assert np.all(np.diff(sizes) <= 0)  # numbered by decreasing size
    assert graph.components(np.empty(0, np.int64)).shape == (0,)


def test_hooked_labels_are_scipys_components(monkeypatch):
    """The NumPy hooking numbers components as scipy does (by their lowest node), on
    random sparse graphs, a long path in a shuffled order and a graph without edges; it
    gives up (None) rather than run past its rounds, and components then asks scipy."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(3)
    cases = [(n, rng.integers(0, n, (2, e))) for n, e in ((50, 30), (400, 350), (2000, 2500))]
    order = rng.permutation(3000)
    cases += [(3000, np.stack([order[:-1], order[1:]])), (10, np.zeros((2, 0), int))]
    for count, (first, second) in cases:
        graph = coo_matrix((np.ones(len(first)), (first, second)), shape=(count, count))
        _, expected = connected_components(graph, directed=True, connection="weak")
        np.testing.assert_array_equal(hooked_labels(count, first, second), expected)
    assert hooked_labels(3000, order[:-1], order[1:], rounds=1) is None
    points = _cloud()
    graph = RadiusGraph.of(points, connect=4.0)
    members = np.flatnonzero(rng.random(len(points)) < 0.5)
    hooked = graph.components(members)
    # (the module, not jaxfit's ``detect`` function of the same name)
    monkeypatch.setattr(sys.modules["jaxfit.detect"], "HOOKING_PAIRS", -1)  # scipy's path
    np.testing.assert_array_equal(graph.components(members), hooked)


def test_near_marks_the_owners_points_and_their_neighbours():
    points = _cloud()
    graph = RadiusGraph.of(points, connect=4.0)
    owner = np.full(len(points), -1)
    owner[:1500] = 0  # the sphere
    owner[1500:1600] = 1
    near = graph.near(owner, 2)
    for i in range(2):
        tree = cKDTree(points[owner == i])
        within = np.isfinite(tree.query(points, distance_upper_bound=graph.radius)[0])
        # (query's bound is strict, the pairs' is not: equal only up to ties at radius)
        assert np.count_nonzero(near[i] != within) <= 2
        assert near[i][owner == i].all()


def test_pair_normals_agree_with_knn_normals_on_smooth_surfaces():
    points = _cloud(outliers=20)
    graph = RadiusGraph.of(points, connect=4.0)
    normals = graph_normals(graph, 16)
    reference = estimate_normals(points, 16, orient=None)
    cosine = np.abs(np.sum(normals * reference, axis=1))
    assert np.median(cosine) > np.cos(np.radians(2.0))
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, rtol=1e-9)
    # On the sphere, the normal is the radial direction.
    radial = points[:1500] / np.linalg.norm(points[:1500], axis=1, keepdims=True)
    assert np.median(np.abs(np.sum(normals[:1500] * radial, axis=1))) > np.cos(np.radians(3))


def test_product_scatter_matches_the_pair_differences():
    """With neighbour sums, the normals come from one sparse product (centred sums); they
    agree with the pairs' differences to rounding, and a cloud whose sums would lose
    too many digits (far from its centre at this radius) takes the differences."""
    from jaxfit.normals import _product_scatter

    points = _cloud(outliers=20)
    graph = RadiusGraph.of(points, connect=4.0)
    d = graph.distinct
    by_pairs = pair_normals(d, graph.pairs, 16, graph.tree)
    by_product = pair_normals(d, graph.pairs, 16, graph.tree, graph.neighbour_sums)
    np.testing.assert_allclose(np.abs(np.sum(by_pairs * by_product, axis=1)), 1.0, atol=1e-12)
    count = graph.neighbour_sums(np.ones((len(d), 1)))[:, 0] + 1.0
    assert _product_scatter(d, graph.neighbour_sums, count) is not None
    # 1e5 radii of empty space: the centred squares round away a neighbourhood's scatter.
    far = np.vstack([d, d[:1] + [1e5 * graph.radius, 0.0, 0.0]])
    wide = RadiusGraph.of(far, radius=graph.radius)
    wide_count = wide.neighbour_sums(np.ones((len(wide.distinct), 1)))[:, 0] + 1.0
    assert _product_scatter(wide.distinct, wide.neighbour_sums, wide_count) is None
    np.testing.assert_array_equal(
        pair_normals(wide.distinct, wide.pairs, 16, wide.tree, wide.neighbour_sums),
        pair_normals(wide.distinct, wide.pairs, 16, wide.tree))


def test_upper_holds_each_pair_once_and_sums_over_both_ends():
    graph = RadiusGraph.of(_cloud(), connect=4.0)
    from scipy.sparse import coo_matrix

    m, (first, second) = len(graph.distinct), graph.pairs.T
    expected = coo_matrix((np.ones(len(first)), (first, second)),
                          shape=(m, m)).tocsr()  # (canonical: sorted, duplicates summed)
    assert graph.upper.dtype == np.float64 and graph.upper.nnz == expected.nnz
    assert (graph.upper != expected).nnz == 0
    values = np.random.default_rng(0).normal(size=(m, 2))
    np.testing.assert_allclose(graph.neighbour_sums(values), (expected + expected.T) @ values)


def test_isolated_points_take_their_nearest_neighbours_normal():
    """A point with fewer than PAIR_LEAST points within the radius gets its normal from
    its k nearest neighbours, as estimate_normals would."""
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-1, 1, (500, 2)), np.zeros(500)]
    far = np.array([[0.0, 0.0, 5.0]])
    points = np.vstack([plane, far])
    normals = pair_normals(points, np.empty((0, 2), np.int64), k=16)  # no pairs at all
    reference = estimate_normals(points, 16, orient=None)
    np.testing.assert_allclose(np.abs(np.sum(normals * reference, axis=1)), 1.0, atol=1e-9)
    with pytest.raises(ValueError, match="at least 3 distinct points"):
        pair_normals(points[:2], np.empty((0, 2), np.int64))


def test_two_distinct_points_give_an_empty_scene():
    """Copies of two points (with a threshold given, so they do not count as one point)
    hold no primitive: an empty scene, every point unassigned, and no fit is run."""
    import jaxfit

    points = np.repeat(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), 20, axis=0)
    scene = jaxfit.detect(points, threshold=0.01, key=0)
    assert scene.shapes == [] and len(scene.unassigned) == len(points)
