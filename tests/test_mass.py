"""Poses and physical quantities of every primitive (``Model.transform``, ``volume``,
``surface_area``, ``centroid``, ``mass``, ``inertia``; ``shapes.mass_properties``),
against trimesh's meshes built with the same parameters and ``transform=``, in random
poses. trimesh integrates its tessellated mesh exactly, so the tolerances are the
tessellation's: 256 sections lose 1e-4 of a cylinder's volume, an icosphere of 5
subdivisions 5e-4 of a sphere's."""

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from jaxfit.shapes import Box, Cone, Cylinder, Plane, Sphere, mass_properties

SECTIONS = 256
DENSITY = 730.0
SEEDS = range(4)


def random_model(cls, seed):
    rng = np.random.default_rng(seed)
    rotation = Rotation.random(random_state=seed).as_matrix()
    return cls.random(rotation, rng.normal(size=3), rng.uniform(0.05, 2.0), rng)


def creation_mesh(model, transform):
    """trimesh.creation's primitive with the model's parameters, built at ``transform``."""
    if isinstance(model, Box):
        return trimesh.creation.box(extents=model.extents, transform=transform)
    if isinstance(model, Cylinder):
        return trimesh.creation.cylinder(radius=float(model.radius), height=float(model.height),
                                         sections=SECTIONS, transform=transform)
    if isinstance(model, Cone):
        return trimesh.creation.cone(radius=float(model.base_radius),
                                     height=float(model.height), sections=SECTIONS,
                                     transform=transform)
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=float(model.radius))
    return mesh.apply_transform(transform)


SOLIDS = [Box, Cylinder, Cone, Sphere]
TOLERANCE = {"box": 1e-9, "cylinder": 1e-3, "cone": 1e-3, "sphere": 2e-3}


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("cls", SOLIDS, ids=lambda c: c.name)
def test_against_trimesh(cls, seed):
    model = random_model(cls, seed)
    mesh = creation_mesh(model, model.transform())
    mesh.density = DENSITY
    tol = TOLERANCE[model.name]
    size = np.linalg.norm(mesh.extents)
    # The transform is the canonical frame: the mesh built there lies on the model.
    assert np.max(model.distance(mesh.vertices)) < 1e-9 * size
    assert model.volume() == pytest.approx(mesh.volume, rel=tol)
    assert model.surface_area() == pytest.approx(mesh.area, rel=tol)
    assert model.mass(DENSITY) == pytest.approx(mesh.mass, rel=tol)
    np.testing.assert_allclose(model.centroid(), mesh.center_mass, atol=1e-9 * size)
    inertia = model.inertia(DENSITY)
    scale = np.abs(mesh.moment_inertia).max()
    np.testing.assert_allclose(inertia, mesh.moment_inertia, atol=2 * tol * scale)


@pytest.mark.parametrize("cls", SOLIDS, ids=lambda c: c.name)
def test_to_mesh_is_built_at_the_transform(cls):
    model = random_model(cls, 7)
    np.testing.assert_allclose(model.to_mesh().bounds,
                               creation_mesh(model, model.transform()).bounds, atol=1e-2)
    transform = model.transform()
    np.testing.assert_allclose(transform[:3, :3] @ transform[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(transform[:3, :3]) == pytest.approx(1.0)
    np.testing.assert_array_equal(transform[3], [0, 0, 0, 1])


def test_axes_of_the_frames():
    """+Z is the cylinder's axis, and runs from a cone's base (the origin) to its apex."""
    cylinder = random_model(Cylinder, 3)
    np.testing.assert_allclose(cylinder.transform()[:3, 2], cylinder.axis)
    np.testing.assert_allclose(cylinder.transform()[:3, 3], cylinder.center)
    cone = random_model(Cone, 3)
    t = cone.transform()
    np.testing.assert_allclose(t[:3, 3] + float(cone.height) * t[:3, 2], cone.apex, atol=1e-12)


@pytest.mark.parametrize("cls", SOLIDS, ids=lambda c: c.name)
def test_inertia_laws(cls):
    """Symmetric, positive definite, the triangle inequality of principal moments, linear
    in density; under p -> s p + shift the volume scales by s^3 and the inertia by s^5."""
    model = random_model(cls, 11)
    inertia = model.inertia(2.0)
    np.testing.assert_allclose(inertia, inertia.T, atol=1e-15 * np.abs(inertia).max())
    moments = np.linalg.eigvalsh(inertia)
    assert moments.min() > 0
    assert moments[0] + moments[1] >= moments[2] * (1 - 1e-12)
    np.testing.assert_allclose(model.inertia(6.0), 3.0 * inertia)
    s, shift = 2.5, np.array([1.0, -2.0, 0.5])
    moved = model.rescaled(s, shift)
    assert moved.volume() == pytest.approx(s**3 * model.volume())
    np.testing.assert_allclose(moved.inertia(2.0), s**5 * inertia, atol=1e-12 * s**5 *
                               np.abs(inertia).max())
    np.testing.assert_allclose(moved.centroid(), s * model.centroid() + shift)


def test_plane_has_a_frame_and_no_mass():
    plane = random_model(Plane, 5)
    t = plane.transform()
    np.testing.assert_allclose(t[:3, 2], plane.normal)
    np.testing.assert_allclose(t[:3, 3], plane.center)
    assert plane.residual(t[:3, 3][None])[0] == pytest.approx(0.0, abs=1e-12)
    assert plane.volume() == 0.0 and plane.mass(1000.0) == 0.0
    np.testing.assert_array_equal(plane.inertia(1000.0), np.zeros((3, 3)))
    assert plane.surface_area() == pytest.approx(np.pi * float(plane.radius) ** 2)
    with pytest.raises(ValueError, match="unbounded plane"):
        Plane(plane.normal, plane.offset).transform()


@pytest.mark.parametrize("density", [0.0, -1.0, float("nan"), float("inf"), "1", True])
def test_density_must_be_positive(density):
    with pytest.raises(ValueError, match="density"):
        random_model(Box, 0).mass(density)


def test_mass_properties_combine_by_the_parallel_axis_theorem():
    """A box cut into two halves along its first axis is the box again; a plane adds no
    mass; the centre of massless primitives is their centroids' mean."""
    whole = random_model(Box, 2)
    rot, ext = np.asarray(whole.rotation), np.asarray(whole.extents)
    half = ext * [0.5, 1.0, 1.0]
    halves = [Box(whole.center + s * 0.25 * ext[0] * rot[:, 0], rot, half) for s in (-1, 1)]
    plane = random_model(Plane, 4)
    mass, centre, inertia = mass_properties(halves + [plane], DENSITY)
    assert mass == pytest.approx(whole.mass(DENSITY))
    np.testing.assert_allclose(centre, whole.center, atol=1e-12)
    np.testing.assert_allclose(inertia, whole.inertia(DENSITY),
                               atol=1e-12 * np.abs(inertia).max())
    mass, centre, inertia = mass_properties([plane, random_model(Plane, 6)])
    assert mass == 0.0 and not inertia.any()
    np.testing.assert_allclose(centre, 0.5 * (plane.center + random_model(Plane, 6).center))
    with pytest.raises(ValueError, match="at least one"):
        mass_properties([])
