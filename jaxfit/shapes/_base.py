"""The contract every primitive fulfils, and the model base class.

A primitive is one frozen dataclass (the *model*: public, canonical parameters, NumPy
methods for distance, export and serialisation) that also carries the pieces the engine
needs as class-level functions:

- ``sample_size``: points in a minimal sample set (k).
- ``estimate(sample, support) -> (theta, valid)``: closed-form estimator, JAX, called
  under ``vmap``. ``sample`` is (k, 3); ``support`` is an (M, 3) subset of the cloud for
  estimators that read the whole cloud (the box's histogram modes). It never raises and
  never returns NaN: degenerate samples give ``valid = False`` and finite parameters.
- ``theta_residual(theta, p, xp)``: signed distance of points to the *unbounded*
  surface of hypothesis ``theta`` (P, ...). ``p`` is a sequence of three coordinate
  arrays; every argument broadcasts, so the engine passes (H,) parameters against
  (C, 1) coordinates and gets a (C, H) block with hypotheses on the fast axis. ``xp`` is
  ``jax.numpy`` or ``numpy``: one formula serves the kernel, the refinement and NumPy.
- ``estimate_oriented(sample, normals, support) -> (theta, valid)`` (optional): an
  estimator from fewer points with their normals (k', 3) (Schnabel, Wahl & Klein 2007),
  with ``oriented_sample_size`` k'. It must not depend on the normals' signs: estimated
  normals are oriented only where that can be done. ``estimators`` holds both as
  ``Estimator`` records, and ``default_estimator`` names the one ``fit`` uses.
- ``canonicalize(theta, xp=jnp)``: projects a flat parameter vector back onto the valid
  set (unit axes, positive radius) after a refinement step. Differentiable: refinement
  differentiates the residual through it; with ``xp=numpy`` it serves the final float64
  refit (a shape whose ``canonicalize`` takes no ``xp`` is not refitted there). Where
  ``batched_canonical`` (default False) it also takes thetas (..., P), each row as it
  alone would: the final refit then projects its P differenced thetas in one call.
- ``theta_jacobian(theta, p, xp) -> (P, ...)`` (optional, else None): the derivatives
  of ``theta_residual`` by each entry of theta at theta (not through ``canonicalize``);
  the final float64 refit takes its Jacobian from it instead of P forward differences,
  and LO's steps instead of P JVPs (``lm_analytic``).
- ``least_squares(points, weights) -> theta`` (optional, else None): the weighted
  geometric least-squares fit (points (S, 3), weights (S,)) in closed form; refinement
  uses it instead of Levenberg-Marquardt steps. ``host_least_squares(jtj, theta) ->
  theta`` (optional, else None): the same fit in NumPy float64 from the points' J^T J
  (``theta_jacobian``'s products, P x P), for the final refit instead of Gauss-Newton
  steps.
- ``from_theta(theta, points, inliers, threshold) -> Model``: the bounded model, with
  height / extents / faces fixed from the inliers after the loop (NumPy, float64;
  points an (N, 3) ndarray, inliers an (N,) bool mask).
- ``from_theta_many(thetas, points, inliers, thresholds[, scales, shifts])`` (optional:
  the default calls ``from_theta`` and ``rescaled`` per cloud) and ``pointwise_theta``
  (default False): ``fit_batch``'s results for many clouds in array code
  (``engine.fit.results_many``).

``theta`` is the flat hypothesis vector of length ``num_params``; it is an engine detail,
documented per primitive, while the dataclass fields are the public parameters.

The rest of jaxfit reads what it needs to know about a primitive from the class too, so a
new primitive is its own file plus its import in ``jaxfit/shapes/__init__.py``:

- ``sample(count, rng)``, ``area()``: points uniform on the *sampled surface* (documented
  per primitive: a cylinder's or cone's side without caps, a plane's disk patch) and its
  area. ``scene_surfaces()``: what ``synthetic.scene`` samples of it standing on a floor.
- ``size()``: the characteristic length noise and thresholds are relative to;
  ``bounding_box()``: exact axis-aligned bounds of the closed, bounded model.
- ``random(rotation, center, size, rng)``: a random model in a given pose and scale
  (``synthetic.random_model``); ``random_cut(rng)``: the ``Cut`` an incomplete scenario
  deletes, ``removed_share`` of the sampled area (``scenarios``).
- ``error_measures(fitted)``: the thesis's errors of a fit against this true model, and
  ``shown_measures``, the ones the evaluation's tables show (``measures``, ``evaluate``).
- ``axial_bounds``: whether the bounds are an interval along the axis (the PSDA re-bounds
  such primitives on the whole cloud).

Pose and mass, for simulators and grasping (docs/robot.md): ``transform()`` (4, 4), the
canonical frame ``trimesh.creation`` builds the primitive in (+Z the axis of a cylinder,
from a cone's base to its apex, a plane's normal at its patch centre); ``volume()``,
``surface_area()`` (the closed surface, where ``area()`` is the sampled one),
``centroid()`` (3,), ``unit_inertia()`` (3,) principal moments per unit mass in that frame;
from these the base class gives ``mass(density)`` and ``inertia(density)`` (3, 3) about the
centroid in the cloud's axes, and ``mass_properties`` combines several primitives.

The fields hold one primitive: ``center`` is (3,), not (..., 3). ``to_dict``,
``from_dict`` and ``rescaled`` also work on fields with leading batch axes; the geometric
methods (``theta``, ``residual``, ``distance``, ``sample``, ``to_mesh``, ...) do not.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

#: name -> model class, filled by ``register``.
REGISTRY: dict[str, type[Model]] = {}

#: Step of the central differences that give a residual's slope in NumPy.
SLOPE_STEP = 1e-6

#: How each field changes when the cloud is mapped by p -> p * scale + shift (the kinds
#: of ``Model.field_specs``): a point scales and shifts, a length scales, a direction or
#: an angle stays.
POINT, LENGTH, INVARIANT = "point", "length", "invariant"


@dataclasses.dataclass(frozen=True)
class Estimator:
    """One way of turning a minimal sample into a hypothesis.

    name : "thesis" or "oriented".
    sample_size : points per minimal sample (k).
    uses_normals : whether ``estimate`` reads the sample's normals.
    min_hypotheses : floor on the confidence-based hypothesis count T for this estimator.
    estimate : (sample (k, 3), normals (k, 3) or None, support (M, 3)) -> (theta, valid).
    """

    name: str
    sample_size: int
    uses_normals: bool
    min_hypotheses: int
    estimate: Callable


ESTIMATORS = ("thesis", "oriented")


def _estimators(cls) -> dict[str, Estimator]:
    """The thesis's estimator always; the oriented one where the primitive defines it."""
    out = {"thesis": Estimator("thesis", cls.sample_size, False, cls.min_hypotheses,
                               lambda sample, normals, support: cls.estimate(sample, support))}
    if "estimate_oriented" in vars(cls):
        out["oriented"] = Estimator("oriented", cls.oriented_sample_size, True, 0,
                                    cls.estimate_oriented)
    return out


