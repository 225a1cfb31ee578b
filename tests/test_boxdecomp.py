"""BoxDecomposition: the MVBB and the recursive split (THESIS.md section 5)."""

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from jaxfit import Box
from jaxfit.decomposition.boxdecomp import BoxTree, decompose_boxes, mvbb

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def contains(box, points, tol=1e-9):
    local = (points - box.center) @ box.rotation
    return bool(np.all(np.abs(local) <= 0.5 * box.extents + tol * (1 + box.extents.max())))


def volume(box):
    return float(np.prod(box.extents))


def l_shape(rng, count=4000):
    """Points on two boxes glued in an L, rotated and moved: a 4 x 1 x 1 bar and a
    1 x 1.032 x 0.6 post on one end. The post's base sits just below the cut at half
    the L's height (the 0.5 cut fraction), and splitting there (volume 4.06 + 0.61)
    beats any other split. Returns points (N, 3), the two boxes, and the rotation."""
    bar = (np.array([0.0, 0.0, 0.0]), np.array([4.0, 1.0, 1.0]))
    post = (np.array([1.5, 0.5 + 0.516, 0.0]), np.array([1.0, 1.032, 0.6]))
    rot, shift = random_rotation(rng), rng.normal(size=3) * 5
    areas = [2 * (e[0] * e[1] + e[0] * e[2] + e[1] * e[2]) for _, e in (bar, post)]
    counts = np.round(count * np.array(areas) / sum(areas)).astype(int)
    boxes, clouds = [], []
    for (center, extents), n in zip((bar, post), counts, strict=True):
        box = Box(center @ rot.T + shift, rot, extents)
        boxes.append(box)
        clouds.append(box.sample(int(n), rng)[0])
    return np.concatenate(clouds), boxes


def check_tree(tree: BoxTree, num_points: int):
    """Structural laws: leaves partition the input; children partition their parent."""
    leaf_indices = np.concatenate([tree.nodes[i].indices for i in tree.leaves])
    np.testing.assert_array_equal(np.sort(leaf_indices), np.arange(num_points))
    for i, node in enumerate(tree.nodes):
        if node.children:
            assert len(node.children) == 2
            kids = [tree.nodes[c] for c in node.children]
            assert all(k.parent == i and k.depth == node.depth + 1 for k in kids)
            both = np.concatenate([k.indices for k in kids])
            np.testing.assert_array_equal(np.sort(both), np.sort(node.indices))
    assert tree.nodes[0].parent is None and tree.nodes[0].depth == 0


# ----- MVBB ------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(4))
def test_mvbb_contains_points_and_beats_axis_aligned_box(seed):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(500, 3)) * [3.0, 1.0, 0.5] @ random_rotation(rng).T
    box = mvbb(points)
    assert contains(box, points)
    assert volume(box) <= np.prod(np.ptp(points, axis=0)) * (1 + 1e-12)
    rot = np.asarray(box.rotation)
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
    assert np.linalg.det(rot) == pytest.approx(1.0)
    # The Box sign rule: the first two axes have their largest component positive.
    for k in range(2):
        assert rot[np.argmax(np.abs(rot[:, k])), k] > 0


@pytest.mark.parametrize("seed", range(3))
def test_mvbb_recovers_a_rotated_box_and_matches_trimesh(seed):
    rng = np.random.default_rng(seed)
    truth = Box(rng.normal(size=3), random_rotation(rng), np.array([3.0, 2.0, 0.7]))
    points, _ = truth.sample(3000, rng)
    box = mvbb(points)
    assert contains(box, points)
    assert volume(box) == pytest.approx(volume(truth), rel=0.02)
    np.testing.assert_allclose(np.sort(box.extents), np.sort(truth.extents), rtol=0.02)
    _, extents = trimesh.bounds.oriented_bounds(points)
    assert volume(box) <= np.prod(extents) * 1.01


def test_mvbb_on_a_curved_cloud_is_no_worse_than_trimesh():
    points, _ = trimesh.sample.sample_surface(trimesh.creation.capsule(2.0, 0.5), 3000, seed=1)
    points = points @ random_rotation(np.random.default_rng(5)).T
    box = mvbb(points)
    _, extents = trimesh.bounds.oriented_bounds(points)
    assert contains(box, points)
    assert volume(box) <= np.prod(extents) * 1.01


