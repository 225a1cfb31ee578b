"""Error measures of THESIS.md section 4: how far a fitted primitive is from the truth.

``errors(true_model, fitted_model, points=..., fitted_inliers=..., true_inliers=...)``
returns a flat ``dict[str, float]`` (one row of a results table). The keys per primitive
are its ``error_measures``' (``Model.error_measures``, documented there): e.g. the
sphere's radius_error, radius_rel, center_error and center_rel, relative errors being
divided by the true value.

With ``points`` and ``fitted_inliers`` also: ``inlier_count`` and ``mee``, the mean distance
of the fitted inliers to the true closed surface (``true_model.distance``); for the sphere
this is the thesis's MEE, mean | |C_o - p| - R_o |. With ``fitted_inliers`` and
``true_inliers``: ``precision`` and ``recall`` of the fitted inlier mask. Means and ratios
over an empty set are NaN.
"""

from __future__ import annotations

import numpy as np

from ..shapes import Model
from ..shapes._geometry import axis_angle_deg
from ..shapes.box import match_box_axes

__all__ = ["errors", "axis_angle_deg", "match_box_axes", "precision_recall",
           "inlier_measures"]


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
    out = true_model.error_measures(fitted_model)
    fitted = _mask(fitted_inliers, "fitted_inliers")
    truth = _mask(true_inliers, "true_inliers")
    if points is not None and fitted is None:
        raise ValueError("points are only used for the MEE, which also needs fitted_inliers")
    if points is not None:
        out.update(inlier_measures(true_model, points, fitted))
    if fitted is not None and truth is not None:
        out.update(precision_recall(fitted, truth))
    return out


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


# ----- helpers ------------------------------------------------------------------------------


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
