"""The thesis's four noise scenarios (THESIS.md section 4) as reproducible synthetic clouds.

``make(shape, scenario, level, count=2000, seed=0)`` returns a ``Scenario``: the cloud,
its true normals, the ground-truth model and the ground-truth inlier mask.

- **RN** (random noise): ``count - round(level * count)`` points exactly on the true
  surface plus ``round(level * count)`` outliers uniform in the *outlier cube*: the
  model's axis-aligned bounding cube (centred on its bounding box, side = the box's
  longest side) grown by ``CUBE_GROWTH`` = 50 % about its centre (``outlier_cube``). The
  cube comes from the complete model, also in RNIM. ``level`` is the outlier share of all
  points, one of ``RN_LEVELS`` in the thesis, any value in [0, 1) here. Outliers that
  happen to fall near the surface still count as outliers in the mask.
- **SN** (surface noise): all ``count`` points are surface points, each moved along its
  true normal by U(-sc * size, +sc * size), with ``sc = level`` (``SN_LEVELS`` in the
  thesis, any value in [0, 1) here) and ``size = shape_size(model)``. There are no
  outliers: the inlier mask is all True.
- **RNIM / SNIM**: the same on an *incomplete* model: a part of the surface (a ``Cut``,
  ``Model.random_cut``) is deleted before sampling, and the points are drawn on the
  remaining surface only (rejection sampling of ``model.sample``), so the counts stay
  exact. The thesis deletes half of the sphere (a hemisphere), of the cylinder's and the
  cone's side (cut by a plane containing the axis) and a strip of 10 % of the box's area
  along an edge of a largest face; the plane (not in the thesis) loses half its disk
  patch. ``REMOVED_SHARE`` has each primitive's share (``Model.removed_share``).

The true model has a random pose (a random rotation, or the identity with
``axis_aligned=True``; centre uniform in [-1, 1]^3) and a random size of unit order, drawn
by ``jaxfit.synthetic.random_model`` (each primitive's proportions: ``Model.random``).
Axes follow the models' sign rules.

Randomness: three independent streams derived from ``seed`` draw the model, the cut and
the points, so one seed gives the same true shape (and the same deleted part) in every
scenario and at every level; only the points differ. The points are shuffled.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass

import numpy as np

from .. import _checks
from ..shapes import REGISTRY, Cut, Model
from ..shapes import _geometry as g
from .synthetic import random_model

#: The thesis's scenarios: random noise, surface noise, each on a complete or an
#: incomplete (IM) model.
SCENARIOS = ("RN", "RNIM", "SN", "SNIM")
#: Outlier share of all points, the thesis's RN / RNIM levels.
RN_LEVELS = (0.10, 0.20, 0.30, 0.40, 0.50, 0.60)
#: Scattering factor sc, the thesis's SN / SNIM levels (relative to ``shape_size``).
SN_LEVELS = (0.010, 0.050, 0.075, 0.100, 0.125, 0.150)

#: Share of the sampled surface's area an incomplete (IM) scenario deletes, per primitive
#: name (``Model.removed_share``).
REMOVED_SHARE = {name: cls.removed_share for name, cls in REGISTRY.items()}
#: The outlier cube is the model's bounding cube scaled by this factor about its centre.
CUBE_GROWTH = 1.5

# Sub-streams of a seed: one per random choice, so they do not shift one another.
_MODEL_STREAM, _CUT_STREAM, _POINT_STREAM = 0, 1, 2


@dataclass(frozen=True, eq=False)  # eq=False: == on array fields would be ambiguous
class Scenario:
    """One synthetic cloud of a thesis scenario. Arrays are read-only.

    points : (N, 3) float64, shuffled.
    normals : (N, 3) unit; the true outward normal at each surface point (before the SN
        displacement), a random unit vector for each outlier.
    model : the ground-truth jaxfit model.
    inliers : (N,) bool ground truth: True for surface-derived points (all of them in
        SN / SNIM), False for RN outliers.
    shape : the primitive's name (``Model.name``).
    scenario : "RN", "RNIM", "SN" or "SNIM".
    level : outlier share (RN*) or scattering factor sc (SN*).
    seed : the seed it was made from.
    size : ``shape_size(model)``, the length SN's displacement is relative to.
    cut : the deleted part (``Cut``) for RNIM / SNIM, None otherwise.
    """

    points: np.ndarray
    normals: np.ndarray
    model: Model
    inliers: np.ndarray
    shape: str
    scenario: str
    level: float
    seed: int
    size: float
    cut: Cut | None = None


def make(shape, scenario: str, level: float, *, count: int = 2000, seed: int = 0,
         axis_aligned: bool = False) -> Scenario:
    """A cloud of ``count`` points of a random ``shape`` under one of the four scenarios.

    Parameters
    ----------
    shape : a primitive's name in ``jaxfit.shapes.REGISTRY`` (the thesis's four are
        "sphere", "cylinder", "cone" and "box") or its model class.
    scenario : one of ``SCENARIOS`` (case-insensitive).
    level : RN / RNIM: outlier share of all points, in [0, 1). SN / SNIM: scattering
        factor sc, in [0, 1): displacements are U(-sc * size, sc * size).
    count : total number of points N.
    seed : non-negative int; all randomness derives from it (see the module docstring).
    axis_aligned : if True the model's rotation is the identity (axes along x, y, z).

    Returns
    -------
    Scenario with points (N, 3), normals (N, 3), inliers (N,), the true model and the cut.
    """
    cls = _checks.model_class(shape)
    scenario = _scenario_name(scenario)
    level = _level(scenario, level)
    count = _checks.positive(count, "count", integer=True)
    seed = _seed(seed)
    num_outliers = int(round(level * count)) if scenario.startswith("RN") else 0
    if count - num_outliers < cls.sample_size:
        raise ValueError(
            f"count={count} at level {level} leaves {count - num_outliers} surface points; "
            f"a {cls.name} needs at least {cls.sample_size}"
        )

    model = random_model(cls, _stream(seed, _MODEL_STREAM), axis_aligned=axis_aligned)
    cut = random_cut(model, _stream(seed, _CUT_STREAM)) if scenario.endswith("IM") else None
    rng = _stream(seed, _POINT_STREAM)
    size = shape_size(model)
    points, normals = sample_surface(model, count - num_outliers, rng, cut)
    if scenario.startswith("SN"):
        shift = rng.uniform(-level * size, level * size, (len(points), 1))
        points = points + shift * normals
    center, half = outlier_cube(model)
    outliers = rng.uniform(center - half, center + half, (num_outliers, 3))
    points = np.vstack([points, outliers])
    normals = np.vstack([normals, g.random_units(num_outliers, rng)])
    inliers = np.arange(count) < count - num_outliers
    order = rng.permutation(count)
    return Scenario(
        _frozen(points[order]), _frozen(normals[order]), model, _frozen(inliers[order]),
        cls.name, scenario, level, seed, size, cut,
    )


def levels(scenario: str) -> tuple[float, ...]:
    """The thesis's levels for a scenario: ``RN_LEVELS`` or ``SN_LEVELS``."""
    return RN_LEVELS if _scenario_name(scenario).startswith("RN") else SN_LEVELS


