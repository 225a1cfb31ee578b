"""What a fit is asked to do: ``FitOptions`` (every setting of ``fit`` and ``fit_batch``,
checked once) and ``Bounds`` (the user's bounds on a hypothesis, a pytree the kernel reads).

``fit`` and ``fit_batch`` build one ``FitOptions`` from their keyword arguments (or take
one), call ``check`` and hand the checked object to the engine; nothing below them
validates again (COLMAP's ``RANSACOptions::Check``).
"""

from __future__ import annotations

import dataclasses
import functools
import numbers

import jax
import jax.export
import jax.numpy as jnp
import numpy as np

from .. import _checks
from ..shapes import Model
from .refine import LevenbergMarquardt, LocalOptimizer
from .sampling import Sampler, UniformSampler
from .scoring import MSAC, Scorer
from .stopping import AdaptiveStopping, StoppingRule

#: The ``normal_cos`` of bounds without a normal gate (no cosine is below it).
NO_GATE = -2.0


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Bounds:
    """The user's bounds on a hypothesis, in the frame of the points they are used with.

    radius_low, radius_high : () the radius a hypothesis may have (``Model.radius_index``).
    axis : (3,) unit direction the axis (a plane's normal) must stay near, either sign.
    axis_cos : () least |cos| between the axis and ``axis`` (0: any axis).
    normal_cos : () least |cos| between a point's normal and the surface's for the point
        to be an inlier (``NO_GATE``: no gate).

    They are read by name; they are kept as one array ``values`` (..., 7) in that order,
    so that a kernel call passes one argument, not five (each array argument of a jitted
    call costs a transfer; five made a 500-point fit ~10 % slower). ``values`` may carry
    leading axes (one row per cloud in the host loop); the kernels see one cloud's.
    """

    values: jax.Array | np.ndarray

    @classmethod
    def make(cls, radius_low=0.0, radius_high=np.inf, axis=(0.0, 0.0, 1.0), axis_cos=0.0,
             normal_cos=NO_GATE) -> Bounds:
        """Bounds from named values (unchecked: see ``of``)."""
        return cls(np.concatenate([[radius_low, radius_high], np.asarray(axis, np.float64),
                                   [axis_cos, normal_cos]]))

    radius_low = property(lambda self: self.values[..., 0])
    radius_high = property(lambda self: self.values[..., 1])
    axis = property(lambda self: self.values[..., 2:5])
    axis_cos = property(lambda self: self.values[..., 5])
    normal_cos = property(lambda self: self.values[..., 6])

    @classmethod
    def of(cls, model: type[Model], radius_range=None, axis_prior=None,
           normal_angle=None) -> Bounds:
        """Bounds from the user's arguments, with clear errors.

        radius_range : None or (low, high), 0 <= low < high (shapes with a radius_index).
        axis_prior : None or (direction (3,), max_angle_deg in (0, 90]) (shapes with an
            axis_index).
        normal_angle : None or degrees in (0, 90].
        """
        low, high, axis, axis_cos, normal_cos = 0.0, np.inf, np.array([0.0, 0.0, 1.0]), 0.0, NO_GATE
        if normal_angle is not None:
            if (isinstance(normal_angle, bool) or not isinstance(normal_angle, numbers.Real)
                    or not 0 < normal_angle <= 90):
                raise ValueError(f"normal_angle must be in (0, 90] degrees, got {normal_angle!r}")
            normal_cos = float(np.cos(np.radians(float(normal_angle))))
        if radius_range is not None:
            if model.radius_index is None:
                raise ValueError(f"radius_range does not apply to a {model.name} "
                                 f"({_having(model, 'radius_index')})")
            low, high = (float(v) for v in radius_range)
            if not 0 <= low < high:
                raise ValueError(f"radius_range must be (low, high) with 0 <= low < high, got "
                                 f"{radius_range!r}")
        if axis_prior is not None:
            if model.axis_index is None:
                raise ValueError(f"axis_prior does not apply to a {model.name} "
                                 f"({_having(model, 'axis_index')})")
            direction, angle = axis_prior
            direction = np.asarray(direction, np.float64).reshape(-1)
            length = np.linalg.norm(direction) if direction.shape == (3,) else np.nan
            if not (np.isfinite(length) and length > 0):
                raise ValueError(f"axis_prior direction must be a non-zero finite 3-vector, got "
                                 f"{axis_prior[0]!r}")
            if not 0 < float(angle) <= 90:
                raise ValueError(f"axis_prior angle must be in (0, 90] degrees, got {angle!r}")
            axis = direction / length
            axis_cos = float(np.cos(np.radians(float(angle))))
        return cls.make(low, high, axis, axis_cos, normal_cos)

    @property
    def gated(self) -> bool:
        """Whether points are gated on their normals (host side, unbatched bounds)."""
        return bool(np.asarray(self.normal_cos) > -1)

    def scaled(self, scale: float) -> Bounds:
        """The bounds for points divided by ``scale``: radii scale, directions do not."""
        values = np.array(self.values, np.float64)
        values[..., :2] /= scale
        return Bounds(values)

    @staticmethod
    def stack(rows: list[Bounds], dtype) -> Bounds:
        """One Bounds with a leading axis over ``rows``, as ``dtype``."""
        return Bounds(np.stack([row.values for row in rows]).astype(dtype))

    def admits(self, model: type[Model], theta, xp=jnp):
        """Whether hypothesis theta (P,) honours the radius and axis bounds (``xp``:
        jax.numpy in the kernels, numpy in the final refit; never raises, so it can mask
        a whole batch)."""
        ok = xp.asarray(True)
        if model.radius_index is not None:
            radius = theta[model.radius_index]
            ok &= (radius >= self.radius_low) & (radius <= self.radius_high)
        if model.axis_index is not None:
            axis = theta[model.axis_index:model.axis_index + 3]
            ok &= xp.abs(xp.dot(axis, self.axis)) >= self.axis_cos
        return ok


