"""Error measures of THESIS.md section 4: how far a fitted primitive is from the truth.

``errors(true_model, fitted_model, points=..., fitted_inliers=..., true_inliers=...)``
returns a flat ``dict[str, float]`` (one row of a results table). Keys per primitive:

========  ===================================================================================
sphere    radius_error |R_e - R_o|, radius_rel (/ R_o), center_error |C_e - C_o|,
          center_rel (/ R_o)
cylinder  radius_error, radius_rel, height_error, height_rel (/ H_o), axis_angle_deg (signs
          ignored), axis_offset (distance of the true centre C_o to the fitted axis line),
          center_error
cone      height_error, height_rel, aperture_error_deg |half_angle_e - half_angle_o| in
          degrees, axis_angle_deg (signs ignored), apex_error |apex_e - apex_o|
box       side_error_0..2 (|side_e - side_o| for the true sides extents[0..2], each fitted
          side matched to a true one, see ``match_box_axes``), side_error_max,
          side_rel_max (largest error relative to its true side), center_error,
          axis_angle_deg (largest angle between matched axes)
plane     normal_angle_deg (signs ignored), offset_error (|offset_e - offset_o| once the
          fitted normal's sign agrees with the true one)
========  ===================================================================================

With ``points`` and ``fitted_inliers`` also: ``inlier_count`` and ``mee``, the mean distance
of the fitted inliers to the true closed surface (``true_model.distance``); for the sphere
this is the thesis's MEE, mean | |C_o - p| - R_o |. With ``fitted_inliers`` and
``true_inliers``: ``precision`` and ``recall`` of the fitted inlier mask. Means and ratios
over an empty set are NaN.
"""

from __future__ import annotations

import itertools

import numpy as np

from ..shapes import Box, Cone, Cylinder, Model, Plane, Sphere

#: The six assignments of fitted box axes to true ones.
_PERMUTATIONS = tuple(itertools.permutations(range(3)))


def errors(true_model: Model, fitted_model: Model, *, points=None, fitted_inliers=None,
           true_inliers=None) -> dict[str, float]:
    """Error measures of ``fitted_model`` against ``true_model`` (see the module docstring).

    Parameters
    ----------
    true_model, fitted_model : unbatched models of the same primitive.
    points : optional (N, 3) cloud the model was fitted to (for ``mee``).
    fitted_inliers : optional (N,) bool, the fit's inlier mask (``FitResult.inliers``).
    true_inliers : optional (N,) bool ground-truth mask (``Scenario.inliers``).

    Returns
    -------
    dict of float, the keys depending on the primitive and on the optional arguments.
    """
    if type(true_model) is not type(fitted_model):
        raise ValueError(
            f"cannot compare a {type(fitted_model).__name__} with a true "
            f"{type(true_model).__name__}: fit the true model's primitive"
        )
    out = _MEASURES[type(true_model)](true_model, fitted_model)
    fitted = _mask(fitted_inliers, "fitted_inliers")
    truth = _mask(true_inliers, "true_inliers")
    if points is not None and fitted is None:
        raise ValueError("points are only used for the MEE, which also needs fitted_inliers")
    if points is not None:
        out.update(inlier_measures(true_model, points, fitted))
    if fitted is not None and truth is not None:
        out.update(precision_recall(fitted, truth))
    return out


def axis_angle_deg(a, b) -> float:
    """Angle in degrees, in [0, 90], between the lines along vectors a (3,) and b (3,).

    atan2 of |a x b| and |a . b| rather than arccos, which loses digits near 0 degrees.
    """
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), abs(a @ b))))


def match_box_axes(true_rotation, fitted_rotation) -> tuple[int, int, int]:
    """For each true axis i (column i of ``true_rotation`` (3, 3)), the fitted column that
    matches it: the permutation maximising the sum of |cos| between matched axes."""
    cos = np.abs(np.asarray(true_rotation, float).T @ np.asarray(fitted_rotation, float))
    return max(_PERMUTATIONS, key=lambda perm: cos[[0, 1, 2], list(perm)].sum())


def precision_recall(fitted_inliers, true_inliers) -> dict[str, float]:
    """Precision |F & T| / |F| and recall |F & T| / |T| of the mask F (N,) against T (N,)."""
    fitted = _mask(fitted_inliers, "fitted_inliers")
    truth = _mask(true_inliers, "true_inliers")
    if fitted.shape != truth.shape:
        raise ValueError(f"fitted_inliers {fitted.shape} and true_inliers {truth.shape} differ")
    hits = float(np.sum(fitted & truth))
    return {"precision": _ratio(hits, fitted.sum()), "recall": _ratio(hits, truth.sum())}