def register(cls):
    """Make ``cls`` a frozen dataclass, a JAX pytree, and a known primitive. (Equality,
    hashing and the repr are ``Model``'s: the dataclass ones compare array fields with
    ``==``, which raises, and print ``np.float64(...)``.)"""
    cls = dataclasses.dataclass(frozen=True, eq=False, repr=False)(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    if sorted(names) != sorted(cls.field_specs):  # (from_dict and rescaled build from it)
        raise TypeError(f"{cls.__name__}.field_specs must name its fields {names}, got "
                        f"{list(cls.field_specs)}")
    cls.estimators = _estimators(cls)
    jax.tree_util.register_dataclass(cls, data_fields=names, meta_fields=[])
    REGISTRY[cls.name] = cls
    return cls


class Model:
    """Base class of the primitives. See the module docstring for the contract."""

    name: ClassVar[str]
    #: RGBA of the primitive in scenes and previews.
    colour: ClassVar[tuple[int, int, int, int]]
    sample_size: ClassVar[int]
    num_params: ClassVar[int]
    #: Floor on the confidence-based hypothesis count T. The rule assumes any all-inlier
    #: sample gives a good model; the thesis's cylinder and cone also need their three
    #: circle points on one cross-section, which it does not model.
    min_hypotheses: ClassVar[int] = 0
    #: Position in theta of the radius a user's ``radius_range`` bounds (None: none;
    #: see ``jaxfit.engine.Bounds``).
    radius_index: ClassVar[int | None] = None
    #: Start in theta of the unit axis (or normal) a user's ``axis_prior`` bounds.
    axis_index: ClassVar[int | None] = None
    #: Whether the estimators read ``support`` (the kernel then draws one support per
    #: group of a batch's hypotheses, ``kernel.SUPPORT_GROUPS``; others get one, unread).
    reads_support: ClassVar[bool] = False
    #: name -> Estimator, filled by ``register``; see ``estimator``.
    estimators: ClassVar[dict[str, Estimator]]
    #: The estimator ``fit`` uses unless told otherwise: the one that measured best.
    default_estimator: ClassVar[str] = "thesis"
    #: LO-RANSAC refines this many of a batch's best hypotheses and keeps the best
    #: result: on noisy cones the single best raw hypothesis often sits in the wrong
    #: basin of the MSAC cost. Each start costs a whole refinement, most of fit_batch's
    #: time on small clouds (measurements: docs/shapes.md).
    lo_starts: ClassVar[int] = 4
    #: Levenberg-Marquardt steps per LO round (None: the refiner's default,
    #: ``engine.refine.LM_STEPS``); a shape whose rounds converge in fewer sets fewer,
    #: since a group of clouds steps until its slowest has (docs/engine.md).
    lm_steps: ClassVar[int | None] = None
    #: Whether LO's Levenberg-Marquardt steps take their Jacobian from ``theta_jacobian``
    #: (where the shape has one) rather than from JVPs of ``theta_residual``: less to
    #: trace, the same fits; off where the JVPs compile faster (the box's refinement,
    #: docs/engine.md "Session 37").
    lm_analytic: ClassVar[bool] = True
    #: Whether ``canonicalize`` takes thetas (..., P) (see the module docstring).
    batched_canonical: ClassVar[bool] = False
    #: field name -> (trailing shape, kind), the kind saying how it maps under scaling.
    field_specs: ClassVar[dict[str, tuple[tuple[int, ...], str]]]

    # ----- engine contract (overridden per primitive) ---------------------------------
    @staticmethod
    def estimate(sample, support):  # pragma: no cover - abstract
        raise NotImplementedError

    @classmethod
    def estimator(cls, name: str | None = None) -> Estimator:
        """The Estimator called ``name`` ("thesis" or "oriented"; None: the default).
        A primitive without an oriented estimator (plane, box) uses its thesis one."""
        if name is None:
            name = cls.default_estimator
        if name not in ESTIMATORS:
            raise ValueError(f"unknown estimator {name!r}; expected one of {ESTIMATORS}")
        return cls.estimators.get(name, cls.estimators["thesis"])

    @staticmethod
    def theta_residual(theta, p, xp):  # pragma: no cover - abstract
        raise NotImplementedError

    @classmethod
    def residual_slope(cls, theta, p, m, xp, step: float = SLOPE_STEP):
        """The residual at coordinates ``p`` and its derivative along directions ``m``
        (both sequences of three arrays, broadcasting as in ``theta_residual``):
        (residual, slope). Every residual is a distance, whose gradient is the unit
        surface normal, so the slope is the cosine between ``m`` and that normal: the
        normal gate's measure. JAX: one JVP; NumPy: a central difference of ``step``."""
        if xp is np:
            along = central_difference(lambda q: cls.theta_residual(theta, q, np), p, m, step)
            return cls.theta_residual(theta, p, np), along / (2 * step)
        return jax.jvp(lambda *c: cls.theta_residual(theta, c, jnp), tuple(p), tuple(m))

    def normal_cosines(self, points, normals, step: float = SLOPE_STEP):
        """(N,) cosine between normals (N, 3) (unit, either sign) and the normal of the
        surface ``residual`` measures (a box's six faces) at points (N, 3): the normal
        gate's measure on this model, by one central difference of ``step``. (On a box
        the kernel's three planes give the far faces' points the wrong normal.)"""
        p, m = components(as_points(points)), components(as_points(normals))
        return central_difference(self.coordinate_residual, p, m, step) / (2 * step)

    def surface_normal(self, points, step: float = SLOPE_STEP):
        """Unit normals (N, 3) of the surface ``residual`` measures (a box's six faces)
        near points (N, 3): its gradient by central differences of ``step``; the
        residual's sign decides the normal's."""
        p = components(as_points(points))
        grad = np.stack([central_difference(self.coordinate_residual, p, e, step)
                         for e in np.eye(3)], axis=1)
        return grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-300)

    @staticmethod
    def canonicalize(theta, xp=jnp):
        return theta

    least_squares = None  # see the module docstring
    host_least_squares = None  # see the module docstring
    theta_jacobian = None  # see the module docstring

    @classmethod
    def from_theta(cls, theta, points, inliers, threshold):  # pragma: no cover - abstract
        raise NotImplementedError

    #: Whether the NumPy ``theta_residual`` reads theta only as scalars ``theta[k]`` in
    #: elementwise arithmetic, and ``distance`` is ``abs(residual)``: then one call with
    #: theta (P, N), each point's column its own cloud's parameters, gives every cloud's
    #: residuals bit for bit, and ``fit_batch`` bounds and scores many clouds in one pass
    #: (``engine.fit.results_many``; a result's host work had been ~40-200 us a cloud).
    pointwise_theta: ClassVar[bool] = False

    @classmethod
    def from_theta_many(cls, thetas, points, inliers, thresholds, scales=None,
                        shifts=None) -> list:
        """``from_theta`` of C clouds at once: thetas (C, P), points a list of C (N_i, 3)
        arrays, inliers (sum N_i,) bool, the clouds' masks concatenated, thresholds (C,);
        with scales (C,) and shifts (C, 3), each model ``rescaled(scale, shift)``. A list
        of C models, each equal to ``from_theta``'s (and ``rescaled``'s). This default
        calls them cloud by cloud; a shape overrides it where array code over all clouds
        is faster."""
        ends = np.cumsum([len(p) for p in points])
        models = [cls.from_theta(theta, p, inliers[end - len(p):end], float(t))
                  for theta, p, end, t in zip(thetas, points, ends, thresholds, strict=True)]
        if scales is None:
            return models
        return [m.rescaled(s, c) for m, s, c in zip(models, scales, shifts, strict=True)]

    # ----- public model API --------------------------------------------------------------
    def residual(self, points):
        """Signed distance (N,) of points (N, 3) to the surface used to classify inliers:
        the unbounded surface for plane, sphere, cylinder and cone; the six faces for a box."""
        return self.coordinate_residual(components(as_points(points)))

    def coordinate_residual(self, p):
        """``residual`` of the points given as three coordinate arrays p (x, y, z), the
        form the finite differences shift (no (N, 3) array stacked per difference)."""
        return self.theta_residual(self.theta(), p, np)

    def theta(self):
        """The flat hypothesis vector (num_params,) of this model (unbatched)."""
        raise NotImplementedError

    def distance(self, points):
        """Unsigned distance (N,) of points (N, 3) to the closed, bounded surface."""
        raise NotImplementedError

    def to_mesh(self):
        """A ``trimesh.Trimesh`` of the bounded primitive. (The primitives import trimesh
        here, not at module level: it costs half a second of every process's start.)"""
        raise NotImplementedError

    def to_open3d(self):
        """An ``open3d.geometry.TriangleMesh`` of ``to_mesh()``'s vertices and triangles,
        with vertex normals and painted in the primitive's ``colour``. Raises ImportError
        (saying how to install it) without Open3D."""
        try:
            import open3d
        except ImportError as err:
            raise ImportError("Model.to_open3d needs Open3D, which is not installed: pip "
                              "install open3d (or jaxfit[test]); to_mesh() gives a trimesh "
                              "mesh without it") from err
        mesh = self.to_mesh()
        out = open3d.geometry.TriangleMesh(
            open3d.utility.Vector3dVector(np.asarray(mesh.vertices, np.float64)),
            open3d.utility.Vector3iVector(np.asarray(mesh.faces, np.int32)))
        out.compute_vertex_normals()
        out.paint_uniform_color(np.asarray(self.colour[:3], np.float64) / 255.0)
        return out

    # ----- comparison and printing -------------------------------------------------------
    def _values(self):
        """(field name, float64 array or None) of every field, in order."""
        return [(f.name, None if (v := getattr(self, f.name)) is None
                 else np.asarray(v, dtype=np.float64)) for f in dataclasses.fields(self)]

    def __eq__(self, other):
        """Same primitive type and every field equal, element by element (as float64:
        ``Sphere([0, 0, 0], 1) == Sphere(np.zeros(3), 1.0)``); NaN equals nothing.
        Exact: for a tolerance use ``allclose``."""
        if not isinstance(other, Model):
            return NotImplemented
        if type(self) is not type(other):
            return False
        return all((a is None and b is None) or (a is not None and b is not None
                                                 and np.array_equal(a, b))
                   for (_, a), (_, b) in zip(self._values(), other._values(), strict=True))

    def __hash__(self):
        """Consistent with ``==``: equal models hash alike (-0.0 is hashed as 0.0)."""
        return hash((type(self).__name__,) + tuple(
            None if v is None else (v.shape, (v + 0.0).tobytes()) for _, v in self._values()))

    def allclose(self, other, rtol: float = 1e-5, atol: float = 1e-8) -> bool:
        """Whether ``other`` is the same primitive type with every field within
        ``atol + rtol * |other's|`` of this one's (``numpy.allclose``, field by field;
        None fields must be None in both). Parameters are compared as they are: two
        models of one solid written differently (an axis and its negation, where a
        primitive's sign rules allow both) are not close."""
        return allclose(self, other, rtol=rtol, atol=atol)

    def __repr__(self):
        """``Sphere(center=[0.0, 0.0, 1.0], radius=0.5)``: fields as plain floats to six
        significant digits (nested lists for arrays), never ``np.float64(...)``."""
        return f"{type(self).__name__}(" + ", ".join(
            f"{f.name}={short(getattr(self, f.name))}" for f in dataclasses.fields(self)) + ")"

    def contains(self, points) -> np.ndarray:
        """(N,) bool: which of points (N, 3) lie in the closed, bounded solid (the surface
        included); the inside test of the two-sided measures (jaxfit.measures)."""
        raise NotImplementedError

    def sample(self, count: int, rng):
        """(count, 3) points uniform on the sampled surface and their unit outward normals
        (count, 3), from the NumPy generator ``rng``."""
        raise NotImplementedError

    # ----- pose and mass: simulators and grasping (see the module docstring) -----------
    def transform(self) -> np.ndarray:
        """(4, 4) pose of the primitive's canonical frame in the cloud's coordinates: the
        ``transform=`` that ``trimesh.creation`` builds its mesh with (``to_mesh``)."""
        raise NotImplementedError

    def volume(self) -> float:
        """Volume of the closed, bounded solid."""
        raise NotImplementedError

    def surface_area(self) -> float:
        """Area of the closed, bounded surface, caps and base included (``area`` is the
        sampled surface's)."""
        raise NotImplementedError

    def centroid(self) -> np.ndarray:
        """(3,) centre of mass of the solid at uniform density."""
        raise NotImplementedError

    def unit_inertia(self) -> np.ndarray:
        """(3,) principal moments of inertia per unit mass about ``centroid``, about the
        axes of ``transform``'s rotation (its columns)."""
        raise NotImplementedError

    def mass(self, density: float = 1.0) -> float:
        """Mass of the solid at ``density`` (mass per unit volume): density * volume."""
        return check_density(density) * self.volume()

    def inertia(self, density: float = 1.0) -> np.ndarray:
        """(3, 3) inertia tensor of the solid at ``density`` about its centre of mass
        (``centroid``), in the cloud's axes: R diag(mass * unit_inertia) R^T."""
        rot = self.transform()[:3, :3]
        return (rot * (self.mass(density) * self.unit_inertia())) @ rot.T

    # ----- facts for scenes, scenarios and the evaluation (see the module docstring) -----
    #: Share of the sampled surface's area that ``random_cut`` deletes.
    removed_share: ClassVar[float]
    #: Keys of ``error_measures`` the evaluation's tables and plots show (the CSV has all).
    shown_measures: ClassVar[tuple[str, ...]]
    #: Whether the bounded surface is the unbounded one cut to an interval along the axis
    #: (cylinder, cone): a box cut of a part can truncate it, so the PSDA re-bounds it on
    #: the inliers of its unbounded surface in the whole cloud (``from_theta``).
    axial_bounds: ClassVar[bool] = False

    @classmethod
    def random(cls, rotation, center, size: float, rng) -> Model:
        """A model in the frame ``rotation`` (3, 3) (its axis or normal, where it has one,
        along the third column) at ``center`` (3,), of scale ``size``; its remaining
        proportions are drawn from ``rng``. It follows the sign rules."""
        raise NotImplementedError

    def size(self) -> float:
        """The characteristic length surface noise and thresholds are relative to."""
        raise NotImplementedError

    def area(self) -> float:
        """Area of the sampled surface (the one ``sample`` draws on)."""
        raise NotImplementedError

    def bounding_box(self) -> tuple[np.ndarray, np.ndarray]:
        """Exact axis-aligned bounds (lo (3,), hi (3,)) of the closed, bounded model."""
        raise NotImplementedError

    def random_cut(self, rng) -> Cut:
        """The part of the sampled surface an incomplete scenario deletes: a ``Cut``
        covering ``removed_share`` of its area, drawn from ``rng``."""
        raise NotImplementedError

    def on_face(self, points, face) -> np.ndarray:
        """(N,) bool: which surface points (N, 3) lie on ``face``, a face label from
        ``random_cut`` (only primitives whose cuts name a face define it)."""
        raise NotImplementedError

    def error_measures(self, fitted: Model) -> dict[str, float]:
        """Errors of the fitted model (same primitive) against this one as the truth,
        named as in ``jaxfit.evaluation.measures`` (keys per primitive)."""
        raise NotImplementedError

    def scene_surfaces(self) -> list[tuple[Model, float, Callable]]:
        """What ``synthetic.scene`` samples of this primitive standing on its floor:
        (surface model, area, ``sample(count, rng)``) per surface. Default: the model
        itself, ``area()`` and ``sample``."""
        return [(self, self.area(), self.sample)]

    def to_dict(self) -> dict:
        """JSON-ready parameters: ``{"type": name, field: list | float, ...}``."""
        out = {"type": self.name}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            out[f.name] = None if value is None else np.asarray(value, dtype=float).tolist()
        return out

    @classmethod
    def from_dict(cls, data: dict) -> Model:
        """Inverse of ``to_dict``. Called on ``Model`` it dispatches on ``data["type"]``."""
        kind = data.get("type", getattr(cls, "name", None))
        if kind not in REGISTRY:
            raise ValueError(f"unknown primitive type {kind!r}; expected one of {sorted(REGISTRY)}")
        target = REGISTRY[kind]
        if cls is not Model and target is not cls:
            raise ValueError(f"{cls.__name__}.from_dict got a {kind!r} dictionary")
        kwargs = {}
        for field, (shape, _) in target.field_specs.items():
            if field not in data:
                raise ValueError(f"{kind} dictionary is missing the field {field!r}")
            value = data[field]
            if value is None:
                kwargs[field] = None
                continue
            arr = np.asarray(value, dtype=np.float64)
            if arr.shape[arr.ndim - len(shape):] != shape or not np.all(np.isfinite(arr)):
                raise ValueError(f"{kind} field {field!r} must be finite with shape (..., {shape})")
            kwargs[field] = arr
        return target(**kwargs)

    def rescaled(self, scale: float, shift) -> Model:
        """The same model in coordinates p * scale + shift (the engine fits a normalised cloud)."""
        fields = {}
        for field, (_, kind) in self.field_specs.items():
            value = getattr(self, field)
            if value is not None and kind != INVARIANT:
                value = value * scale + (shift if kind == POINT else 0.0)
            fields[field] = value
        # (every field is in field_specs: 3.4 us, where dataclasses.replace took 9)
        return type(self)(**fields)

    def _array(self, field):
        return np.asarray(getattr(self, field), dtype=np.float64)