def shape_size(model: Model) -> float:
    """The characteristic length SN's scattering factor is relative to (``Model.size``;
    e.g. a sphere's radius, a cone's base radius, a box's mean side)."""
    return model.size()


def outlier_cube(model: Model) -> tuple[np.ndarray, float]:
    """Centre (3,) and half side of the RN outlier cube: the cube around the model's
    axis-aligned bounding box (same centre, side = its longest side), grown by 50 %."""
    lo, hi = bounding_box(model)
    return 0.5 * (lo + hi), 0.5 * CUBE_GROWTH * float(np.max(hi - lo))


def bounding_box(model: Model) -> tuple[np.ndarray, np.ndarray]:
    """Exact axis-aligned bounds (lo (3,), hi (3,)) of the closed, bounded model
    (``Model.bounding_box``)."""
    return model.bounding_box()


def random_cut(model: Model, rng) -> Cut:
    """The part of ``model``'s surface an incomplete scenario deletes
    (``Model.random_cut``)."""
    return model.random_cut(rng)


def sample_surface(model: Model, count: int, rng, cut: Cut | None = None):
    """Exactly ``count`` points (count, 3) uniform on ``model``'s sampled surface outside
    ``cut``, and their outward normals (count, 3), by rejection from ``model.sample``."""
    if cut is None:
        return model.sample(count, rng)
    points, normals, have = [np.empty((0, 3))], [np.empty((0, 3))], 0
    while have < count:
        # Every cut keeps at least half the surface, so two draws per missing point
        # usually finish in one or two rounds.
        p, n = model.sample(2 * (count - have) + 16, rng)
        keep = ~cut.covers(model, p)
        p, n = p[keep], n[keep]
        points.append(p[: count - have])
        normals.append(n[: count - have])
        have += len(points[-1])
    return np.concatenate(points), np.concatenate(normals)


# ----- helpers ------------------------------------------------------------------------------


def _stream(seed: int, purpose: int):
    return np.random.default_rng([seed, purpose])


def _frozen(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


def _scenario_name(scenario) -> str:
    name = scenario.strip().upper() if isinstance(scenario, str) else None
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; expected one of {SCENARIOS}")
    return name


def _level(scenario: str, level) -> float:
    what = "outlier share" if scenario.startswith("RN") else "scattering factor sc"
    if isinstance(level, bool) or not isinstance(level, numbers.Real) or not 0 <= level < 1:
        raise ValueError(f"{scenario} level ({what}) must be in [0, 1), got {level!r}")
    return float(level)


def _seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise ValueError(f"seed must be a non-negative int, got {seed!r}")
    return int(seed)
