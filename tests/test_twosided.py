"""Two-sided measures (jaxfit.evaluation.twosided) and Model.contains, on hand-made cases
with known answers. NumPy only: nothing here compiles a JAX kernel."""

import numpy as np
import pytest
import trimesh

from jaxfit.evaluation import twosided as ts
from jaxfit.shapes import Box, Cone, Cylinder, Plane, Sphere

UNIT_CUBE = Box(np.zeros(3), np.eye(3), np.ones(3))


def _tilted(rng):
    """A random proper rotation (3, 3)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q * np.array([1.0, 1.0, np.linalg.det(q)])


def _solids(rng):
    rot = _tilted(rng)
    return [
        Sphere(np.array([0.3, -0.2, 1.0]), np.float64(0.7)),
        Cylinder(np.array([1.0, 0.5, 0.0]), rot[:, 2], np.float64(0.4), np.float64(1.5)),
        Cone(np.array([0.0, 0.0, 1.0]), rot[:, 0], np.float64(0.5), np.float64(1.2)),
        Box(np.array([0.0, 1.0, -0.5]), rot, np.array([1.0, 0.4, 2.0])),
    ]


def _closed_surface_with_normals(model, rng, count=400):
    """Points on the closed surface and outward normals, caps and bases included."""
    points, normals = model.sample(count, rng)
    pose = model.transform()
    if model.name == "cylinder":
        rho = 0.9 * float(model.radius) * np.sqrt(rng.uniform(size=count))
        z = np.where(rng.uniform(size=count) < 0.5, -0.5, 0.5) * float(model.height)
        local = np.stack([rho, np.zeros(count), z], 1)
        cap_normals = np.sign(z)[:, None] * pose[:3, 2]
    elif model.name == "cone":  # the base at z = 0, the apex at +z
        rho = 0.9 * float(model.base_radius) * np.sqrt(rng.uniform(size=count))
        local = np.stack([rho, np.zeros(count), np.zeros(count)], 1)
        cap_normals = np.tile(-pose[:3, 2], (count, 1))
    else:
        return points, normals
    caps = local @ pose[:3, :3].T + pose[:3, 3]
    return np.concatenate([points, caps]), np.concatenate([normals, cap_normals])


@pytest.mark.parametrize("index", range(4))
def test_contains_just_inside_and_outside(index):
    rng = np.random.default_rng(index)
    model = _solids(rng)[index]
    points, normals = _closed_surface_with_normals(model, rng)
    step = 1e-4 * model.size()
    # stay off a cone's apex and a cylinder's or box's rims, where a step along one
    # face's normal can leave through the other
    interior = model.distance(points - 20 * step * normals) > 10 * step
    assert interior.mean() > 0.8
    assert model.contains(points - step * normals)[interior].all()
    assert not model.contains(points + step * normals)[interior].any()
    assert model.contains(points).mean() > 0.99  # the surface is included


@pytest.mark.parametrize("index", range(4))
def test_contains_volume_matches(index):
    """The share of uniform points in the solid times the box's volume is volume()."""
    rng = np.random.default_rng(10 + index)
    model = _solids(rng)[index]
    lo, hi = model.bounding_box()
    points = rng.uniform(lo, hi, (60000, 3))
    share = model.contains(points).mean()
    box = np.prod(hi - lo)
    se = np.sqrt(share * (1 - share) / len(points)) * box
    assert abs(share * box - model.volume()) < 4 * se


def test_plane_has_no_solid():
    plane = Plane(np.array([0.0, 0.0, 1.0]), np.float64(0.0), np.zeros(3), np.float64(1.0))
    with pytest.raises(ValueError, match="no solid"):
        plane.contains(np.zeros((2, 3)))


def test_winding_number_closed_mesh():
    sphere = trimesh.creation.icosphere(subdivisions=3)  # 1280 faces: the far field is used
    rng = np.random.default_rng(0)
    points = rng.uniform(-1.5, 1.5, (3000, 3))
    radius = np.linalg.norm(points, axis=1)
    clear = np.abs(radius - 1.0) > 0.02  # off the (faceted) surface
    fast = ts.winding_numbers(sphere.vertices, sphere.faces, points)
    exact = ts.winding_numbers(sphere.vertices, sphere.faces, points[:300], far=np.inf)
    assert np.abs(fast[:300] - exact).max() < 0.02
    assert np.allclose(fast[clear], (radius[clear] < 1.0).astype(float), atol=0.02)
    assert (ts.inside_mesh(sphere.vertices, sphere.faces, points)[clear]
            == (radius[clear] < 1.0)).all()


def test_winding_number_mesh_with_a_hole():
    """A cube missing one face: each face subtends a sixth of the sphere from the centre,
    so the centre's winding number is 5/6; a half icosphere (it is centrally symmetric)
    gives exactly 1/2 at its centre."""
    cube = trimesh.creation.box(extents=(1, 1, 1))
    top = cube.face_normals[:, 2] > 0.5
    assert top.sum() == 2
    w = ts.winding_numbers(cube.vertices, cube.faces[~top], np.zeros((1, 3)), far=np.inf)
    assert w[0] == pytest.approx(5 / 6, abs=1e-12)
    sphere = trimesh.creation.icosphere(subdivisions=3)
    # a generic direction splits every face from its antipode (z = 0 would cut faces)
    lower = sphere.triangles_center @ np.array([0.3, 0.5, 0.8]) < 0
    assert lower.sum() == len(sphere.faces) // 2
    centre = np.zeros((1, 3))
    exact = ts.winding_numbers(sphere.vertices, sphere.faces[lower], centre, far=np.inf)
    assert exact[0] == pytest.approx(0.5, abs=1e-9)
    half = ts.winding_numbers(sphere.vertices, sphere.faces[lower], centre)
    assert half[0] == pytest.approx(0.5, abs=0.005)
    far_away = ts.winding_numbers(sphere.vertices, sphere.faces[lower], np.array([[0, 0, 50.0]]))
    assert abs(far_away[0]) < 1e-3