@dataclasses.dataclass(frozen=True, eq=False)  # eq=False: == on array fields would be ambiguous
class Cut:
    """A part of a model's surface, deleted in the incomplete scenarios: the surface
    points p with ``(p - origin) . direction > 0``, on the whole surface, or only on
    ``face`` where one is named (``Model.on_face``).

    origin : (3,) a point on the cutting plane.
    direction : (3,) unit normal of the cutting plane, pointing into the deleted part.
    face : None, or a face label of the model (the box's: (axis index i, sign +-1), the
        face whose outward normal is sign * rotation[:, i]).
    """

    origin: np.ndarray
    direction: np.ndarray
    face: tuple[int, int] | None = None

    def covers(self, model: Model, points) -> np.ndarray:
        """(N,) bool: which surface points (N, 3) of ``model`` lie in the deleted part."""
        points = np.asarray(points, dtype=np.float64)
        beyond = (points - self.origin) @ self.direction > 0
        if self.face is None:
            return beyond
        return beyond & model.on_face(points, self.face)


def allclose(a: Model, b: Model, *, rtol: float = 1e-5, atol: float = 1e-8) -> bool:
    """Whether models a and b are of the same primitive type with every field close
    (``Model.allclose``); False, not an error, for other types or field shapes."""
    if not (isinstance(a, Model) and isinstance(b, Model)) or type(a) is not type(b):
        return False
    for (_, x), (_, y) in zip(a._values(), b._values(), strict=True):
        if x is None or y is None:
            if x is not y:
                return False
        elif x.shape != y.shape or not np.allclose(x, y, rtol=rtol, atol=atol):
            return False
    return True


