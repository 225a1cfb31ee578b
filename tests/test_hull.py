"""Depth below the convex hull (``decomposition.hull``): the hollow-part test's work is
bounded by the coarse hull's size, not the exact hull's, and its answer is the exact one."""

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from jaxfit.decomposition import hull, psda
from jaxfit.engine import bucket_size

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def _tube(count, rng, *, outer=1.0, inner=0.8, height=2.0):
    """Points on a closed-bottom tube (outer and inner walls, rim, outer and inner
    bottom): an inner wall at every depth from 0 at the rim down to ``outer - inner``."""
    walls = np.array([outer * height, inner * height, 0.5 * (outer ** 2 - inner ** 2),
                      0.5 * outer ** 2, 0.5 * inner ** 2])
    which = rng.choice(5, count, p=walls / walls.sum())
    angle = rng.uniform(0, 2 * np.pi, count)
    floor = 0.2 * height
    rho = np.select([which == 0, which == 1, which == 2, which == 3],
                    [outer, inner, np.sqrt(rng.uniform(inner ** 2, outer ** 2, count)),
                     outer * np.sqrt(rng.uniform(0, 1, count))],
                    inner * np.sqrt(rng.uniform(0, 1, count)))
    z = np.select([which == 0, which == 1, which == 2, which == 3],
                  [rng.uniform(0, height, count), rng.uniform(floor, height, count),
                   height, 0.0], floor)
    return np.column_stack([rho * np.cos(angle), rho * np.sin(angle), z])


def _exact(cloud):
    return hull.hull_depth(cloud, ConvexHull(cloud).equations)


def _exact_cylinder(count, rng):
    """Every point on a cylinder's surface, so every side point is a hull vertex."""
    which = rng.choice(3, count, p=[0.6, 0.2, 0.2])
    angle = rng.uniform(0, 2 * np.pi, count)
    rho = np.where(which == 0, 0.5, 0.5 * np.sqrt(rng.uniform(0, 1, count)))
    z = np.where(which == 0, rng.uniform(-1, 1, count), np.where(which == 1, -1.0, 1.0))
    return np.column_stack([rho * np.cos(angle), rho * np.sin(angle), z])


def test_hollow_test_work_is_bounded_on_an_exact_convex_sample(monkeypatch, rng):
    # An exact cylinder's hull has ~2 faces per side point; the kernel must only ever see
    # the coarse hull's (fewer than 2 per HULL_VERTICES), so its work grows as N, not N^2.
    cloud = _exact_cylinder(12000, rng)
    faces = len(ConvexHull(cloud).equations)
    assert faces > 10 * hull.HULL_VERTICES  # (the exact hull is large)
    calls = []

    def recording(kernel):
        def call(points, planes):
            calls.append((len(points), len(planes)))
            return kernel(points, planes)
        return call

    monkeypatch.setattr(hull, "_hull_depth", recording(hull._hull_depth))
    monkeypatch.setattr(hull, "_support_max", recording(hull._support_max))
    threshold = psda._threshold(psda.mvbb(cloud), psda.THRESHOLD_FRACTION)
    assert len(psda._outside(cloud, threshold)) == len(cloud)  # all on the hull: outside
    # (padded sizes) three passes of the points over the coarse faces (lower bound,
    # support planes, upper bound) and an exact pass that may cost no more than one
    work = sum(points * planes for points, planes in calls)
    assert work <= 4 * bucket_size(len(cloud)) * bucket_size(2 * hull.HULL_VERTICES)


@pytest.mark.parametrize("limit", [0.05, 0.1, 0.15])
def test_shallow_is_the_exact_classification_on_a_hollow_tube(rng, limit):
    cloud = _tube(6000, rng)
    exact = _exact(cloud) <= limit
    assert 0.1 < exact.mean() < 0.9  # (the inner wall crosses the limit)
    np.testing.assert_array_equal(hull.shallow(cloud, limit), exact)


@pytest.mark.parametrize(("count", "shift"), [(9, 0.0), (300, 1e3), (1500, -50.0)])
def test_shallow_is_the_exact_classification_on_small_clouds(count, shift):
    rng = np.random.default_rng(2)
    cloud = rng.normal(size=(count, 3)) * [3.0, 1.0, 2.0] + shift
    depth = _exact(cloud)
    for limit in np.quantile(depth, [0.0, 0.3, 0.7, 1.0]):
        np.testing.assert_array_equal(hull.shallow(cloud, limit), depth <= limit)


def test_undecided_points_meet_the_exact_faces(monkeypatch, rng):
    # A wide margin leaves many points undecided: the exact pass must run, on them only.
    cloud, limit = _tube(6000, rng), 0.1
    faces = len(ConvexHull(cloud).equations)
    monkeypatch.setattr(hull, "DEPTH_MARGIN", 0.01)
    calls = []
    depth = hull.hull_depth

    def recording(points, equations, centre=None):
        calls.append((len(points), len(equations)))
        return depth(points, equations, centre)

    monkeypatch.setattr(hull, "hull_depth", recording)
    result = hull.shallow(cloud, limit)
    exact = [n for n, f in calls if f == faces]
    assert len(exact) == 1 and 0 < exact[0] < 0.2 * len(cloud)
    np.testing.assert_array_equal(result, depth(cloud, ConvexHull(cloud).equations) <= limit)


def test_too_costly_an_exact_pass_decides_on_the_coarse_hull(monkeypatch, rng):
    # Every point undecided: the exact pass would cost more than the coarse one, so the
    # coarse hull decides, off only for points deeper than the limit by at most the gap.
    cloud, limit = _tube(6000, rng), 0.1
    lower, upper, _ = hull._bounds(cloud, cloud.mean(axis=0), hull.MERGE_DEPTH * limit)
    monkeypatch.setattr(hull, "DEPTH_MARGIN", 1.0)
    result, depth = hull.shallow(cloud, limit), _exact(cloud)
    np.testing.assert_array_equal(result, lower <= limit)
    assert np.all(result[depth <= limit])
    gap = np.max(upper - lower)
    assert not np.any(result[depth > limit + gap + 1e-5])
    assert gap < 0.1 * limit


def test_coarse_bounds_bracket_the_exact_depths(rng):
    # lower <= depth <= upper (up to the float32 error, ~1e-5 of the size): what the
    # classification rests on, and its tolerance where the exact pass would cost too much.
    cloud = _tube(6000, rng)
    lower, upper, coarse = hull._bounds(cloud, cloud.mean(axis=0), 0.002)
    depth = _exact(cloud)
    size = np.linalg.norm(np.ptp(cloud, axis=0))
    assert len(coarse) <= 2 * hull.HULL_VERTICES
    assert np.all(lower <= depth + 1e-5 * size)
    assert np.all(depth <= upper + 1e-5 * size)
    assert np.max(upper - lower) < 0.005 * size  # (a fine coarse hull)


def test_shallow_is_exact_on_the_mug():
    mug = DATA / "graspit" / "mug.iv"
    if not mug.is_file():
        pytest.skip(f"no {mug}")
    from jaxfit.decomposition import load_source

    cloud = load_source(mug, num_points=8000, seed=0)
    limit = psda.HOLLOW_DEPTH * psda._threshold(psda.mvbb(cloud), psda.THRESHOLD_FRACTION)
    exact = _exact(cloud) <= limit
    assert 0.05 < 1 - exact.mean()  # (the inside wall lies deeper)
    np.testing.assert_array_equal(hull.shallow(cloud, limit), exact)
