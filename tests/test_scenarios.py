"""The thesis's noise scenarios: exact counts, clean points on the surface, the deleted
part really missing, the asked-for noise levels, and reproducibility."""

import numpy as np
import pytest
from conftest import SHAPES

from jaxfit.evaluation import scenarios
from jaxfit.evaluation.scenarios import RN_LEVELS, SCENARIOS, SN_LEVELS, make
from jaxfit.shapes import Box, Cone, Cylinder, Sphere

THESIS_SHAPES = ("sphere", "cylinder", "cone", "box")


def surface_share_removed(scn, count=40_000, seed=7):
    """Share of the complete sampled surface that the scenario's cut covers."""
    full, _ = scn.model.sample(count, np.random.default_rng(seed))
    return float(np.mean(scn.cut.covers(scn.model, full)))


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_counts_shapes_and_masks(shape, scenario):
    scn = make(shape, scenario, 0.3, count=1000, seed=3)
    assert scn.points.shape == scn.normals.shape == (1000, 3)
    assert scn.inliers.shape == (1000,) and scn.inliers.dtype == bool
    np.testing.assert_allclose(np.linalg.norm(scn.normals, axis=1), 1.0)
    expected_outliers = 300 if scenario.startswith("RN") else 0  # SN has no outliers
    assert np.sum(~scn.inliers) == expected_outliers
    assert (scn.shape, scn.scenario, scn.level, scn.seed) == (shape, scenario, 0.3, 3)
    assert (scn.cut is not None) == scenario.endswith("IM")
    assert not scn.points.flags.writeable


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("scenario", ["RN", "RNIM"])
def test_rn_surface_points_lie_on_the_true_model(shape, scenario):
    scn = make(shape, scenario, 0.5, seed=11)
    assert np.max(scn.model.distance(scn.points[scn.inliers])) < 1e-9
    # The true normals are the surface's: moving along them leaves the surface.
    stepped = scn.points[scn.inliers] + 1e-3 * scn.normals[scn.inliers]
    assert np.min(scn.model.distance(stepped)) > 0.5e-3


@pytest.mark.parametrize("level", RN_LEVELS)
def test_rn_outlier_share_is_exact_and_outliers_fill_the_cube(level):
    scn = make("cylinder", "RN", level, count=2000, seed=1)
    assert np.sum(~scn.inliers) == round(level * 2000)
    center, half = scenarios.outlier_cube(scn.model)
    outliers = scn.points[~scn.inliers]
    assert np.all(np.abs(outliers - center) <= half)
    # Uniform in the cube, not squeezed near the shape: they reach close to its faces.
    assert np.all(np.max(np.abs(outliers - center), axis=0) > 0.9 * half)


def test_outlier_cube_is_the_bounding_cube_grown_by_half():
    model = make("box", "RN", 0.1, axis_aligned=True).model
    center, half = scenarios.outlier_cube(model)
    np.testing.assert_allclose(center, model.center)
    assert half == pytest.approx(0.75 * np.max(model.extents))
    # The analytic bounds enclose the mesh of every primitive, and touch it.
    for shape in SHAPES:
        m = make(shape, "RN", 0.1, seed=5).model
        lo, hi = scenarios.bounding_box(m)
        verts = m.to_mesh().vertices
        assert np.all(verts >= lo - 1e-9) and np.all(verts <= hi + 1e-9)
        np.testing.assert_allclose(verts.min(axis=0), lo, atol=0.01 * np.max(hi - lo))


@pytest.mark.parametrize("scenario", ["RNIM", "SNIM"])
def test_rnim_sphere_misses_a_hemisphere(scenario):
    scn = make("sphere", scenario, 0.2, seed=4)
    cut = scn.cut
    np.testing.assert_allclose(cut.origin, scn.model.center)
    surface = scn.points[scn.inliers]
    if scenario == "SNIM":  # undo the radial displacement to find the surface point
        surface = scn.model.center + scn.model.radius * scn.normals[scn.inliers]
    assert np.all((surface - cut.origin) @ cut.direction <= 0)
    assert surface_share_removed(scn) == pytest.approx(0.5, abs=0.01)


