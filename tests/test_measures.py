"""Error measures on hand-made cases with known answers."""

import numpy as np
import pytest

import jaxfit
from jaxfit.evaluation import measures, scenarios
from jaxfit.evaluation.measures import axis_angle_deg, errors
from jaxfit.evaluation.synthetic import random_rotation
from jaxfit.shapes import Box, Cone, Cylinder, Plane, Sphere


def tilt(angle_deg, axis=(0.0, 0.0, 1.0)):
    """``axis`` (3,) rotated by ``angle_deg`` about x."""
    a = np.radians(angle_deg)
    rot = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    return rot @ np.asarray(axis)


def test_axis_angle_reads_ten_degrees_and_ignores_sign():
    z = np.array([0.0, 0.0, 1.0])
    assert axis_angle_deg(z, tilt(10)) == pytest.approx(10.0, abs=1e-9)
    assert axis_angle_deg(z, -tilt(10)) == pytest.approx(10.0, abs=1e-9)
    assert axis_angle_deg(z, 3 * tilt(170)) == pytest.approx(10.0, abs=1e-9)
    assert axis_angle_deg(z, tilt(90)) == pytest.approx(90.0, abs=1e-9)
    assert axis_angle_deg(z, z) == 0.0
    # Tiny angles keep their digits (arccos would return 0 here).
    assert axis_angle_deg(z, tilt(1e-7)) == pytest.approx(1e-7, rel=1e-6)


def test_sphere_errors_and_mee():
    true = Sphere(np.array([1.0, 2.0, 3.0]), np.float64(2.0))
    fit = Sphere(np.array([1.0, 2.0, 5.0]), np.float64(2.5))
    # Points at known distances from the true surface: 0.2, 0.4, 0 and (not an inlier) 3.
    dirs = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0], [1.0, 0, 0]])
    points = true.center + dirs * np.array([2.2, 1.6, 2.0, 5.0])[:, None]
    mask = np.array([True, True, True, False])
    out = errors(true, fit, points=points, fitted_inliers=mask)
    assert out["center_error"] == pytest.approx(2.0)
    assert out["center_rel"] == pytest.approx(1.0)
    assert out["radius_error"] == pytest.approx(0.5)
    assert out["radius_rel"] == pytest.approx(0.25)
    assert out["mee"] == pytest.approx(0.2)
    assert out["inlier_count"] == 3
    assert "precision" not in out


def test_cylinder_tilt_offset_and_sizes():
    center = np.array([0.5, -1.0, 2.0])
    true = Cylinder(center, np.array([0.0, 0.0, 1.0]), np.float64(0.5), np.float64(2.0))
    # Tilted 10 degrees about the true centre, and shifted along the true axis (which
    # does not move the axis line off the true centre).
    fit = Cylinder(center + tilt(10) * 0.7, tilt(10), np.float64(0.6), np.float64(2.5))
    out = errors(true, fit)
    assert out["axis_angle_deg"] == pytest.approx(10.0, abs=1e-9)
    assert out["axis_offset"] == pytest.approx(0.0, abs=1e-12)
    assert out["radius_error"] == pytest.approx(0.1)
    assert out["radius_rel"] == pytest.approx(0.2)
    assert out["height_error"] == pytest.approx(0.5)
    assert out["height_rel"] == pytest.approx(0.25)
    assert out["center_error"] == pytest.approx(0.7)
    # A parallel axis moved sideways by 0.3 and along itself by 2: the offset is 0.3.
    moved = Cylinder(center + [0.3, 0.0, 2.0], -true.axis, true.radius, true.height)
    out = errors(true, moved)
    assert out["axis_offset"] == pytest.approx(0.3)
    assert out["axis_angle_deg"] == pytest.approx(0.0, abs=1e-12)
    assert out["center_error"] == pytest.approx(np.hypot(0.3, 2.0))


def test_cone_errors():
    apex = np.array([0.0, 1.0, 0.0])
    true = Cone(apex, np.array([0.0, 0.0, 1.0]), np.radians(30.0), np.float64(2.0))
    fit = Cone(apex + [2.0, 0.0, 0.0], -tilt(10), np.radians(32.0), np.float64(1.5))
    out = errors(true, fit)
    assert out["axis_angle_deg"] == pytest.approx(10.0, abs=1e-9)
    assert out["aperture_error_deg"] == pytest.approx(2.0)
    assert out["apex_error"] == pytest.approx(2.0)
    assert out["height_error"] == pytest.approx(0.5)
    assert out["height_rel"] == pytest.approx(0.25)


def test_box_with_permuted_and_flipped_axes_has_no_side_error():
    rot = random_rotation(np.random.default_rng(3))
    true = Box(np.zeros(3), rot, np.array([1.0, 2.0, 3.0]))
    order = [2, 0, 1]
    fitted_rot = rot[:, order] * np.array([-1.0, 1.0, -1.0])  # still a rotation
    fit = Box(np.array([0.0, 2.0, 0.0]), fitted_rot, true.extents[order])
    out = errors(true, fit)
    for i in range(3):
        assert out[f"side_error_{i}"] == pytest.approx(0.0, abs=1e-12)
    assert out["side_rel_max"] == pytest.approx(0.0, abs=1e-12)
    assert out["axis_angle_deg"] == pytest.approx(0.0, abs=1e-6)
    assert out["center_error"] == pytest.approx(2.0)
    assert measures.match_box_axes(true.rotation, fit.rotation) == (1, 2, 0)