@pytest.mark.parametrize(
    "points",
    [
        np.array([[1.0, 2.0, 3.0]]),
        np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]]),
        np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]),
        np.linspace([0.0, 0.0, 0.0], [1.0, 2.0, 3.0], 10),  # collinear
        np.c_[np.random.default_rng(0).uniform(size=(100, 2)), np.zeros(100)]
        @ random_rotation(np.random.default_rng(1)).T,  # coplanar
        np.zeros((5, 3)),  # all the same point
    ],
    ids=["one", "two", "three", "collinear", "coplanar", "coincident"],
)
def test_mvbb_degenerate_input_gives_a_thin_box(points):
    box = mvbb(points)
    assert np.all(np.isfinite(box.center)) and np.all(np.isfinite(box.rotation))
    assert np.all(box.extents > 0)
    assert contains(box, points, tol=1e-6)
    span = np.linalg.norm(np.ptp(points, axis=0))
    assert box.extents.min() <= 1e-6 * max(span, 1.0)


def test_mvbb_coplanar_finds_the_rectangle():
    rng = np.random.default_rng(2)
    rot = random_rotation(rng)
    corners = rng.uniform(-0.5, 0.5, size=(400, 2)) * [4.0, 1.0]
    points = np.c_[corners, np.zeros(len(corners))] @ rot.T
    box = mvbb(points)
    assert np.prod(np.sort(box.extents)[1:]) == pytest.approx(4.0, rel=0.03)


@pytest.mark.parametrize("bad", [np.empty((0, 3)), np.ones((4, 2)), [[0.0, np.nan, 1.0]]])
def test_mvbb_rejects_bad_input(bad):
    with pytest.raises(ValueError):
        mvbb(bad)


# ----- decomposition ----------------------------------------------------------------------
@pytest.mark.parametrize("gain", [0.9, 0.96])
@pytest.mark.parametrize("reference", ["parent", "root"])
def test_l_shape_splits_into_its_two_boxes(gain, reference):
    points, truth = l_shape(np.random.default_rng(0))
    tree = decompose_boxes(points, gain=gain, reference=reference)
    check_tree(tree, len(points))
    assert len(tree.leaves) == 2
    found = sorted(volume(b) for b in tree.leaf_boxes)
    expected = sorted(volume(b) for b in truth)
    np.testing.assert_allclose(found, expected, rtol=0.1)
    # Each leaf is centred on its part.
    for box in tree.leaf_boxes:
        assert min(np.linalg.norm(box.center - t.center) for t in truth) < 0.05


def test_cuts_land_on_the_junctions_between_primitives():
    # The lamp's base is 0.02 thick, as thin as a step of the cut grid (5 % of the
    # 0.41 m height): on the grid alone its leaf kept 0.02 m of the post above it.
    from jaxfit.evaluation.synthetic import composite

    points, models, labels = composite("lamp", count=4000, seed=1)
    tree = decompose_boxes(points, gain=0.96, min_points=79, reference="root")
    base = [tree.nodes[i] for i in tree.leaves if np.any(labels[tree.nodes[i].indices] == 0)]
    assert len(base) == 1
    assert np.sum(labels[base[0].indices] == 0) == np.sum(labels == 0)
    assert np.min(base[0].box.extents) == pytest.approx(0.02, rel=0.1)


def test_single_box_stays_one_leaf():
    rng = np.random.default_rng(3)
    points, _ = Box(np.zeros(3), random_rotation(rng), np.array([3.0, 2.0, 1.0])).sample(
        3000, rng)
    for gain in (0.5, 0.9, 0.96):
        tree = decompose_boxes(points, gain=gain)
        assert tree.leaves == [0]
        assert len(tree.nodes) == 1


def test_low_gain_keeps_one_leaf():
    points, _ = l_shape(np.random.default_rng(0))
    tree = decompose_boxes(points, gain=0.5)
    assert tree.leaves == [0]
    np.testing.assert_array_equal(tree.nodes[0].indices, np.arange(len(points)))


def capsule(count=2000):
    return trimesh.sample.sample_surface(trimesh.creation.capsule(2.0, 0.6), count, seed=2)[0]