@pytest.mark.parametrize("shape", ["cylinder", "cone"])
def test_rnim_cylinder_and_cone_miss_half_the_side_cut_along_the_axis(shape):
    scn = make(shape, "RNIM", 0.3, seed=8)
    model, cut = scn.model, scn.cut
    # The cutting plane contains the axis: its normal is orthogonal to the axis and it
    # passes through a point of the axis.
    assert abs(cut.direction @ model.axis) < 1e-12
    origin = model.center if shape == "cylinder" else model.apex
    np.testing.assert_allclose(cut.origin, origin)
    surface = scn.points[scn.inliers]
    assert np.all((surface - cut.origin) @ cut.direction <= 0)
    assert surface_share_removed(scn) == pytest.approx(0.5, abs=0.01)
    # Both halves of the kept side are well covered: no other part is missing.
    assert np.mean((surface - cut.origin) @ model.axis > 0) > 0.3


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rnim_box_misses_a_strip_of_ten_percent_of_the_area(seed):
    scn = make("box", "RNIM", 0.2, seed=seed)
    box, cut = scn.model, scn.cut
    ext, rot = box.extents, box.rotation
    face_axis, face_sign = cut.face
    assert ext[face_axis] == ext.min()  # one of the two largest faces
    # Recover the strip from the cut: the edge axis j it lies against, and its width.
    j = int(np.argmax(np.abs(rot.T @ cut.direction)))
    k = 3 - face_axis - j
    width = 0.5 * ext[j] - (cut.origin - box.center) @ cut.direction
    total = 2 * (ext[0] * ext[1] + ext[0] * ext[2] + ext[1] * ext[2])
    assert width * ext[k] == pytest.approx(0.1 * total)
    assert 0 < width < ext[j]
    # No generated point on that face reaches into the strip...
    local = (scn.points[scn.inliers] - box.center) @ rot
    on_face = np.abs(face_sign * local[:, face_axis] - 0.5 * ext[face_axis]) < 1e-9
    assert on_face.sum() > 50
    along = local[on_face] @ (rot.T @ cut.direction)
    assert np.max(along) <= 0.5 * ext[j] - width + 1e-12
    # ... while the rest of the face keeps its points, up to the strip's edge.
    assert np.max(along) > 0.5 * ext[j] - width - 0.1 * ext[j]
    assert surface_share_removed(scn) == pytest.approx(0.1, abs=0.008)


@pytest.mark.parametrize("sc", SN_LEVELS)
@pytest.mark.parametrize("shape", ["sphere", "cylinder"])
def test_sn_displacements_are_uniform_within_sc_size(shape, sc):
    scn = make(shape, "SN", sc, seed=2)
    bound = sc * scn.size
    # For the sphere and the cylinder the normal is radial: the residual is the shift.
    d = scn.model.residual(scn.points)
    assert np.all(scn.inliers)
    assert np.max(np.abs(d)) <= bound * (1 + 1e-12)
    assert np.max(np.abs(d)) > 0.99 * bound
    assert np.mean(np.abs(d)) == pytest.approx(bound / 2, rel=0.1)
    assert np.mean(d > 0) == pytest.approx(0.5, abs=0.05)
    quarters = np.histogram(d, bins=4, range=(-bound, bound))[0] / len(d)
    np.testing.assert_allclose(quarters, 0.25, atol=0.04)


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("scenario", ["SN", "SNIM"])
def test_sn_points_stay_within_sc_size_of_the_surface(shape, scenario):
    sc = 0.1
    scn = make(shape, scenario, sc, seed=6)
    dist = scn.model.distance(scn.points)
    # A point moved by |d| along the normal is at most |d| from the surface.
    assert np.max(dist) <= sc * scn.size + 1e-12
    assert np.mean(dist) > 0.25 * sc * scn.size


