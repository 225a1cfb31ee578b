"""What the field passes around goes in (arrays, trimesh, Open3D, paths) and comes out
(dictionaries, files, Open3D meshes); models compare, hash and print briefly.

Every entry point is checked against the same call on ``as_cloud``'s arrays, so each
source type is tested for what it converts to (``test_as_cloud_*``) and for reaching the
engine with its normals. Clouds are spheres of 800 points (bucket 1024, the size the
other tests compile), meshes sampled at that count (``MESH_POINTS`` patched)."""

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import trimesh

import jaxfit
from jaxfit import Box, Cylinder, Decomposition, FitResult, Scene, Sphere
from jaxfit.io import inputs
from jaxfit.io.inputs import SourceTypeError, as_cloud
from jaxfit.shapes import REGISTRY, allclose

COUNT = 800
TRUE = Sphere(np.array([0.3, -0.2, 0.1]), 0.5)
HEADER = "#Inventor V2.1 ascii\n"


@pytest.fixture(autouse=True)
def mesh_points(monkeypatch):
    """Meshes given to the entry points are sampled at COUNT points."""
    monkeypatch.setattr(inputs, "MESH_POINTS", COUNT)


def sphere_cloud(seed=0):
    """(COUNT, 3) points on TRUE and their outward normals."""
    return TRUE.sample(COUNT, np.random.default_rng(seed))


def o3d_cloud(points, normals=None):
    o3d = pytest.importorskip("open3d")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(normals)
    return cloud


def o3d_mesh(mesh):
    o3d = pytest.importorskip("open3d")
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                     o3d.utility.Vector3iVector(mesh.faces))


def make_source(kind, tmp_path):
    """A source of the given kind showing TRUE (points, a mesh or a file of either)."""
    points, normals = sphere_cloud()
    mesh = TRUE.to_mesh()
    if kind == "array":
        return points
    if kind == "list":
        return points.tolist()
    if kind == "trimesh.PointCloud":
        return trimesh.PointCloud(points)
    if kind == "trimesh.Trimesh":
        return mesh
    if kind == "trimesh.Scene":  # a body moved by its node's transform, as a glTF holds it
        scene = trimesh.Scene()
        moved = mesh.copy().apply_translation(-TRUE.center)
        scene.add_geometry(moved, transform=trimesh.transformations.translation_matrix(
            TRUE.center))
        return scene
    if kind == "xyz path":
        np.savetxt(tmp_path / "cloud.xyz", np.hstack([points, normals]))
        return str(tmp_path / "cloud.xyz")
    if kind == "npy path":
        np.save(tmp_path / "cloud.npy", points)
        return tmp_path / "cloud.npy"
    if kind == "obj path":
        mesh.export(tmp_path / "ball.obj")
        return tmp_path / "ball.obj"
    if kind == "iv path":
        x, y, z = TRUE.center
        (tmp_path / "ball.iv").write_text(
            HEADER + f"Separator {{ Translation {{ translation {x} {y} {z} }} "
            f"Sphere {{ radius {TRUE.radius} }} }}")
        return tmp_path / "ball.iv"
    if kind == "open3d.PointCloud":
        return o3d_cloud(points, normals)
    if kind == "open3d.TriangleMesh":
        return o3d_mesh(mesh)
    if kind == "open3d.t.PointCloud":
        return pytest.importorskip("open3d").t.geometry.PointCloud.from_legacy(
            o3d_cloud(points, normals))
    raise AssertionError(kind)


KINDS = ["array", "list", "trimesh.PointCloud", "trimesh.Trimesh", "trimesh.Scene",
         "xyz path", "npy path", "obj path", "iv path", "open3d.PointCloud",
         "open3d.TriangleMesh", "open3d.t.PointCloud"]
#: Kinds whose normals as_cloud returns.
WITH_NORMALS = {"trimesh.Trimesh", "trimesh.Scene", "xyz path", "obj path", "iv path",
                "open3d.PointCloud", "open3d.TriangleMesh", "open3d.t.PointCloud"}
