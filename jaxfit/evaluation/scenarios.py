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
- **RNIM / SNIM**: the same on an *incomplete* model: a part of the surface (``Cut``) is
  deleted before sampling, and the points are drawn on the remaining surface only
  (rejection sampling of ``model.sample``), so the counts stay exact:

  ======== ======================================================================
  sphere   the hemisphere on one side of a random plane through the centre (50 %)
  cylinder the half of the side on one side of a random plane containing the axis
           (50 %; the caps are never sampled)
  cone     the same, a random plane containing the axis (50 % of the side)
  box      a strip along one edge of one of the two largest faces, as long as that
           edge and as wide as needed for 10 % of the box's total surface area (the
           largest faces hold at least 1/6 of it, so the strip always fits)
  plane    (not in the thesis) the half of the disk patch on one side of a random
           line through its centre (50 %)
  ======== ======================================================================

The true model has a random pose (a random rotation, or the identity with
``axis_aligned=True``; centre uniform in [-1, 1]^3) and a random size of unit order, drawn
like ``jaxfit.synthetic.random_model``: with s ~ U(0.7, 1.3), sphere radius s; cylinder
radius s/2 and height 2s; cone height 2s and half-angle U(20, 40) degrees; box sides
s * U(0.6, 1.4) each; plane disk radius s. Axes follow the models' sign rules.

Randomness: three independent streams derived from ``seed`` draw the model, the cut and
the points, so one seed gives the same true shape (and the same deleted part) in every
scenario and at every level; only the points differ. The points are shuffled.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass

import numpy as np

from .. import _checks
from ..shapes import Box, Cone, Cylinder, Model, Plane, Sphere
from ..shapes import _geometry as g
from .synthetic import random_model

SCENARIOS = ("RN", "RNIM", "SN", "SNIM")
#: Outlier share of all points, the thesis's RN / RNIM levels.
RN_LEVELS = (0.10, 0.20, 0.30, 0.40, 0.50, 0.60)
#: Scattering factor sc, the thesis's SN / SNIM levels (relative to ``shape_size``).
SN_LEVELS = (0.010, 0.050, 0.075, 0.100, 0.125, 0.150)

#: Share of the total surface area an incomplete (IM) scenario deletes, per primitive.
REMOVED_SHARE = {"plane": 0.5, "sphere": 0.5, "cylinder": 0.5, "cone": 0.5, "box": 0.1}
#: The outlier cube is the model's bounding cube scaled by this factor about its centre.
CUBE_GROWTH = 1.5

# Sub-streams of a seed: one per random choice, so they do not shift one another.
_MODEL_STREAM, _CUT_STREAM, _POINT_STREAM = 0, 1, 2


@dataclass(frozen=True, eq=False)  # eq=False: == on array fields would be ambiguous
class Cut:
    """The part of the surface an incomplete scenario deletes: the surface points p with
    ``(p - origin) . direction > 0``, on the whole surface, or for the box only on
    ``face``.

    origin : (3,) a point on the cutting plane.
    direction : (3,) unit normal of the cutting plane, pointing into the deleted part.
    face : None, or for the box (axis index i, sign +-1): the face whose outward normal
        is sign * rotation[:, i].
    """

    origin: np.ndarray
    direction: np.ndarray
    face: tuple[int, int] | None = None

    def covers(self, model: Model, points) -> np.ndarray:
        """(N,) bool: which surface points (N, 3) of ``model`` lie in the deleted part.

        For the box a point belongs to the face it is nearest to (the face it lies on, for
        points on the surface).
        """
        points = np.asarray(points, dtype=np.float64)
        beyond = (points - self.origin) @ self.direction > 0
        if self.face is None:
            return beyond
        return beyond & (_nearest_face(model, points) == self.face[0] * 2 + (self.face[1] > 0))


@dataclass(frozen=True, eq=False)  # eq=False: == on array fields would be ambiguous
class Scenario:
    """One synthetic cloud of a thesis scenario. Arrays are read-only.

    points : (N, 3) float64, shuffled.
    normals : (N, 3) unit; the true outward normal at each surface point (before the SN
        displacement), a random unit vector for each outlier.
    model : the ground-truth jaxfit model.
    inliers : (N,) bool ground truth: True for surface-derived points (all of them in
        SN / SNIM), False for RN outliers.
    shape : "plane", "sphere", "cylinder", "cone" or "box".
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
    shape : "sphere", "cylinder", "cone", "box" (the thesis's four), "plane", or a class.
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
    normals = np.vstack([normals, _random_units(num_outliers, rng)])
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
    """The characteristic length SN's scattering factor is relative to: the radius of a
    sphere, of a cylinder, of a cone's base, of a plane's disk patch; a box's mean side."""
    if isinstance(model, Box):
        return float(np.mean(model.extents))
    if isinstance(model, Cone):
        return float(model.base_radius)
    return float(model.radius)


