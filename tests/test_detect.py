"""jaxfit.detect on synthetic scenes of a floor with objects, its stopping rule, bad input.

Every fit inside detect sees at most ``fit_points`` = 1024 points (bucket 1024), so each
shape's kernel compiles once for the whole file."""

import jax
import numpy as np
import pytest

import jaxfit
from jaxfit.detect import choose, components
from jaxfit.evaluation.synthetic import scene

SCENES = [  # 3 to 6 primitives: the floor plus objects touching it
    (200, ["sphere", "lying_cylinder"]),
    (204, ["lying_cylinder", "lying_cylinder"]),  # undersides in the floor's threshold band
    (302, ["cone", "cone", "cone"]),
    (400, ["cone", "sphere", "cylinder", "lying_cylinder"]),
    (501, ["cone", "cone", "cylinder", "lying_cylinder", "cylinder"]),
]


def _match(labels, models, result):
    """Per true primitive: (type of the best-overlapping detection, precision, recall)."""
    out = []
    for t in range(len(models)):
        members = np.flatnonzero(labels == t)
        overlaps = [len(np.intersect1d(members, d.indices)) for d in result.shapes]
        best = int(np.argmax(overlaps))
        d = result.shapes[best]
        out.append((d.shape, overlaps[best] / len(d.indices), overlaps[best] / len(members)))
    return out


@pytest.mark.slow
@pytest.mark.parametrize(("seed", "objects"), SCENES)
def test_every_primitive_is_recovered(seed, objects):
    points, models, labels = scene(seed, objects=objects, count=3000)
    result = jaxfit.detect(points, key=seed)
    assert len(result.shapes) == len(models)
    for model, (shape, precision, recall) in zip(models, _match(labels, models, result),
                                                 strict=True):
        assert shape == model.name
        assert precision >= 0.9 and recall >= 0.9, (model.name, precision, recall)
    # Every point is in at most one detection or unassigned.
    assigned = np.concatenate([d.indices for d in result.shapes] + [result.unassigned])
    np.testing.assert_array_equal(np.sort(assigned), np.arange(len(points)))
    assert np.array_equal(result.labels()[result.unassigned], -np.ones(len(result.unassigned)))


def test_min_inliers_stops_the_loop_and_the_key_fixes_the_result():
    points, models, labels = scene(200, objects=["sphere", "lying_cylinder"], count=3000)
    floor = int(np.sum(labels == 0))
    only_floor = jaxfit.detect(points, min_inliers=floor - 200, key=1)
    assert [d.shape for d in only_floor.shapes] == ["plane"]
    assert len(only_floor.unassigned) >= len(points) - floor - 100
    assert jaxfit.detect(points, min_inliers=len(points), key=1).shapes == []
    again = jaxfit.detect(points, min_inliers=floor - 200, key=1)
    np.testing.assert_array_equal(again.shapes[0].indices, only_floor.shapes[0].indices)
    # An int seed and the JAX key made from it seed the same choices.
    as_key = jaxfit.detect(points, min_inliers=floor - 200, key=jax.random.key(1))
    np.testing.assert_array_equal(as_key.shapes[0].indices, only_floor.shapes[0].indices)
    assert as_key.shapes[0].model == only_floor.shapes[0].model


class _Stop(Exception):
    pass


def test_candidates_skip_lo_unless_the_caller_asks(monkeypatch):
    """The candidates' fit_batch calls (``started_shared``) get CANDIDATE_OPTIONS (no
    LO-RANSAC) under the caller's settings; a FitOptions given whole is passed as it is."""
    import sys

    from jaxfit.engine import FitOptions

    module = sys.modules["jaxfit.detect"]
    seen = []

    def fake(clouds, shape, **kwargs):
        seen.append(kwargs)
        raise _Stop

    monkeypatch.setattr(module, "started_shared", fake)
    points, _, _ = scene(0, objects=["sphere"], count=300)
    for kwargs in ({}, {"refine": True}, {"options": FitOptions(refine=True)}):
        with pytest.raises(_Stop):
            jaxfit.detect(points, **kwargs)
    assert seen[0]["refine"] is False and seen[1]["refine"] is True
    assert "refine" not in seen[2] and seen[2]["options"].refine is True