MESHES = {"trimesh.Trimesh", "trimesh.Scene", "obj path", "iv path", "open3d.TriangleMesh"}


# ----- as_cloud ---------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_as_cloud_gives_the_points_on_the_surface_and_their_normals(kind, tmp_path):
    points, normals = as_cloud(make_source(kind, tmp_path), num_points=COUNT, seed=3)
    assert points.shape == (COUNT, 3) and points.dtype == np.float64
    # Sampled from a mesh: on its facets, within their sagitta of the sphere.
    tolerance = 0.01 * TRUE.radius if kind in MESHES else 1e-5
    assert np.abs(TRUE.distance(points)).max() < tolerance
    if kind not in WITH_NORMALS:
        assert normals is None
        return
    assert normals.shape == (COUNT, 3)
    radial = (points - TRUE.center) / np.linalg.norm(points - TRUE.center, axis=1)[:, None]
    assert np.abs(np.einsum("ij,ij->i", normals, radial)).min() > 0.98


@pytest.mark.parametrize("kind", sorted(MESHES))
def test_meshes_are_sampled_by_the_seed_and_count(kind, tmp_path):
    source = make_source(kind, tmp_path)
    first = as_cloud(source, num_points=300, seed=1)[0]
    assert first.shape == (300, 3)
    np.testing.assert_array_equal(first, as_cloud(source, num_points=300, seed=1)[0])
    assert not np.array_equal(first, as_cloud(source, num_points=300, seed=2)[0])
    assert len(as_cloud(source)[0]) == inputs.MESH_POINTS  # the default count


def test_a_mesh_gives_the_same_points_however_it_is_wrapped(tmp_path):
    """A Trimesh, the Open3D mesh of its triangles and decompose's load_source agree."""
    from jaxfit.decomposition import load_source

    mesh = TRUE.to_mesh()
    points, normals = as_cloud(mesh, num_points=500, seed=4)
    np.testing.assert_array_equal(points, load_source(mesh, num_points=500, seed=4))
    np.testing.assert_array_equal(points, trimesh.sample.sample_surface(mesh, 500, seed=4)[0])
    pytest.importorskip("open3d")
    again, same = as_cloud(o3d_mesh(mesh), num_points=500, seed=4)
    np.testing.assert_array_equal(again, points)
    np.testing.assert_allclose(same, normals, atol=1e-12)


def test_a_scene_merges_its_bodies_with_their_transforms():
    scene = trimesh.Scene()
    for dx in (-10.0, 10.0):
        scene.add_geometry(trimesh.creation.box(extents=(1, 1, 1)),
                           transform=trimesh.transformations.translation_matrix([dx, 0, 0]))
    points, normals = as_cloud(scene, num_points=1000)
    assert np.allclose(np.abs(points[:, 0]).min(), 9.5)
    assert 0.4 < (points[:, 0] > 0).mean() < 0.6
    # Box face normals are axis directions.
    assert np.allclose(np.sort(np.abs(normals), axis=1), [0, 0, 1])


def test_a_scene_of_point_clouds_gives_their_vertices():
    points = np.random.default_rng(0).normal(size=(50, 3))
    scene = trimesh.Scene([trimesh.PointCloud(points[:20]), trimesh.PointCloud(points[20:])])
    out, normals = as_cloud(scene)
    np.testing.assert_array_equal(np.sort(out, axis=0), np.sort(points, axis=0))
    assert normals is None


def test_an_open3d_cloud_without_normals_and_with_normals_off():
    points, normals = sphere_cloud()
    assert as_cloud(o3d_cloud(points))[1] is None
    assert as_cloud(o3d_cloud(points, normals), with_normals=False)[1] is None
    np.testing.assert_array_equal(as_cloud(o3d_cloud(points, normals))[1], normals)