def test_shape_size_definitions():
    sphere, cyl, cone, box = (make(s, "SN", 0.1, seed=9).model for s in THESIS_SHAPES)
    assert scenarios.shape_size(sphere) == sphere.radius
    assert scenarios.shape_size(cyl) == cyl.radius
    assert scenarios.shape_size(cone) == pytest.approx(cone.height * np.tan(cone.half_angle))
    assert scenarios.shape_size(box) == pytest.approx(np.mean(box.extents))


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_same_seed_same_cloud_other_seed_other_cloud(scenario):
    a, b = make("cone", scenario, 0.1, seed=5), make("cone", scenario, 0.1, seed=5)
    c = make("cone", scenario, 0.1, seed=6)
    for field in ("points", "normals", "inliers"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    np.testing.assert_array_equal(a.model.apex, b.model.apex)
    assert not np.allclose(a.points, c.points)
    assert not np.allclose(a.model.apex, c.model.apex)


def test_one_seed_one_shape_across_scenarios_and_levels():
    models = [make("box", s, lvl, seed=3).model for s in SCENARIOS for lvl in (0.1, 0.5)]
    for m in models[1:]:
        np.testing.assert_array_equal(m.center, models[0].center)
        np.testing.assert_array_equal(m.extents, models[0].extents)
    cut_rn, cut_sn = make("box", "RNIM", 0.1, seed=3).cut, make("box", "SNIM", 0.1, seed=3).cut
    np.testing.assert_array_equal(cut_rn.origin, cut_sn.origin)


def test_pose_is_random_unless_axis_aligned():
    for seed in range(5):
        model = make("cylinder", "RN", 0.1, seed=seed).model
        assert np.max(np.abs(model.axis)) < 0.999
        assert isinstance(model, Cylinder)
    aligned = make("cylinder", "RN", 0.1, axis_aligned=True).model
    np.testing.assert_array_equal(aligned.axis, [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(make("box", "SN", 0.1, axis_aligned=True).model.rotation,
                                  np.eye(3))
    box = make("box", "SN", 0.1, seed=4).model
    assert isinstance(box, Box) and np.linalg.det(box.rotation) == pytest.approx(1.0)
    assert isinstance(make("sphere", "SN", 0.1).model, Sphere)
    assert isinstance(make("cone", "SN", 0.1).model, Cone)


def test_sizes_are_of_unit_order():
    for shape in THESIS_SHAPES:
        for seed in range(5):
            assert 0.3 < make(shape, "RN", 0.1, seed=seed).size < 1.5


@pytest.mark.parametrize(
    ("args", "kwargs", "message"),
    [
        (("torus", "RN", 0.1), {}, "unknown shape"),
        (("sphere", "XN", 0.1), {}, "unknown scenario"),
        (("sphere", None, 0.1), {}, "unknown scenario"),
        (("sphere", "RN", -0.1), {}, r"\[0, 1\)"),
        (("sphere", "RN", 1.0), {}, r"\[0, 1\)"),
        (("sphere", "SN", 1.5), {}, "scattering factor"),
        (("sphere", "SN", True), {}, r"\[0, 1\)"),
        (("sphere", "RN", 0.1), {"count": 0}, "count"),
        (("sphere", "RN", 0.1), {"count": 2.5}, "count"),
        (("sphere", "RN", 0.5), {"count": 6}, "at least 4"),
        (("sphere", "RN", 0.1), {"seed": -1}, "seed"),
    ],
)
def test_bad_arguments_raise_clear_errors(args, kwargs, message):
    with pytest.raises(ValueError, match=message):
        make(*args, **kwargs)


def test_names_are_case_insensitive_and_levels_listed():
    scn = make("Sphere", "rnim", 0.2, count=100)
    assert (scn.shape, scn.scenario) == ("sphere", "RNIM")
    assert scenarios.levels("snim") == SN_LEVELS and scenarios.levels("RN") == RN_LEVELS


# ----- the shape facts the scenarios read (Model.area, size, bounding_box, random, cut) -----


def test_removed_share_table_is_the_shapes_attribute():
    from jaxfit.shapes import REGISTRY

    assert scenarios.REMOVED_SHARE == {n: c.removed_share for n, c in REGISTRY.items()}
    assert scenarios.REMOVED_SHARE["box"] == 0.1 and scenarios.REMOVED_SHARE["sphere"] == 0.5


@pytest.mark.parametrize("shape", SHAPES)
def test_random_cut_deletes_the_removed_share_of_the_area(shape):
    scn = make(shape, "RNIM", 0.2, seed=2)
    assert surface_share_removed(scn) == pytest.approx(scn.model.removed_share, abs=0.01)
    # The cut is the shape's own, drawn from the scenario's cut stream.
    cut = scn.model.random_cut(np.random.default_rng([2, 1]))
    np.testing.assert_array_equal(cut.origin, scn.cut.origin)
    np.testing.assert_array_equal(cut.direction, scn.cut.direction)


def _sides_area(model, mesh):
    """Area of the mesh's faces whose outward normal is not along the axis (the side of a
    cylinder or a cone, without caps or base)."""
    along = np.abs(mesh.face_normals @ model.axis) > 0.999
    return float(mesh.area_faces[~along].sum())


@pytest.mark.parametrize("shape", SHAPES)
def test_area_is_the_area_of_the_sampled_surface(shape):
    model = make(shape, "RN", 0.1, seed=4).model
    if shape == "sphere":
        mesh_area = model.to_mesh(subdivisions=6).area
    elif shape in ("cylinder", "cone"):
        mesh_area = _sides_area(model, model.to_mesh(sections=2048))
    elif shape == "plane":
        mesh_area = model.to_mesh(sections=2048).area
    else:
        mesh_area = model.to_mesh().area
    assert model.area() == pytest.approx(mesh_area, rel=1e-4)


def test_size_of_a_plane_is_its_patch_radius():
    plane = make("plane", "SN", 0.1, seed=9).model
    assert plane.size() == scenarios.shape_size(plane) == plane.radius


@pytest.mark.parametrize("shape", SHAPES)
def test_bounding_box_holds_the_sampled_surface_and_touches_it(shape):
    model = make(shape, "RN", 0.1, seed=3).model
    lo, hi = model.bounding_box()
    points, _ = model.sample(20_000, np.random.default_rng(0))
    assert np.all(points >= lo - 1e-12) and np.all(points <= hi + 1e-12)
    np.testing.assert_allclose(points.min(axis=0), lo, atol=0.02 * np.max(hi - lo))


@pytest.mark.parametrize("shape", SHAPES)
def test_random_places_the_model_in_the_given_frame(shape):
    from jaxfit.evaluation.synthetic import random_rotation
    from jaxfit.shapes import REGISTRY

    cls = REGISTRY[shape]
    rotation, center = random_rotation(np.random.default_rng(1)), np.array([0.3, -0.2, 0.5])
    model = cls.random(rotation, center, 0.9, np.random.default_rng(2))
    again = cls.random(rotation, center, 0.9, np.random.default_rng(2))
    assert model.to_dict() == again.to_dict()  # all randomness from rng
    lo, hi = model.bounding_box()
    assert np.all(lo <= center) and np.all(center <= hi)
    assert 0.3 < model.size() < 1.5
    # The sign rules hold: canonicalising the parameters changes nothing.
    assert type(model).from_dict(model.to_dict()).to_dict() == model.to_dict()
    if shape in ("cylinder", "cone", "plane"):
        direction = model.normal if shape == "plane" else model.axis
        assert abs(abs(direction @ rotation[:, 2]) - 1.0) < 1e-12


def test_box_cut_names_a_face_and_on_face_picks_its_points():
    box = make("box", "RN", 0.1, seed=1).model
    cut = box.random_cut(np.random.default_rng(0))
    axis, sign = cut.face
    for other_axis in range(3):
        for other_sign in (-1, 1):
            points, normals = box.sample_face(other_axis, other_sign, 200,
                                              np.random.default_rng(5))
            assert np.max(box.distance(points)) < 1e-12
            np.testing.assert_array_equal(
                normals, np.tile(other_sign * box.rotation[:, other_axis], (200, 1)))
            expected = (other_axis, other_sign) == (axis, sign)
            assert np.all(box.on_face(points, (axis, sign)) == expected)


def test_scene_surfaces_of_a_box_are_its_five_upper_faces():
    from jaxfit.shapes import Plane

    box = make("box", "RN", 0.1, seed=2, axis_aligned=True).model
    surfaces = box.scene_surfaces()
    assert len(surfaces) == 5 and all(isinstance(m, Plane) for m, _, _ in surfaces)
    bottom = box.extents[0] * box.extents[1]
    assert sum(area for _, area, _ in surfaces) == pytest.approx(box.area() - bottom)
    for face, area, sample in surfaces:
        axis = int(np.argmax(np.abs(box.rotation.T @ face.normal)))
        assert area == pytest.approx(np.prod(box.extents) / box.extents[axis])
        points, normals = sample(300, np.random.default_rng(0))
        assert np.max(np.abs(face.residual(points))) < 1e-12
        assert np.max(box.distance(points)) < 1e-12
        np.testing.assert_allclose(np.abs(normals @ face.normal), 1.0)
        assert np.all(points[:, 2] > box.center[2] - 0.5 * box.extents[2] + 1e-9)
    sphere = make("sphere", "RN", 0.1).model
    ((model, area, sample),) = sphere.scene_surfaces()
    assert model is sphere and area == sphere.area() and sample == sphere.sample
