"""The whole-object side of decompose: the PSDA's parts against the object's one best
primitive, judged two-sided (``psda._splits_better``), and the normals shared by a
part's fits (``parts.SharedNormals``)."""

import numpy as np
import pytest
import trimesh

from jaxfit import Box, Cylinder, Sphere
from jaxfit.decomposition.boxdecomp import mvbb
from jaxfit.decomposition.measure import Scorer, parts_score
from jaxfit.decomposition.parts import MAX_FIT_POINTS, Candidate, Part, SharedNormals, fits
from jaxfit.decomposition.psda import _splits_better, decompose, load_source
from jaxfit.engine.cloud import NORMAL_POOL


def _surface(model, count, seed):
    return trimesh.sample.sample_surface(model.to_mesh(), count, seed=seed)[0]


def _part(model, points, indices):
    """A Part of ``points[indices]`` won by ``model`` (its own distances; box: the MVBB)."""
    distance = float(np.mean(model.distance(points[indices])))
    return Part(indices, mvbb(points[indices]), model.name, model.name, model, distance,
                {model.name: Candidate(model, distance)})


def _whole(model, points, scorer):
    mean, surface = scorer.score(model, points)
    return Part(np.arange(len(points)), mvbb(points), model.name, model.name, model, mean,
                {model.name: Candidate(model, mean, 0.0, surface)})


def test_a_box_inscribed_in_a_can_does_not_beat_the_can():
    # The YCB soup can's failure in small: one part of the can won by a box inside it
    # (its faces far from every point), the rest by the can's cylinder.
    can = Cylinder(np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.033, 0.1)
    points = _surface(can, 4000, 0)
    scorer = Scorer(points, 0)
    slab = np.abs(points[:, 0]) < 0.012
    inner = Box(np.zeros(3), np.eye(3), np.array([0.024, 0.06, 0.1]))
    parts = [_part(inner, points, np.flatnonzero(slab)), _part(can, points, np.flatnonzero(~slab))]
    whole = _whole(can, points, scorer)
    assert parts_score(scorer, parts) > whole.candidates["cylinder"].two_sided / scorer.diagonal
    assert not _splits_better(whole, parts, scorer)


def test_two_balls_as_two_parts_beat_one_ball_around_both():
    left = Sphere(np.array([-0.06, 0.0, 0.0]), 0.04)
    right = Sphere(np.array([0.06, 0.0, 0.0]), 0.04)
    points = np.concatenate([_surface(left, 2000, 0), _surface(right, 2000, 1)])
    scorer = Scorer(points, 0)
    whole = _whole(Sphere(np.zeros(3), 0.1), points, scorer)
    parts = [_part(left, points, np.arange(2000)), _part(right, points, np.arange(2000, 4000))]
    assert _splits_better(whole, parts, scorer)


@pytest.mark.slow
def test_shared_normals_give_the_same_fits():
    # The whole-object check's fit of a sample (a lone cloud: fitted twice) of the
    # engine's pool size, where it estimates every point's normal itself.
    can = Cylinder(np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.033, 0.1)
    sample = _surface(can, NORMAL_POOL, 0)
    shared = SharedNormals([sample])
    assert shared.of(Sphere) is None  # the sphere's estimator reads no normals
    normals = shared.of(Cylinder)
    assert normals is not None and normals[0].shape == (NORMAL_POOL, 3)
    (alone,) = fits([sample], Cylinder, [0.002], 0)
    (given,) = fits([sample], Cylinder, [0.002], 0, normals)
    assert given.num_inliers == alone.num_inliers
    assert np.allclose(given.model.theta(), alone.model.theta())
    # A sample of up to MAX_FIT_POINTS shares every point's normal; a larger one none.
    assert SharedNormals([_surface(can, MAX_FIT_POINTS, 1)]).of(Cylinder)[0].shape == \
        (MAX_FIT_POINTS, 3)
    assert SharedNormals([_surface(can, MAX_FIT_POINTS + 1, 1)]).of(Cylinder) is None


@pytest.mark.slow
def test_ycb_soup_can_is_one_cylinder(data_dir):
    # The box cuts slice the can; a box inscribed in its middle slab wins there by the
    # one-sided score and takes the recessed lids in reassignment (2 parts before); the
    # parts fit the can no better than its one cylinder, two-sided.
    points = load_source(data_dir / "ycb" / "005_tomato_soup_can_textured.gltf",
                         num_points=20000, seed=0)
    result = decompose(points, gain=0.96, key=0)
    assert [p.kind for p in result.parts] == ["cylinder"]
    assert result.parts[0].indices.size == len(points)
    assert 0.031 < result.parts[0].model.radius < 0.035