# jax.export writes the kernels' argument structure with their programs (_cache.Stored):
# Bounds must be a node it can serialize (it has no auxiliary data).
jax.export.register_pytree_node_serialization(
    Bounds, serialized_name="jaxfit.engine.Bounds", serialize_auxdata=lambda aux: b"",
    deserialize_auxdata=lambda data: ())


def _having(model: type[Model], attribute: str) -> str:
    """The registered shapes that have ``attribute`` set, for an error message."""
    from ..shapes import REGISTRY

    return ", ".join(name for name, cls in REGISTRY.items() if getattr(cls, attribute) is not None)


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Every setting of ``fit`` and ``fit_batch`` but the data, the threshold and the key.

    confidence : probability p of having drawn one all-inlier sample when stopping.
    max_hypotheses : budget of hypotheses (rounded up to whole batches).
    batch_size : hypotheses per kernel call (H); each value compiles its own kernel.
    max_stall : stop after this many hypotheses without a better model.
    min_hypotheses : floor on the confidence-based count T; default the estimator's own.
        ``min_hypotheses=max_hypotheses`` (with a large ``max_stall``) runs a fixed number.
    refine : local optimisation (LO-RANSAC) of each new best hypothesis by ``refiner``.
    final_refit : a float64 least-squares refit on all inliers of each cloud of more than
        ``refine.FINAL_MIN_POINTS`` points after the search (``refine.final_refit``);
        off with ``refine=False`` too.
    polish : with ``refine=False``, LO's refit on the host after the search
        (``refine.host_lo``, float64, every cloud, each of the best batch's
        ``lo_starts`` starts): no refinement program is compiled, for one-off fits in a
        fresh process, where compiling it costs more than all its rounds. MSAC only.
    estimator : "thesis" or "oriented" (see ``Model.estimators``); default the shape's
        ``default_estimator``.
    radius_range, axis_prior, normal_angle : the user's bounds (see ``Bounds.of``).
    sampler, scorer, stopping, refiner : the RANSAC stages (``UniformSampler``, ``MSAC``,
        ``AdaptiveStopping``, ``LevenbergMarquardt``); frozen, hashable objects, passed
        to the kernels as static arguments, so each choice compiles its own kernel.

    ``check(shape)`` returns the checked options: numbers converted, the estimator and
    ``min_hypotheses`` resolved for the shape, ``bounds`` made; it is idempotent.
    """

    confidence: float = 0.99
    max_hypotheses: int = 100_000
    batch_size: int = 256
    max_stall: int = 20_000
    min_hypotheses: int | None = None
    refine: bool = True
    final_refit: bool = True
    polish: bool = False
    estimator: str | None = None
    radius_range: tuple | None = None
    axis_prior: tuple | None = None
    normal_angle: float | None = None
    sampler: Sampler = UniformSampler()
    scorer: Scorer = MSAC()
    stopping: StoppingRule = AdaptiveStopping()
    refiner: LocalOptimizer = LevenbergMarquardt()
    #: Filled by ``check``: the bounds in the points' units.
    bounds: Bounds | None = dataclasses.field(default=None, repr=False, compare=False)

    @classmethod
    def build(cls, options: FitOptions | None = None, **settings) -> FitOptions:
        """``options`` (default ``FitOptions()``) with ``settings`` replaced; an unknown
        setting raises a TypeError that lists the known ones."""
        known = {f.name for f in dataclasses.fields(cls)} - {"bounds"}
        unknown = sorted(set(settings) - known)
        if unknown:
            raise TypeError(f"unknown fit option(s) {', '.join(map(repr, unknown))}; "
                            f"expected among {', '.join(sorted(known))}")
        if options is not None and not isinstance(options, FitOptions):
            raise TypeError(f"options must be a jaxfit.FitOptions, got {type(options).__name__}")
        base = FitOptions() if options is None else options
        return dataclasses.replace(base, **settings) if settings else base

    def check(self, shape: type[Model]) -> FitOptions:
        """The checked options for fitting ``shape`` (see the class docstring); kept for
        hashable options (a small fit spent ~15 us checking the same ones again), keyed
        on the fields' types too, since 256.0 == 256 and True == 1 check differently."""
        try:
            hash(self)
        except TypeError:  # unhashable settings (lists, arrays): check them now
            return self._check(shape)
        types = tuple(type(getattr(self, f.name)) for f in dataclasses.fields(self))
        return _checked(self, shape, types)

    def _check(self, shape: type[Model]) -> FitOptions:
        est = shape.estimator(self.estimator)
        bounds = Bounds.of(shape, self.radius_range, self.axis_prior, self.normal_angle)
        min_hypotheses = self.min_hypotheses
        if min_hypotheses is None:
            min_hypotheses = est.min_hypotheses
        elif isinstance(min_hypotheses, bool) or not (isinstance(min_hypotheses, numbers.Integral)
                                                      and min_hypotheses >= 0):
            raise ValueError(
                f"min_hypotheses must be a non-negative integer, got {min_hypotheses!r}")
        for name in ("refine", "final_refit", "polish"):
            if not isinstance(getattr(self, name), bool | np.bool_):
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")
        if self.polish and self.refine:
            raise ValueError("polish refits on the host instead of LO: set refine=False "
                             "with it")
        if self.polish and type(self.scorer) is not MSAC:
            raise ValueError(f"polish fits least squares, MSAC's own optimum: it needs the "
                             f"MSAC scorer, got {self.scorer!r}")
        for stage, kind in ((self.sampler, Sampler), (self.scorer, Scorer),
                            (self.stopping, StoppingRule), (self.refiner, LocalOptimizer)):
            if not isinstance(stage, kind):
                raise TypeError(f"{kind.__name__.lower()} must be a jaxfit {kind.__name__}, "
                                f"got {stage!r}")
            try:
                hash(stage)
            except TypeError:
                raise TypeError(f"{kind.__name__.lower()} {stage!r} must be hashable (a frozen "
                                "dataclass): the kernels take it as a static argument") from None
        return dataclasses.replace(
            self,
            confidence=_checks.probability(self.confidence, "confidence"),
            max_hypotheses=_checks.positive(self.max_hypotheses, "max_hypotheses", integer=True),
            batch_size=_batch_size(self.batch_size),
            max_stall=_checks.positive(self.max_stall, "max_stall", integer=True),
            min_hypotheses=int(min_hypotheses), refine=bool(self.refine),
            final_refit=bool(self.final_refit), polish=bool(self.polish),
            estimator=est.name,
            bounds=bounds,
        )


#: Largest ``batch_size``: one call's hypotheses times a bucket's points must stay within
#: memory and int32 (2**28 asked XLA for 151 GB; 2**31 overflowed).
MAX_BATCH = 1 << 16


def _batch_size(value) -> int:
    size = _checks.positive(value, "batch_size", integer=True)
    if size > MAX_BATCH:
        raise ValueError(f"batch_size must be at most {MAX_BATCH} (jaxfit.engine.options."
                         f"MAX_BATCH: hypotheses scored in one call), got {size}")
    return size


@functools.lru_cache(maxsize=256)
def _checked(options: FitOptions, shape: type[Model], types: tuple) -> FitOptions:
    return options._check(shape)