@pytest.mark.parametrize("reference", ["parent", "root"])
@pytest.mark.parametrize("cloud", ["L", "capsule"])
def test_leaf_count_is_monotone_in_gain(cloud, reference):
    points = l_shape(np.random.default_rng(0))[0] if cloud == "L" else capsule()
    counts = []
    for gain in (0.8, 0.9, 0.96, 0.99):
        tree = decompose_boxes(points, gain=gain, reference=reference)
        check_tree(tree, len(points))
        counts.append(len(tree.leaves))
    assert counts == sorted(counts)
    assert counts[-1] > 1


def test_min_points_is_honoured():
    points = capsule()
    for min_points in (40, 150):
        tree = decompose_boxes(points, gain=0.99, min_points=min_points)
        assert len(tree.leaves) > 1
        assert all(len(n.indices) >= min_points for n in tree.nodes)
    # No split can leave min_points on both sides.
    assert decompose_boxes(points, gain=0.99, min_points=1001).leaves == [0]


def test_max_leaves_stops_the_splits_breadth_first():
    points = capsule()
    full = decompose_boxes(points, gain=0.99, min_points=40)
    assert len(full.leaves) > 3
    for limit in (1, 2, 3):
        tree = decompose_boxes(points, gain=0.99, min_points=40, max_leaves=limit)
        check_tree(tree, len(points))
        assert len(tree.leaves) == limit
        # the same splits as the full tree, in its breadth-first order
        for mine, theirs in zip(tree.nodes, full.nodes, strict=False):
            assert np.array_equal(mine.indices, theirs.indices)
    with pytest.raises(ValueError, match="max_leaves must be an integer >= 1"):
        decompose_boxes(points, max_leaves=0)


def test_tree_to_dict_is_json_ready():
    points, _ = l_shape(np.random.default_rng(0), count=2000)
    tree = decompose_boxes(points, gain=0.96)
    data = json.loads(json.dumps(tree.to_dict()))
    assert data["leaves"] == tree.leaves
    assert [n["num_points"] for n in data["nodes"]] == [len(n.indices) for n in tree.nodes]
    assert data["nodes"][0]["parent"] is None and len(data["nodes"][0]["children"]) == 2
    box = Box.from_dict(data["nodes"][1]["box"])
    np.testing.assert_allclose(box.extents, tree.nodes[1].box.extents)
    assert len(tree.leaf_boxes) == len(tree.leaves)
    labels = tree.leaf_labels()
    assert labels.min() == 0 and labels.max() == len(tree.leaves) - 1


def test_flat_cloud_does_not_crash():
    rng = np.random.default_rng(4)
    flat = np.c_[rng.uniform(size=(1000, 2)) * [4.0, 1.0], np.zeros(1000)]
    flat[:500, 1] += 2.0  # two strips in one plane
    tree = decompose_boxes(flat, gain=0.9)
    check_tree(tree, len(flat))
    assert all(np.all(b.extents > 0) for b in tree.leaf_boxes)


@pytest.mark.parametrize(
    "kwargs",
    [{"gain": 0.0}, {"min_points": 0}, {"min_points": 2.5}, {"cuts": [0.0, 0.5]}, {"cuts": []},
     {"reference": "grandparent"}],
)
def test_decompose_rejects_bad_settings(kwargs):
    points, _ = l_shape(np.random.default_rng(0), count=500)
    with pytest.raises(ValueError):
        decompose_boxes(points, **kwargs)


# ----- real data --------------------------------------------------------------------------
def graspit(name):
    path = DATA / "graspit" / name
    if not path.is_file():
        pytest.skip(f"shared data not found at {path} (it sits beside the checkout)")
    from jaxfit.io.iv import load_iv

    points, _ = trimesh.sample.sample_surface(load_iv(path), 5000, seed=0)
    return points


def test_graspit_primitive_mug_splits_into_body_and_handle():
    # primitives/mug.iv: body cylinder r50 h100 centred (3, -10, 0), handle on the -x side.
    tree = decompose_boxes(graspit("primitives/mug.iv"), gain=0.96, reference="root")
    assert len(tree.leaves) == 2
    body, handle = sorted(tree.leaf_boxes, key=volume, reverse=True)
    np.testing.assert_allclose(np.sort(body.extents), [100, 100, 100], rtol=0.03)
    np.testing.assert_allclose(body.center, [3, -10, 0], atol=2.0)
    assert handle.center[0] < -52


def test_graspit_primitive_phone_splits_into_three_boxes():
    tree = decompose_boxes(graspit("primitives/phone.iv"), gain=0.96, reference="root")
    assert len(tree.leaves) == 3