@pytest.mark.parametrize("bad", [object(), {"points": [1, 2, 3]}, b"cloud.xyz", iter([])])
def test_anything_else_is_named_by_its_type(bad):
    with pytest.raises(SourceTypeError, match=type(bad).__name__) as info:
        as_cloud(bad)
    assert "trimesh" in str(info.value) and "Open3D" in str(info.value)
    assert isinstance(info.value, TypeError) and isinstance(info.value, ValueError)
    with pytest.raises(ValueError, match=type(bad).__name__):
        jaxfit.fit(bad, "sphere")
    with pytest.raises(ValueError, match=type(bad).__name__):
        jaxfit.estimate_normals(bad)


def test_bad_arrays_and_files_keep_their_messages(tmp_path):
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        as_cloud(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="NaN or inf"):
        as_cloud([[0, 0, np.nan]])
    with pytest.raises(ValueError, match="file not found"):
        as_cloud(tmp_path / "missing.xyz")
    with pytest.raises(ValueError, match="unsupported file extension"):
        jaxfit.fit(str(tmp_path / "cloud.las"), "sphere")
    with pytest.raises(ValueError, match="num_points"):
        as_cloud(TRUE.to_mesh(), num_points=0)


def test_neither_trimesh_nor_open3d_is_imported_for_arrays():
    code = textwrap.dedent("""
        import sys
        import numpy as np
        import jaxfit
        from jaxfit.io.inputs import as_cloud
        as_cloud(np.zeros((4, 3)))
        jaxfit.estimate_normals(np.random.default_rng(0).normal(size=(50, 3)))
        print(sorted(m for m in ("trimesh", "open3d") if m in sys.modules))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "[]", out.stderr


# ----- the entry points -----------------------------------------------------------------


def spy_prepare(monkeypatch):
    """The normals fit_batch hands to the engine, one entry per cloud."""
    engine_fit = sys.modules["jaxfit.engine.fit"]  # (jaxfit.engine.fit is the function)
    seen = []
    real = engine_fit.prepare

    def prepare(points, cls, normals, *args, **kwargs):
        seen.append(normals)
        return real(points, cls, normals, *args, **kwargs)

    monkeypatch.setattr(engine_fit, "prepare", prepare)
    return seen


@pytest.mark.parametrize("kind", KINDS)
def test_fit_takes_every_source_with_its_normals(kind, tmp_path, monkeypatch):
    source = make_source(kind, tmp_path)
    points, normals = as_cloud(source, seed=0)
    seen = spy_prepare(monkeypatch)
    result = jaxfit.fit(source, "sphere", key=0)
    if normals is None:
        assert seen == [None]
    else:
        np.testing.assert_array_equal(seen[0], normals)
    expected = jaxfit.fit(points, "sphere", normals=normals, key=0)
    assert result.model == expected.model
    np.testing.assert_array_equal(result.inliers, expected.inliers)
    assert result.model.allclose(TRUE, rtol=0.02, atol=0.01)


def test_normals_given_win_over_the_sources(tmp_path, monkeypatch):
    source = make_source("open3d.PointCloud", tmp_path)
    mine = np.tile([0.0, 0.0, 1.0], (COUNT, 1))
    seen = spy_prepare(monkeypatch)
    jaxfit.fit(source, "sphere", normals=mine, key=0)
    np.testing.assert_array_equal(seen[0], mine)


def test_fit_batch_takes_a_mix_of_sources(tmp_path, monkeypatch):
    # (three clouds of one bucket, as test_inputs batches: no new kernel)
    sources = [make_source(k, tmp_path) for k in ("array", "trimesh.Scene", "xyz path")]
    seen = spy_prepare(monkeypatch)
    results = jaxfit.fit_batch(sources, "sphere", key=5)
    assert seen[0] is None and all(s is not None for s in seen[1:])
    clouds = [as_cloud(source, seed=5) for source in sources]
    again = jaxfit.fit_batch([c[0] for c in clouds], "sphere", normals=[c[1] for c in clouds],
                             key=5)
    assert [r.model for r in results] == [r.model for r in again]
    with pytest.raises(SourceTypeError, match="cloud 1: .*object"):
        jaxfit.fit_batch([sources[0], object()], "sphere")


@pytest.mark.parametrize("kind", KINDS)
def test_estimate_normals_takes_every_source(kind, tmp_path):
    source = make_source(kind, tmp_path)
    points, _ = as_cloud(source, seed=0)
    np.testing.assert_array_equal(jaxfit.estimate_normals(source),
                                  jaxfit.estimate_normals(points))


@pytest.mark.parametrize("kind", KINDS)
def test_detect_takes_every_source_with_its_normals(kind, tmp_path, monkeypatch):
    source = make_source(kind, tmp_path)
    points, normals = as_cloud(source, seed=0)
    if normals is not None:  # the source's own normals: none are estimated
        def refuse(*args, **kwargs):
            raise AssertionError("detect estimated normals the source has")

        monkeypatch.setattr(sys.modules["jaxfit.detect"], "estimate_normals", refuse)
    else:
        normals = jaxfit.estimate_normals(points, k=16, orient=None)
    found = jaxfit.detect(source, shapes=("sphere",), key=0)
    expected = jaxfit.detect(points, shapes=("sphere",), normals=normals, key=0)
    assert [d.model for d in found.shapes] == [d.model for d in expected.shapes]
    assert len(found.shapes) == 1 and found.shapes[0].model.allclose(TRUE, rtol=0.02,
                                                                       atol=0.01)
    np.testing.assert_array_equal(found.points, points)


@pytest.fixture(scope="module")
def decomposed():
    """decompose of a trimesh.Scene (what trimesh.load gives for the YCB glTFs: it was
    rejected with "points must be numeric ... not 'Scene'"), as test_decompose's sphere."""
    scene = trimesh.Scene(Sphere(np.zeros(3), 1.0).to_mesh())
    return scene, jaxfit.decompose(scene, num_points=1500, gain=0.8, shapes=("sphere",))


def test_decompose_takes_a_scene(decomposed):
    scene, result = decomposed
    np.testing.assert_array_equal(result.points, as_cloud(scene, num_points=1500, seed=0)[0])
    assert len(result.parts) == 1 and result.parts[0].kind == "sphere"
    with pytest.raises(ValueError, match="dict"):
        jaxfit.decompose({"mesh": scene})


@pytest.mark.slow
def test_decompose_takes_open3d_and_files(decomposed, tmp_path):
    scene, result = decomposed
    mesh = scene.to_mesh()
    mesh.export(tmp_path / "ball.ply")
    for source in (o3d_mesh(mesh), tmp_path / "ball.ply"):
        again = jaxfit.decompose(source, num_points=1500, gain=0.8, shapes=("sphere",))
        # (PLY stores float32 vertices)
        assert again.parts[0].model.allclose(result.parts[0].model, rtol=1e-5, atol=1e-6)


# ----- results out ---------------------------------------------------------------------


def through_json(data):
    return json.loads(json.dumps(data))


def test_fit_result_round_trips_and_gives_indices():
    points, _ = sphere_cloud()
    result = jaxfit.fit(points, "sphere", key=0)
    np.testing.assert_array_equal(result.inlier_indices, np.flatnonzero(result.inliers))
    back = FitResult.from_dict(through_json(result.to_dict()))
    assert back.model == result.model and back.status is result.status
    np.testing.assert_array_equal(back.inliers, result.inliers)
    assert (back.num_inliers, back.cost, back.num_hypotheses, back.threshold) == (
        result.num_inliers, result.cost, result.num_hypotheses, result.threshold)
    with pytest.raises(ValueError, match="missing cost"):
        FitResult.from_dict({k: v for k, v in result.to_dict().items() if k != "cost"})


def scene_of_two():
    """Two spheres apart: detect finds both (sphere kernels only)."""
    a, _ = sphere_cloud(0)
    b, _ = Sphere(np.array([3.0, 0.0, 0.0]), 0.4).sample(600, np.random.default_rng(1))
    return np.vstack([a[:600], b])


def check_same_scene(back, scene):
    assert [d.model for d in back.shapes] == [d.model for d in scene.shapes]
    for d, e in zip(back.shapes, scene.shapes, strict=True):
        np.testing.assert_array_equal(d.indices, e.indices)
        assert (d.cost, d.round) == (e.cost, e.round)
    np.testing.assert_array_equal(back.unassigned, scene.unassigned)
    assert (back.threshold, back.spacing, back.radius) == (scene.threshold, scene.spacing,
                                                           scene.radius)


def test_scene_round_trips_saves_and_gives_masks(tmp_path):
    points = scene_of_two()
    scene = jaxfit.detect(points, shapes=("sphere",), key=0)
    assert len(scene.shapes) == 2
    masks = scene.masks()
    assert masks.shape == (2, len(points)) and not (masks.sum(axis=0) > 1).any()
    for mask, d in zip(masks, scene.shapes, strict=True):
        np.testing.assert_array_equal(np.flatnonzero(mask), d.indices)
    back = Scene.from_dict(through_json(scene.to_dict()), points=points)
    check_same_scene(back, scene)
    assert Scene.from_dict(through_json(scene.to_dict(with_points=True))).points.shape == \
        points.shape

    folder = scene.save(tmp_path / "out")
    assert {p.name for p in folder.iterdir()} == {"scene.json", "points.npy", "scene.glb",
                                                 "preview.png"}
    assert (folder / "preview.png").stat().st_size > 10_000
    assert len(trimesh.load(folder / "scene.glb").geometry) == 2
    loaded = Scene.load(folder)
    check_same_scene(loaded, scene)
    np.testing.assert_array_equal(loaded.points, points)
    with pytest.raises(ValueError, match="covers 1200 points"):
        Scene.from_dict(scene.to_dict(), points=points[:10])
    with pytest.raises(ValueError, match="no readable scene.json"):
        Scene.load(tmp_path)


def test_decomposition_round_trips_and_loads(decomposed, tmp_path):
    _, result = decomposed
    back = Decomposition.from_dict(through_json(result.to_dict()), points=result.points)
    assert through_json(back.to_dict()) == through_json(result.to_dict())
    check_same_decomposition(back, result)
    check_same_decomposition(
        Decomposition.from_dict(through_json(result.to_dict(with_points=True))), result)
    folder = result.save(tmp_path / "out")
    loaded = Decomposition.load(folder)
    check_same_decomposition(loaded, result)
    assert loaded.summary() == result.summary()
    masks = result.masks()
    assert masks.shape == (len(result.parts), len(result.points))
    np.testing.assert_array_equal(np.flatnonzero(masks[0]), result.parts[0].indices)
    with pytest.raises(ValueError, match="holds no points"):
        Decomposition.from_dict(result.to_dict())
    with pytest.raises(ValueError, match="no saved decomposition"):
        Decomposition.load(tmp_path)


def check_same_decomposition(back, result):
    np.testing.assert_array_equal(back.points, result.points)
    assert back.seconds == result.seconds
    for p, q in zip(back.parts, result.parts, strict=True):
        assert (p.kind, p.winner, p.mean_distance) == (q.kind, q.winner, q.mean_distance)
        assert p.model == q.model and p.box == q.box and p.candidates == q.candidates
        np.testing.assert_array_equal(p.indices, q.indices)
        assert p.candidates["mvbb"].model is p.box
        assert p.candidates[p.winner].model is p.model
    assert back.tree.leaves == result.tree.leaves
    for m, n in zip(back.tree.nodes, result.tree.nodes, strict=True):
        assert m.box == n.box and (m.children, m.parent, m.depth) == (n.children, n.parent,
                                                                      n.depth)
        np.testing.assert_array_equal(m.indices, n.indices)


# ----- models: compare, hash, print, Open3D ----------------------------------------------


def random_models(seed=0):
    """One random model of every primitive (``Model.random``)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    return [cls.random(Rotation.random(random_state=seed).as_matrix(), rng.normal(size=3),
                       1.0, rng) for _, cls in sorted(REGISTRY.items())]


@pytest.mark.parametrize("model", random_models(), ids=sorted(REGISTRY))
def test_models_compare_and_hash_by_their_fields(model):
    same = type(model).from_dict(through_json(model.to_dict()))
    assert same == model and not same != model and hash(same) == hash(model)
    assert len({model, same}) == 1
    field = next(iter(model.field_specs))
    value = np.asarray(getattr(model, field), np.float64)
    nudged = type(model)(**{**{f: getattr(model, f) for f in model.field_specs},
                            field: value + 1e-9})
    assert nudged != model and nudged.allclose(model) and allclose(nudged, model)
    moved = type(model)(**{**{f: getattr(model, f) for f in model.field_specs},
                           field: value + 0.1})
    assert not moved.allclose(model) and moved.allclose(model, atol=0.2)
    assert model != object() and not allclose(model, object())
    assert "np.float64" not in repr(model) and "array(" not in repr(model)


def test_equality_across_dtypes_types_and_signed_zeros():
    a = Sphere(np.array([0.0, -0.0, 1.0]), 2.0)
    b = Sphere([0, 0, 1], 2)
    assert a == b and hash(a) == hash(b)
    assert Sphere(np.zeros(3), 1.0) != Cylinder(np.zeros(3), np.array([0, 0, 1.0]), 1.0, 1.0)
    assert not allclose(Sphere(np.zeros(3), 1.0),
                        Cylinder(np.zeros(3), np.array([0, 0, 1.0]), 1.0, 1.0))
    assert repr(b) == "Sphere(center=[0.0, 0.0, 1.0], radius=2.0)"
    assert Sphere(np.array([np.nan, 0, 0]), 1.0) != Sphere(np.array([np.nan, 0, 0]), 1.0)


def test_reprs_are_short(decomposed):
    points, _ = sphere_cloud()
    result = jaxfit.fit(points, "sphere", key=0)
    text = repr(result)
    assert len(text) < 300 and f"inliers={result.num_inliers} of {COUNT}" in text
    assert "np.float64" not in text and "True" not in text
    _, decomposition = decomposed
    for obj in (decomposition, decomposition.parts[0]):
        assert len(repr(obj)) < 400 and "array(" not in repr(obj)
    scene = jaxfit.detect(points, shapes=("sphere",), key=0)
    for obj in (scene, scene.shapes[0]):
        assert len(repr(obj)) < 400 and "array(" not in repr(obj)


@pytest.mark.parametrize("model", [Box(np.zeros(3), np.eye(3), np.array([1.0, 2.0, 3.0])),
                                   TRUE], ids=["box", "sphere"])
def test_to_open3d_is_the_trimesh_mesh(model):
    pytest.importorskip("open3d")
    out, mesh = model.to_open3d(), model.to_mesh()
    np.testing.assert_array_equal(np.asarray(out.vertices), mesh.vertices)
    np.testing.assert_array_equal(np.asarray(out.triangles), mesh.faces)
    assert out.has_vertex_normals()
    np.testing.assert_allclose(np.asarray(out.vertex_colors)[0],
                               np.asarray(model.colour[:3]) / 255)
    # and back in: the Open3D mesh is a source like any other (on the facets)
    assert np.abs(model.distance(as_cloud(out, num_points=200)[0])).max() < 0.01


def test_to_open3d_without_open3d_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)  # import open3d now raises
    with pytest.raises(ImportError, match="pip install open3d"):
        TRUE.to_open3d()
