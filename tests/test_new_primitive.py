"""A new primitive is one class plus its registration: a line (an edge, a thin pole),
written here as the README's worked example, is fitted by the unchanged engine with
every feature that reads the class's attributes (bounds on its axis, fit_batch,
serialisation)."""

from typing import ClassVar

import jax.numpy as jnp
import numpy as np
import pytest

import jaxfit
from jaxfit.shapes import REGISTRY, Model
from jaxfit.shapes import _geometry as g
from jaxfit.shapes._base import INVARIANT, POINT, register


def define_line():
    """The worked example of the README (in a real primitive: jaxfit/shapes/line.py, and
    one import in jaxfit/shapes/__init__.py)."""

    @register
    class Line(Model):
        """Infinite line through ``point`` along the unit ``direction``.
        theta = (point (3), direction (3))."""

        point: np.ndarray
        direction: np.ndarray

        name: ClassVar[str] = "line"
        colour: ClassVar[tuple[int, int, int, int]] = (0, 0, 0, 255)
        sample_size: ClassVar[int] = 2
        num_params: ClassVar[int] = 6
        axis_index: ClassVar[int] = 3  # axis_prior bounds the direction
        field_specs: ClassVar = {"point": ((3,), POINT), "direction": ((3,), INVARIANT)}

        @staticmethod
        def estimate(sample, support):  # JAX, under vmap; never raises
            direction, length = g.safe_normalize(sample[1] - sample[0])
            return jnp.concatenate([sample[0], direction]), length > g.LEN_TOL

        @staticmethod
        def theta_residual(theta, p, xp):  # distance to the line, broadcasting
            d = [p[i] - theta[i] for i in range(3)]
            along = d[0] * theta[3] + d[1] * theta[4] + d[2] * theta[5]
            return xp.sqrt(xp.maximum(d[0] ** 2 + d[1] ** 2 + d[2] ** 2 - along**2, 0.0))

        @staticmethod
        def canonicalize(theta):
            return theta.at[3:].set(theta[3:] / jnp.linalg.norm(theta[3:]))

        @classmethod
        def from_theta(cls, theta, points, inliers, threshold):
            return cls(np.asarray(theta[:3]), g.unit(np.asarray(theta[3:])))

        def theta(self):
            return np.concatenate([self.point, self.direction])

        def distance(self, points):
            return self.residual(points)

    return Line


@pytest.fixture(scope="module")
def line():
    cls = define_line()
    yield cls
    del REGISTRY[cls.name]  # other tests iterate over the five built-in primitives


def line_cloud(seed, count=600, outliers=0.4):
    rng = np.random.default_rng(seed)
    point, direction = rng.uniform(-1, 1, 3), g.unit(rng.normal(size=3))
    on = int(count * (1 - outliers))
    points = point + rng.uniform(-2, 2, (on, 1)) * direction + rng.normal(0, 0.002, (on, 3))
    return np.vstack([points, rng.uniform(-2, 2, (count - on, 3))]), point, direction


def test_the_engine_fits_a_registered_line(line):
    points, point, direction = line_cloud(0)
    result = jaxfit.fit(points, "line", threshold=0.01, key=0)
    assert isinstance(result.model, line)
    assert np.degrees(np.arccos(min(1.0, abs(result.model.direction @ direction)))) < 0.5
    assert line(point, direction).distance(result.model.point[None])[0] < 0.01
    assert result.num_inliers >= 360 and result.status is jaxfit.Status.CONVERGED


def test_a_line_takes_bounds_batches_and_serialisation(line):
    clouds = [line_cloud(seed)[0] for seed in (1, 2, 3)]
    results = jaxfit.fit_batch(clouds, line, thresholds=0.01, key=1)
    assert all(r.num_inliers >= 360 for r in results)
    _, _, direction = line_cloud(4)
    bounded = jaxfit.fit(line_cloud(4)[0], "line", threshold=0.01,
                         axis_prior=(direction, 5), key=2)
    assert abs(bounded.model.direction @ direction) >= np.cos(np.radians(5))
    with pytest.raises(ValueError, match="radius_range does not apply to a line"):
        jaxfit.fit(clouds[0], "line", radius_range=(0, 1))
    data = results[0].model.to_dict()
    assert Model.from_dict(data).to_dict() == data


def test_field_specs_must_name_the_fields():
    """``from_dict`` and ``rescaled`` build a model from its ``field_specs``: a class whose
    specs leave out a field is refused when it is registered, naming both lists."""

    class Ray(Model):
        origin: np.ndarray
        direction: np.ndarray

        name: ClassVar[str] = "ray-not-registered"
        field_specs: ClassVar = {"origin": ((3,), POINT)}

    with pytest.raises(TypeError, match=r"field_specs must name its fields \['origin', "
                                         r"'direction'\]"):
        register(Ray)
    assert "ray-not-registered" not in REGISTRY