def outlier_cube(model: Model) -> tuple[np.ndarray, float]:
    """Centre (3,) and half side of the RN outlier cube: the cube around the model's
    axis-aligned bounding box (same centre, side = its longest side), grown by 50 %."""
    lo, hi = bounding_box(model)
    return 0.5 * (lo + hi), 0.5 * CUBE_GROWTH * float(np.max(hi - lo))


def bounding_box(model: Model) -> tuple[np.ndarray, np.ndarray]:
    """Exact axis-aligned bounds (lo (3,), hi (3,)) of the closed, bounded model."""
    if isinstance(model, Sphere):
        return model.center - model.radius, model.center + model.radius
    if isinstance(model, Box):
        half = 0.5 * np.abs(model.rotation) @ model.extents
        return model.center - half, model.center + half
    if isinstance(model, Plane):
        return _disk_bounds(model.center, model.normal, model.radius)
    if isinstance(model, Cylinder):
        ends = model.center + np.outer([-0.5, 0.5], model.axis) * model.height
        bounds = [_disk_bounds(end, model.axis, model.radius) for end in ends]
    else:  # a cone: its apex and its base disk
        base = model.apex + model.height * model.axis
        bounds = [_disk_bounds(base, model.axis, model.base_radius), (model.apex, model.apex)]
    return np.min([b[0] for b in bounds], axis=0), np.max([b[1] for b in bounds], axis=0)


def random_cut(model: Model, rng) -> Cut:
    """The part of ``model``'s surface an incomplete scenario deletes (see the module
    docstring for which part, per primitive)."""
    if isinstance(model, Sphere):
        return Cut(model.center, _random_units(1, rng)[0])
    if isinstance(model, Box):
        return _box_strip(model, rng)
    # A plane containing the axis (cylinder, cone) or a line through the patch centre
    # (plane): a random direction orthogonal to the axis / normal. Either side of such a
    # plane holds half the area by symmetry.
    if isinstance(model, Plane):
        axis, origin = model.normal, model.center
    else:
        axis, origin = model.axis, model.center if isinstance(model, Cylinder) else model.apex
    angle = rng.uniform(0.0, 2.0 * np.pi)
    direction = g.frame(axis) @ np.array([np.cos(angle), np.sin(angle), 0.0])
    return Cut(np.asarray(origin, dtype=np.float64), direction)


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


def _box_strip(box: Box, rng) -> Cut:
    """A strip along one edge of one of the two largest faces, with 10 % of the area.

    The face is perpendicular to the shortest side (axis i, random sign). Of its two
    in-face axes, a random one k is the strip's length direction; the strip lies against
    the face's edge at +-e_j / 2 along the other axis j (random sign) and has width
    w = 10 % of the total area / e_k. The largest faces hold at least 1/6 of the area,
    so w < e_j always.
    """
    ext = np.asarray(box.extents, dtype=np.float64)
    rot = np.asarray(box.rotation, dtype=np.float64)
    i = int(np.argmin(ext))
    j, k = rng.permutation([a for a in range(3) if a != i])
    face_sign, edge_sign = rng.choice([-1, 1], size=2)
    total = 2.0 * (ext[0] * ext[1] + ext[0] * ext[2] + ext[1] * ext[2])
    width = REMOVED_SHARE["box"] * total / ext[k]
    direction = edge_sign * rot[:, j]
    origin = box.center + (0.5 * ext[j] - width) * direction
    return Cut(origin, direction, (i, int(face_sign)))


def _nearest_face(box: Box, points) -> np.ndarray:
    """(N,) index 2 * axis + (sign > 0) of the box face nearest to each point (N, 3)."""
    local = (points - np.asarray(box.center)) @ np.asarray(box.rotation)
    axis = np.argmin(np.abs(0.5 * np.asarray(box.extents) - np.abs(local)), axis=1)
    return 2 * axis + (local[np.arange(len(points)), axis] > 0)


def _disk_bounds(center, normal, radius):
    """Axis-aligned bounds of a disk: it reaches radius * sqrt(1 - n_i^2) along axis i."""
    reach = radius * np.sqrt(np.clip(1.0 - np.asarray(normal) ** 2, 0.0, None))
    return np.asarray(center) - reach, np.asarray(center) + reach


def _random_units(count: int, rng) -> np.ndarray:
    """(count, 3) unit vectors uniform on the sphere."""
    v = rng.normal(size=(count, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


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