def test_unit_cube_against_itself():
    out = ts.compare(trimesh.creation.box(extents=(1, 1, 1)), [UNIT_CUBE], seed=0)
    assert out["viou"] == pytest.approx(1.0, abs=3 * out["viou_se"] + 1e-12)
    assert out["chamfer"] < 1e-9 and out["hausdorff"] < 1e-9
    assert out["diagonal"] == pytest.approx(np.sqrt(3))


def test_cube_against_its_inscribed_sphere():
    """vIoU = (pi/6) / 1 within four standard errors, and the one-sided parts of the
    Chamfer distance: a corner of the cube is sqrt(3)/2 - 1/2 from the sphere."""
    out = ts.compare(trimesh.creation.box(extents=(1, 1, 1)),
                     [Sphere(np.zeros(3), np.float64(0.5))], seed=0)
    assert 0 < out["viou_se"] < 0.004
    assert out["viou"] == pytest.approx(np.pi / 6, abs=4 * out["viou_se"])
    corner = (np.sqrt(3) / 2 - 0.5) / np.sqrt(3)
    assert out["hausdorff"] == pytest.approx(corner, rel=0.05)
    assert out["object_volume"] == pytest.approx(1.0)


def test_hausdorff_of_a_shifted_sphere():
    """Two unit spheres 0.1 apart: Hausdorff 0.1 and Chamfer near 0.05 (mean |cos|
    of the shift over the sphere is 1/2), over the diagonal 2 sqrt(3)."""
    mesh = trimesh.creation.icosphere(subdivisions=4)
    out = ts.compare(mesh, [Sphere(np.array([0.1, 0.0, 0.0]), np.float64(1.0))], seed=1)
    diagonal = np.linalg.norm(np.ptp(mesh.vertices, axis=0))
    assert out["hausdorff"] * diagonal == pytest.approx(0.1, rel=0.03)
    assert out["chamfer"] * diagonal == pytest.approx(0.05, rel=0.05)


def test_surface_inside_another_primitive_is_not_surface():
    """Two overlapping unit-side boxes forming a 1 x 1 x 1.5 bar: the faces inside the
    other box are dropped, so the bar's own mesh is matched exactly."""
    a = Box(np.array([0.0, 0.0, -0.25]), np.eye(3), np.ones(3))
    b = Box(np.array([0.0, 0.0, 0.25]), np.eye(3), np.ones(3))
    bar = trimesh.creation.box(extents=(1, 1, 1.5))
    out = ts.compare(bar, [a, b], seed=2)
    assert out["chamfer"] < 1e-9
    kept = out["union_surface_kept"]
    # of the 12 faces' area, the inner end faces (1 each) are dropped; the side strips
    # where the boxes overlap lie on both boxes' surfaces (not inside either), so stay
    assert kept == pytest.approx(10.0 / 12.0, abs=0.02)
    assert out["viou"] == pytest.approx(1.0)


def test_point_cloud_coverage():
    """A cloud on a unit sphere against the sphere and a far box: the box is wholly
    uncovered, the sphere nowhere."""
    rng = np.random.default_rng(3)
    sphere = Sphere(np.zeros(3), np.float64(1.0))
    cloud = sphere.sample(4000, rng)[0]
    out = ts.compare(cloud, [sphere, Box(np.array([4.0, 0, 0]), np.eye(3), np.ones(3))])
    assert "viou" not in out
    assert out["uncovered_per_model"][0] < 0.01
    assert out["uncovered_per_model"][1] == 1.0
    alone = ts.compare(cloud, [sphere])
    assert alone["uncovered"] < 0.01 and alone["chamfer"] < 0.01


def test_convex_solid_matches_box():
    """A convex piece built from a box's corners measures like the box."""
    corners = np.array(np.meshgrid(*[[-0.5, 0.5]] * 3)).reshape(3, -1).T
    piece = ts.ConvexSolid(corners)
    rng = np.random.default_rng(4)
    points = rng.uniform(-1, 1, (2000, 3))
    assert (piece.contains(points) == UNIT_CUBE.contains(points)).all()
    assert np.allclose(piece.distance(points), UNIT_CUBE.distance(points), atol=1e-12)
    obb = ts.oriented_box(corners @ _tilted(rng).T)
    assert np.allclose(np.sort(obb.extents), 1.0, atol=1e-6)


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="at least one model"):
        ts.compare(np.zeros((5, 3)), [])
    with pytest.raises(ValueError, match="faces"):
        ts.winding_numbers(np.zeros((3, 3)), np.array([[0, 1, 5]]), np.zeros((1, 3)))


def test_faces_two_solids_share_are_not_surface():
    """Two unit cubes side by side, face to face (as a convex decomposition's pieces
    meet): the shared face is inside the 2 x 1 x 1 bar, so it is neither sampled nor far
    from the bar's mesh (it would be 0.5 from it)."""
    a = Box(np.array([-0.5, 0.0, 0.0]), np.eye(3), np.ones(3))
    b = Box(np.array([0.5, 0.0, 0.0]), np.eye(3), np.ones(3))
    out = ts.compare(trimesh.creation.box(extents=(2, 1, 1)), [a, b], seed=3)
    assert out["union_surface_kept"] == pytest.approx(10.0 / 12.0, abs=0.02)
    assert out["hausdorff"] < 1e-9