def test_simpler_candidates_search_only_as_long_as_they_could_matter():
    """A simpler shape's candidates are capped at the hypotheses that find a model with
    RELEVANT times the largest share a more complex shape's candidate explains in any
    group (the most hypotheses any group of the call needs); uncapped where a group has
    no such candidate, or the caller sets max_hypotheses or options."""
    import sys
    import types

    from jaxfit.engine.stopping import required_hypotheses
    from jaxfit.shapes import Plane

    module = sys.modules["jaxfit.detect"]
    ctx = types.SimpleNamespace(fit_options={"refine": False})
    samples = [np.arange(1000), np.arange(500)]
    later = [[(None, None, 0.0, 900), (None, None, 0.0, 100)],  # cone
             [(None, None, 0.0, 400), (None, None, 0.0, 200)]]  # cylinder
    capped = module._cap(ctx, Plane, later, samples)
    # (group 1's best share, 200 of 500, needs more hypotheses than group 0's 900 of 1000)
    expected = required_hypotheses(module.RELEVANT * 0.4, Plane.sample_size, 0.99)
    assert capped == expected and expected > 256
    assert module._cap(ctx, Plane, [], samples) is None
    later[1][1] = later[0][1] = None  # (group 1 has no candidate to compare with)
    assert module._cap(ctx, Plane, later, samples) is None
    for given in ({"max_hypotheses": 10}, {"options": None}):
        ctx.fit_options = given
        assert module._cap(ctx, Plane, later[:1], samples[:1]) is None


def test_every_candidate_fit_runs_one_cloud_per_kernel_call(monkeypatch):
    """Each group is fitted in a loop of its own (``fit_batch(separate=True)``), so a
    shape's kernel is one program of one cloud whatever the number of groups in a round:
    batched, the rounds' 1, 2, 3 or 4 groups had compiled each shape's kernel once per
    slot count (12 programs on PC33, a cold call 7.1 s against 2.3 s)."""
    import sys

    loop = sys.modules["jaxfit.engine.loop"]
    module = sys.modules["jaxfit.detect"]
    slot_counts, group_counts = [], []
    kernel, rounds = loop.batch_best_many, module._round

    def counting_kernel(cls, batch_size, estimator, points, *args, **kwargs):
        slot_counts.append(points.shape[0])
        return kernel(cls, batch_size, estimator, points, *args, **kwargs)

    def counting_round(ctx, groups, rnd):
        group_counts.append(len(groups))
        return rounds(ctx, groups, rnd)

    monkeypatch.setattr(loop, "batch_best_many", counting_kernel)
    monkeypatch.setattr(module, "_round", counting_round)
    points, models, _ = scene(400, objects=["cone", "sphere", "cylinder", "lying_cylinder"],
                              count=3000)
    result = jaxfit.detect(points, key=400)
    assert len(result.shapes) == len(models)
    assert max(group_counts) >= 3  # (the objects, once the floor is taken)
    assert slot_counts and set(slot_counts) == {1}


def test_connected_components_and_choice():
    line = np.c_[np.arange(10.0), np.zeros(10), np.zeros(10)]
    points = np.vstack([line, line[:4] + [100.0, 0.0, 0.0]])
    np.testing.assert_array_equal(components(points, 1.5), [0] * 10 + [1] * 4)
    # The simpler shape wins within the tolerance; outside it the larger one does; equal
    # supports go to the lower cost.
    assert choose(np.array([100, 104]), np.array([1.0, 0.5]), 0.05) == 0
    assert choose(np.array([100, 110]), np.array([1.0, 0.5]), 0.05) == 1
    assert choose(np.array([100, 100]), np.array([1.0, 0.5]), 0.0) == 1


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"shapes": ()}, "shapes is empty"),
        ({"shapes": ("plane", "torus")}, "unknown shape"),
        ({"shapes": ("plane", "plane")}, "repeated"),
        ({"min_inliers": 2}, "min_inliers must be at least"),
        ({"min_inliers": 0}, "min_inliers must be a positive integer"),
        ({"min_inliers": 10_000}, "too few points"),
        ({"threshold": -1.0}, "threshold must be a positive"),
        ({"max_angle": 120.0}, "max_angle"),
        ({"connect": 0}, "connect must be a positive"),
        ({"tolerance": -0.1}, "tolerance"),
        ({"normals": np.zeros((5, 3))}, "normals must match"),
    ],
)
def test_bad_options_raise(kwargs, message):
    points, _, _ = scene(0, objects=["sphere"], count=300)
    with pytest.raises(ValueError, match=message):
        jaxfit.detect(points, **kwargs)


@pytest.mark.parametrize(
    ("points", "message"),
    [(np.zeros((20, 2)), r"shape \(N, 3\)"), (np.full((20, 3), np.nan), "NaN")],
)
def test_bad_points_raise(points, message):
    with pytest.raises(ValueError, match=message):
        jaxfit.detect(points)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["PC21", "PC33"])
def test_no_detection_is_smaller_than_min_inliers(data_dir, name):
    """On the Fit4CAD scans settling had left detections of 0 and 4 points (min_inliers
    10 and 15); none may be returned."""
    from benchmarks.detect import load_fit4cad

    points = load_fit4cad(name)[0]
    result = jaxfit.detect(points, key=0)
    smallest = int(np.ceil(0.01 * len(points)))  # the default min_inliers (at least)
    assert result.shapes and min(len(d.indices) for d in result.shapes) >= smallest
    taken = np.concatenate([d.indices for d in result.shapes] + [result.unassigned])
    np.testing.assert_array_equal(np.sort(taken), np.arange(len(points)))