def short(value, digits: int = 6) -> str:
    """A number or array as plain Python floats rounded to ``digits`` significant
    digits, nested lists for arrays (``1.0``, ``[0.5, -1.0, 2e-07]``); "None" for None.
    The reprs of models and results use it."""
    if value is None:
        return "None"
    try:
        arr = np.asarray(value, dtype=np.float64)
    except Exception:  # a traced value, inside jit: it has its own repr
        return repr(value)
    rounded = np.vectorize(lambda x: float(f"{x:.{digits}g}"), otypes=[object])(arr) \
        if arr.size else arr
    return repr(rounded.tolist() if arr.ndim else float(rounded))


def check_density(density) -> float:
    """``density`` as a float, or ValueError unless it is a positive finite number."""
    if isinstance(density, bool) or not isinstance(density, int | float | np.number):
        raise ValueError(f"density must be a positive number, got {density!r}")
    if not (np.isfinite(density) and density > 0):
        raise ValueError(f"density must be positive and finite, got {density!r}")
    return float(density)


def trimesh_scene(models, names):
    """A ``trimesh.Scene`` of the bounded models (``to_mesh``), each coloured by its type
    (``colour``) and added as the node of its name in ``names``."""
    import trimesh

    scene = trimesh.Scene()
    for model, name in zip(models, names, strict=True):
        mesh = model.to_mesh()
        mesh.visual.face_colors = model.colour
        scene.add_geometry(mesh, node_name=name)
    return scene