def inlier_measures(true_model: Model, points, fitted_inliers) -> dict[str, float]:
    """``inlier_count`` and ``mee``: mean distance of the fitted inliers among ``points``
    (N, 3) to the true closed surface."""
    points = np.asarray(points, dtype=np.float64)
    fitted = _mask(fitted_inliers, "fitted_inliers")
    if points.ndim != 2 or points.shape[1] != 3 or fitted.shape != points.shape[:1]:
        raise ValueError(
            f"points must be (N, 3) and fitted_inliers (N,), got {points.shape} and "
            f"{fitted.shape}"
        )
    count = int(fitted.sum())
    mee = float(np.mean(true_model.distance(points[fitted]))) if count else float("nan")
    return {"inlier_count": float(count), "mee": mee}


# ----- per primitive ------------------------------------------------------------------------


def _sphere(true: Sphere, fit: Sphere) -> dict[str, float]:
    radius = float(true.radius)
    center = _dist(true.center, fit.center)
    radius_error = abs(float(fit.radius) - radius)
    return {"radius_error": radius_error, "radius_rel": radius_error / radius,
            "center_error": center, "center_rel": center / radius}


def _cylinder(true: Cylinder, fit: Cylinder) -> dict[str, float]:
    radius_error = abs(float(fit.radius) - float(true.radius))
    height_error = abs(float(fit.height) - float(true.height))
    # How far the fitted axis line passes from the true centre (a point of the true axis).
    axis = _unit(fit.axis)
    v = np.asarray(true.center, float) - np.asarray(fit.center, float)
    return {
        "radius_error": radius_error, "radius_rel": radius_error / float(true.radius),
        "height_error": height_error, "height_rel": height_error / float(true.height),
        "axis_angle_deg": axis_angle_deg(true.axis, fit.axis),
        "axis_offset": float(np.linalg.norm(v - (v @ axis) * axis)),
        "center_error": _dist(true.center, fit.center),
    }


def _cone(true: Cone, fit: Cone) -> dict[str, float]:
    height_error = abs(float(fit.height) - float(true.height))
    aperture = abs(float(fit.half_angle) - float(true.half_angle))
    return {
        "height_error": height_error, "height_rel": height_error / float(true.height),
        "aperture_error_deg": float(np.degrees(aperture)),
        "axis_angle_deg": axis_angle_deg(true.axis, fit.axis),
        "apex_error": _dist(true.apex, fit.apex),
    }


def _box(true: Box, fit: Box) -> dict[str, float]:
    perm = list(match_box_axes(true.rotation, fit.rotation))
    true_sides = np.asarray(true.extents, float)
    side = np.abs(np.asarray(fit.extents, float)[perm] - true_sides)
    t_rot, f_rot = np.asarray(true.rotation, float), np.asarray(fit.rotation, float)
    angles = [axis_angle_deg(t_rot[:, i], f_rot[:, perm[i]]) for i in range(3)]
    out = {f"side_error_{i}": float(side[i]) for i in range(3)}
    out.update({
        "side_error_max": float(side.max()),
        "side_rel_max": float(np.max(side / true_sides)),
        "center_error": _dist(true.center, fit.center),
        "axis_angle_deg": max(angles),
    })
    return out


def _plane(true: Plane, fit: Plane) -> dict[str, float]:
    # n . p + d = 0 and -n . p - d = 0 are one plane: align the signs before comparing d.
    t_n, f_n = _unit(true.normal), np.asarray(fit.normal, float)
    f_len = np.linalg.norm(f_n)
    sign = 1.0 if t_n @ f_n >= 0 else -1.0
    offset = sign * float(fit.offset) / f_len
    t_offset = float(true.offset) / np.linalg.norm(np.asarray(true.normal, float))
    return {"normal_angle_deg": axis_angle_deg(t_n, f_n),
            "offset_error": abs(offset - t_offset)}


_MEASURES = {Sphere: _sphere, Cylinder: _cylinder, Cone: _cone, Box: _box, Plane: _plane}


# ----- helpers ------------------------------------------------------------------------------


def _dist(a, b) -> float:
    return float(np.linalg.norm(np.asarray(a, float) - np.asarray(b, float)))


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _ratio(num: float, den) -> float:
    return num / float(den) if den else float("nan")


def _mask(mask, name: str):
    """The (N,) bool array, or None; refuses index arrays, which would be misread."""
    if mask is None:
        return None
    arr = np.asarray(mask)
    if arr.dtype != bool or arr.ndim != 1:
        raise ValueError(f"{name} must be a 1-D bool mask, got dtype {arr.dtype} shape {arr.shape}")
    return arr