def test_copies_of_points_neither_crash_nor_hide_the_shapes():
    """5,000 copies of one point beside a sphere had raised 'all points coincide'; a cloud
    with every point stored twice had a median spacing of 0 and found nothing."""
    from jaxfit.shapes import Sphere

    sphere = Sphere(np.zeros(3), 1.0).sample(3000, np.random.default_rng(0))[0]
    piled = jaxfit.detect(np.vstack([sphere, np.tile([[3.0, 0.0, 0.0]], (5000, 1))]), key=0)
    assert [d.shape for d in piled.shapes] == ["sphere"]
    assert len(piled.shapes[0].indices) == 3000 and len(piled.unassigned) == 5000
    twice = jaxfit.detect(np.repeat(sphere, 2, axis=0), key=0)
    assert [d.shape for d in twice.shapes] == ["sphere"] and len(twice.unassigned) == 0


def test_a_dense_cluster_is_joined_without_listing_its_pairs(monkeypatch):
    """3,000 near-copies of one point of a plane patch: query_pairs listed their ~4.5
    million pairs (20,000 of them needed 9 GB); now the pairs listed stay within the
    budget and the components are the same."""
    import scipy.spatial

    from jaxfit.detect import PAIR_BUDGET

    rng = np.random.default_rng(0)
    grid = np.stack(np.meshgrid(np.arange(40.0), np.arange(40.0)), -1).reshape(-1, 2)
    patch = np.c_[grid, np.zeros(len(grid))]
    far = patch[:200] + [100.0, 0.0, 0.0]
    dense = patch[5] + 1e-6 * rng.standard_normal((3000, 3))
    points = np.vstack([patch, dense, far])
    listed = []

    class Counting(scipy.spatial.cKDTree):
        def query_pairs(self, *args, **kwargs):
            pairs = super().query_pairs(*args, **kwargs)
            listed.append(len(pairs))
            return pairs

    monkeypatch.setattr(scipy.spatial, "cKDTree", Counting)
    labels = components(points, 1.5)
    assert max(listed, default=0) <= PAIR_BUDGET * len(points)
    np.testing.assert_array_equal(labels, [0] * (len(patch) + len(dense)) + [1] * len(far))


def test_the_neighbour_structure_holds_each_distinct_point_once(monkeypatch):
    """The settling step queried every copy of a point against KD-trees holding every
    copy (a leaf of 20,000 copies took it from 1 s to 16 s); detect now builds one tree,
    over the distinct points, and every point, copies included, is assigned."""
    import scipy.spatial

    from jaxfit.shapes import Sphere

    sphere = Sphere(np.zeros(3), 1.0).sample(3000, np.random.default_rng(0))[0]
    points = np.vstack([sphere, np.repeat(sphere[:1], 3000, axis=0)])
    built = []

    class Counting(scipy.spatial.cKDTree):
        def __init__(self, data, *args, **kwargs):
            built.append(len(data))
            super().__init__(data, *args, **kwargs)

    monkeypatch.setattr(scipy.spatial, "cKDTree", Counting)
    found = jaxfit.detect(points, key=0)
    assert built and max(built) <= len(np.unique(points, axis=0))
    assert [d.shape for d in found.shapes] == ["sphere"]
    assert len(found.shapes[0].indices) == len(points)


def test_the_preview_draws_the_patch_a_detection_covers(tmp_path):
    """A detection's picture is the patch of its primitive that its points cover: a cap
    of a large sphere is drawn as that cap (every face near the points, a small share
    of the sphere's area), not as the sphere, which had hidden a free-form scan."""
    from jaxfit.detect import Detection, Scene, _Preview
    from jaxfit.io.preview import surface_patch

    rng = np.random.default_rng(0)
    sphere = jaxfit.Sphere(np.zeros(3), 10.0)
    directions = rng.normal(size=(2000, 3)) + [0, 0, 6]  # (a cap about +z)
    cap = 10.0 * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    cap = cap[cap[:, 2] > 9.0]
    reach = 0.4
    patch = surface_patch(sphere.to_mesh(), cap, reach)
    centres = patch.triangles.mean(axis=1)
    gaps = np.linalg.norm(centres[:, None] - cap[None], axis=2).min(axis=1)
    assert gaps.max() <= reach
    assert 0.0 < patch.area < 0.25 * sphere.to_mesh().area
    assert surface_patch(sphere.to_mesh(), cap + [0, 0, 50], reach) is None  # nothing near
    scene = Scene([Detection(sphere, np.arange(len(cap)), 0.0, 0)], np.empty(0, np.int64),
                  0.1, 0.1, reach, cap)
    (part,) = _Preview(scene).parts
    assert len(part.mesh.faces) == len(patch.faces)
    scene.save(tmp_path)
    assert (tmp_path / "preview.png").stat().st_size > 0