def mass_properties(models, density: float = 1.0):
    """Mass (), centre of mass (3,) and inertia tensor (3, 3) about it, in the cloud's
    axes, of several primitives as one rigid body of uniform ``density``: their masses
    add, their tensors move to the common centre by the parallel-axis theorem. Where
    primitives overlap, the overlap counts once per primitive. Primitives without volume
    (planes) add nothing; with no mass at all the centre is the mean of the centroids."""
    models = list(models)
    if not models:
        raise ValueError("mass_properties needs at least one primitive")
    masses = np.array([m.mass(density) for m in models])
    return combine(masses, np.array([m.centroid() for m in models]),
                   np.array([m.inertia(density) for m in models]))


def combine(masses, centroids, inertias):
    """(mass (), centre (3,), inertia (3, 3)) of bodies with masses (P,), centres of mass
    (P, 3) and inertia tensors (P, 3, 3) about them, rigidly joined: the tensors move to
    the common centre by the parallel-axis theorem, I + m (|d|^2 E - d d^T)."""
    masses, centroids = np.asarray(masses, np.float64), np.asarray(centroids, np.float64)
    total = float(masses.sum())
    centre = (masses @ centroids / total) if total > 0 else centroids.mean(axis=0)
    d = centroids - centre
    shift = (np.einsum("pi,pi->p", d, d)[:, None, None] * np.eye(3)
             - d[:, :, None] * d[:, None, :])
    tensor = np.asarray(inertias, np.float64).sum(axis=0) + np.einsum("p,pij->ij", masses, shift)
    return total, centre, 0.5 * (tensor + tensor.T)


def as_points(points):
    """(N, 3) float64 view for the NumPy model methods, with a clear error otherwise."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {arr.shape}")
    return arr


def central_difference(f, p, m, step: float):
    """f(p + step m) - f(p - step m) for coordinate sequences p and m (three arrays each):
    the one finite difference behind ``residual_slope`` and ``surface_normal``."""
    ahead, back = (f(tuple(c + s * d for c, d in zip(p, m, strict=True))) for s in (step, -step))
    return ahead - back


def components(points):
    """Coordinate arrays (x, y, z) of an (N, 3) array, in the form theta_residual takes."""
    return points[:, 0], points[:, 1], points[:, 2]