def test_box_side_errors_follow_the_true_axes():
    true = Box(np.zeros(3), np.eye(3), np.array([1.0, 2.0, 4.0]))
    # Fitted axes: the true y, z, x, the last tilted 10 degrees about y.
    a = np.radians(10.0)
    x_tilted = np.array([np.cos(a), 0.0, -np.sin(a)])
    fitted_rot = np.stack([[0.0, 1, 0], np.cross(x_tilted, [0.0, 1, 0]), x_tilted], axis=1)
    fit = Box(np.zeros(3), fitted_rot, np.array([2.2, 4.0, 0.9]))
    out = errors(true, fit)
    assert out["side_error_0"] == pytest.approx(0.1)
    assert out["side_error_1"] == pytest.approx(0.2)
    assert out["side_error_2"] == pytest.approx(0.0, abs=1e-12)
    assert out["side_error_max"] == pytest.approx(0.2)
    assert out["side_rel_max"] == pytest.approx(0.1)
    assert out["axis_angle_deg"] == pytest.approx(10.0, abs=1e-9)


def test_plane_errors_ignore_the_normal_sign():
    normal = np.array([0.0, 0.0, 1.0])
    true = Plane(normal, np.float64(-1.0))  # z = 1
    same = Plane(-normal, np.float64(1.0))
    assert errors(true, same) == pytest.approx({"normal_angle_deg": 0.0, "offset_error": 0.0})
    out = errors(true, Plane(-tilt(10), np.float64(1.5)))
    assert out["normal_angle_deg"] == pytest.approx(10.0, abs=1e-9)
    assert out["offset_error"] == pytest.approx(0.5)


def test_precision_recall_on_a_tiny_mask():
    fitted = np.array([True, True, True, True, False, False])
    truth = np.array([True, False, False, True, True, False])
    out = measures.precision_recall(fitted, truth)
    assert out == pytest.approx({"precision": 0.5, "recall": 2 / 3})
    sphere = Sphere(np.zeros(3), np.float64(1.0))
    out = errors(sphere, sphere, fitted_inliers=fitted, true_inliers=truth)
    assert out["precision"] == 0.5 and out["recall"] == pytest.approx(2 / 3)
    empty = measures.precision_recall(np.zeros(6, bool), truth)
    assert np.isnan(empty["precision"]) and empty["recall"] == 0.0


def test_bad_inputs_raise():
    sphere = Sphere(np.zeros(3), np.float64(1.0))
    cylinder = Cylinder(np.zeros(3), np.array([0.0, 0, 1]), np.float64(1.0), np.float64(1.0))
    with pytest.raises(ValueError, match="cannot compare"):
        errors(sphere, cylinder)
    with pytest.raises(ValueError, match="bool mask"):
        errors(sphere, sphere, fitted_inliers=np.array([0, 2]), true_inliers=np.ones(3, bool))
    with pytest.raises(ValueError, match="differ"):
        errors(sphere, sphere, fitted_inliers=np.ones(2, bool), true_inliers=np.ones(3, bool))
    with pytest.raises(ValueError, match="fitted_inliers"):
        errors(sphere, sphere, points=np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        errors(sphere, sphere, points=np.zeros((3, 3)), fitted_inliers=np.ones(2, bool))


def test_measures_of_a_real_fit_on_a_scenario():
    scn = scenarios.make("sphere", "RNIM", 0.5, count=1000, seed=2)
    result = jaxfit.fit(scn.points, "sphere", key=0)
    out = errors(scn.model, result.model, points=scn.points, fitted_inliers=result.inliers,
                 true_inliers=scn.inliers)
    assert out["center_rel"] < 0.02 and out["radius_rel"] < 0.02
    assert out["mee"] < result.threshold
    assert out["precision"] > 0.95 and out["recall"] > 0.95


# ----- the per-shape measures (Model.error_measures, shown_measures) ------------------------


@pytest.mark.parametrize("shape", sorted(jaxfit.shapes.REGISTRY))
def test_a_model_has_no_error_against_itself_and_shows_its_own_keys(shape):
    scn = scenarios.make(shape, "RN", 0.3, count=300, seed=1)
    out = errors(scn.model, scn.model, points=scn.points, fitted_inliers=scn.inliers,
                 true_inliers=scn.inliers)
    measured = {k: v for k, v in out.items() if k not in ("inlier_count", "precision", "recall")}
    assert max(measured.values()) < 1e-6, measured  # axis angles of equal axes: ~1e-7 deg
    assert out["precision"] == out["recall"] == 1.0
    assert set(type(scn.model).shown_measures) <= set(out)
    assert out == {**scn.model.error_measures(scn.model), **measures.inlier_measures(
        scn.model, scn.points, scn.inliers), **measures.precision_recall(scn.inliers,
                                                                           scn.inliers)}


@pytest.mark.parametrize("shape", sorted(jaxfit.shapes.REGISTRY))
def test_a_moved_model_has_a_center_or_offset_error(shape):
    model = scenarios.make(shape, "RN", 0.3, count=300, seed=1).model
    moved = model.rescaled(1.0, np.array([0.0, 0.0, 0.1]))
    out = errors(model, moved)
    # A shift of 0.1 shows as a position error of 0.1 (along a plane's normal: |n_z| 0.1).
    position = {k: v for k, v in out.items()
                if k in ("center_error", "apex_error", "offset_error")}
    assert position, out
    expected = 0.1 * abs(model.normal[2]) if shape == "plane" else 0.1
    assert all(v == pytest.approx(expected) for v in position.values())
