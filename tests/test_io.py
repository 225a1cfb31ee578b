"""Tests for jaxfit.io.load_points: round trips, error messages and the shared real data."""

from pathlib import Path

import numpy as np
import pytest
import trimesh

from jaxfit.io import SUPPORTED_EXTENSIONS, LoadError, load_points
from jaxfit.io.points import load_cloud

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

# Dyadic extents so that the float32 coordinates of an STL hold the box corners exactly.
BOX_EXTENTS = np.array([1.0, 2.0, 0.5])


@pytest.fixture
def pts():
    return np.random.default_rng(7).normal(size=(40, 3))


def check(out, n=None):
    assert isinstance(out, np.ndarray)
    assert out.dtype == np.float64 and out.flags.c_contiguous
    assert out.ndim == 2 and out.shape[1] == 3
    if n is not None:
        assert out.shape[0] == n
    assert np.isfinite(out).all()


def fmt(row, sep=" "):
    return sep.join(f"{v:.17g}" for v in row)  # 17 digits round-trip float64 exactly


def write(path, text):
    path.write_text(text)
    return path


# --- round trips -------------------------------------------------------------------------


def test_xyz_whitespace(tmp_path, pts):
    lines = ["# exported by some scanner", ""]
    lines += [fmt(p, "  ") for p in pts]
    lines.insert(10, "\t")  # blank-but-for-whitespace lines are skipped too
    out = load_points(write(tmp_path / "a.xyz", "\n".join(lines) + "\n"))
    check(out, len(pts))
    np.testing.assert_array_equal(out, pts)


def test_csv_commas_and_header(tmp_path, pts):
    text = "x, y, z\n" + "\n".join(fmt(p, ",") for p in pts)
    out = load_points(write(tmp_path / "a.CSV", text))  # extension is case-insensitive
    np.testing.assert_array_equal(out, pts)


def test_txt_six_columns_uses_first_three(tmp_path, pts):
    normals = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    data = np.hstack([pts, normals])
    np.savetxt(tmp_path / "a.txt", data, header="x y z nx ny nz")  # '#' header
    out = load_points(tmp_path / "a.txt")
    np.testing.assert_allclose(out, pts, rtol=1e-15)


def test_pts_point_count_line(tmp_path, pts):
    text = f"{len(pts)}\n" + "\n".join(fmt(p) + " 0 255 0 0" for p in pts)
    np.testing.assert_array_equal(load_points(write(tmp_path / "a.pts", text)), pts)


def test_npy(tmp_path, pts):
    np.save(tmp_path / "a.npy", pts.astype(np.float32))
    out = load_points(str(tmp_path / "a.npy"))
    check(out, len(pts))
    np.testing.assert_array_equal(out, pts.astype(np.float32))
    np.save(tmp_path / "b.npy", np.hstack([pts, pts]))
    np.testing.assert_array_equal(load_points(tmp_path / "b.npy"), pts)


def test_ply_point_cloud_returns_vertices_as_stored(tmp_path, pts):
    pts = np.vstack([pts, pts[:3]])  # duplicates must survive (no vertex merging)
    trimesh.PointCloud(pts).export(tmp_path / "cloud.ply")
    out = load_points(tmp_path / "cloud.ply", num_points=5)
    check(out, len(pts))
    np.testing.assert_array_equal(out, pts.astype(np.float32))  # PLY stores float32


@pytest.mark.parametrize("ext", [".stl", ".obj", ".ply", ".off"])
def test_mesh_box_is_surface_sampled(tmp_path, ext):
    path = tmp_path / f"box{ext}"
    trimesh.creation.box(extents=BOX_EXTENTS).export(path)
    out = load_points(path, num_points=3000, seed=1)
    check(out, 3000)
    # On the surface of an axis-aligned box centred at 0: inside the box, and on (at
    # least) one face plane |x_i| == h_i.
    half = BOX_EXTENTS / 2
    excess = np.abs(out) - half
    assert excess.max() < 1e-9
    assert np.abs(excess).min(axis=1).max() < 1e-9
    # Spread over all six faces, not stuck on a few triangles.
    on_face = np.abs(excess) < 1e-9
    for axis in range(3):
        for sign in (-1, 1):
            assert (on_face[:, axis] & (np.sign(out[:, axis]) == sign)).any()

    np.testing.assert_array_equal(out, load_points(path, num_points=3000, seed=1))
    assert not np.array_equal(out, load_points(path, num_points=3000, seed=2))


def test_scene_bodies_are_merged_with_transforms(tmp_path):
    scene = trimesh.Scene()
    for dx in (-10.0, 10.0):
        move = trimesh.transformations.translation_matrix([dx, 0.0, 0.0])
        scene.add_geometry(trimesh.creation.box(extents=(1, 1, 1)), transform=move)
    scene.export(tmp_path / "two.glb")
    out = load_points(tmp_path / "two.glb", num_points=1000)
    check(out, 1000)
    assert np.allclose(np.abs(out[:, 0]).min(), 9.5) and np.allclose(np.abs(out).max(), 10.5)
    assert 0.4 < (out[:, 0] > 0).mean() < 0.6  # both bodies sampled, by area


def test_material_failure_falls_back_to_geometry(tmp_path, monkeypatch):
    path = tmp_path / "box.obj"
    trimesh.creation.box(extents=BOX_EXTENTS).export(path)
    real_load = trimesh.load

    def picky_load(*args, **kwargs):
        if not kwargs.get("skip_materials"):
            raise OSError("texture image not found")
        return real_load(*args, **kwargs)

    monkeypatch.setattr(trimesh, "load", picky_load)
    check(load_points(path, num_points=100), 100)


def test_supported_extensions():
    assert isinstance(SUPPORTED_EXTENSIONS, tuple)
    expected = ".ply .obj .stl .off .glb .gltf .xyz .txt .csv .crd .pts .npy".split()
    assert set(expected) <= set(SUPPORTED_EXTENSIONS)


# --- errors ------------------------------------------------------------------------------


def test_error_is_value_error():
    assert issubclass(LoadError, ValueError)


def test_missing_file(tmp_path):
    with pytest.raises(ValueError, match="not found.*nope.xyz"):
        load_points(tmp_path / "nope.xyz")


def test_unsupported_extension(tmp_path):
    path = write(tmp_path / "a.las", "1 2 3\n")
    with pytest.raises(ValueError, match=r"unsupported.*\.las.*\.ply.*\.npy") as info:
        load_points(path)
    assert isinstance(info.value, LoadError)


@pytest.mark.parametrize(
    "name, text",
    [
        ("empty.xyz", ""),
        ("comments.xyz", "# nothing here\n\n# still nothing\n"),
        ("header_only.csv", "x,y,z\n"),
        ("empty.obj", ""),
        ("noverts.obj", "# no geometry\n"),
    ],
)
def test_no_points(tmp_path, name, text):
    with pytest.raises(ValueError, match="no points"):
        load_points(write(tmp_path / name, text))


def test_empty_npy(tmp_path):
    np.save(tmp_path / "e.npy", np.zeros((0, 3)))
    with pytest.raises(ValueError, match="no points"):
        load_points(tmp_path / "e.npy")


def test_too_few_columns(tmp_path):
    with pytest.raises(ValueError, match="line 2 .* 2 column"):
        load_points(write(tmp_path / "a.xyz", "1 2 3\n4 5\n"))
    np.save(tmp_path / "a.npy", np.zeros((4, 2)))
    with pytest.raises(ValueError, match="at least 3 columns"):
        load_points(tmp_path / "a.npy")
    np.save(tmp_path / "b.npy", np.zeros(6))
    with pytest.raises(ValueError, match="shape"):
        load_points(tmp_path / "b.npy")


def test_non_numeric(tmp_path):
    with pytest.raises(ValueError, match="non-numeric.*line 3"):
        load_points(write(tmp_path / "a.csv", "x,y,z\n1,2,3\n4,five,6\n"))
    with pytest.raises(ValueError, match="non-numeric"):
        load_points(write(tmp_path / "b.xyz", "1 2 3\n1 2 abc\n"))
    (tmp_path / "c.txt").write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(ValueError, match="non-numeric"):
        load_points(tmp_path / "c.txt")
    np.save(tmp_path / "d.npy", np.array([["a", "b", "c"]]))
    with pytest.raises(ValueError, match="non-numeric"):
        load_points(tmp_path / "d.npy")


def test_non_finite(tmp_path):
    text = "1 2 3\nnan 0 0\n4 5 6\n7 inf 9\n"
    with pytest.raises(ValueError, match=r"2 of 4 rows.*non-finite.*line 2"):
        load_points(write(tmp_path / "a.xyz", text))
    arr = np.ones((10, 3))
    arr[3, 1] = np.nan
    np.save(tmp_path / "a.npy", arr)
    with pytest.raises(ValueError, match="1 of 10 .*non-finite"):
        load_points(tmp_path / "a.npy")


def test_bad_num_points(tmp_path):
    path = tmp_path / "box.stl"
    trimesh.creation.box().export(path)
    for bad in (0, -5):
        with pytest.raises(ValueError, match="num_points"):
            load_points(path, num_points=bad)
    with pytest.raises(ValueError, match="num_points"):
        load_points(path, num_points=2.5)


def test_corrupt_mesh(tmp_path):
    with pytest.raises(ValueError, match="could not read mesh"):
        load_points(write(tmp_path / "bad.ply", "definitely not a ply\n"))


# --- real data ---------------------------------------------------------------------------


@pytest.fixture
def shared_data():
    if not DATA.is_dir():
        pytest.skip(f"shared data not found at {DATA} (it sits beside the checkout)")
    return DATA


def test_ycb_gltf_with_missing_textures(shared_data):
    path = shared_data / "ycb" / "005_tomato_soup_can_textured.gltf"
    out = load_points(path, num_points=5000)
    check(out, 5000)
    extents = np.ptp(out, axis=0)
    np.testing.assert_allclose(extents, [0.068, 0.102, 0.068], rtol=0.1)


@pytest.mark.parametrize(
    "name, extents",
    [
        ("vhacd_homer.off", [0.564, 1.0, 0.327]),
        ("pyvista_examples_sphere.ply", [251.0, 253.0, 254.0]),  # radius ~127 units
        ("pybullet_data_objects_mug.obj", [0.082, 0.122, 0.100]),
    ],
)
def test_misc_meshes(shared_data, name, extents):
    out = load_points(shared_data / "misc" / name, num_points=4000, seed=3)
    check(out, 4000)
    np.testing.assert_allclose(np.ptp(out, axis=0), extents, rtol=0.1)


def test_open_inventor_model_is_surface_sampled(shared_data):
    # GraspIt!'s cylinder: r 17, h 58 (MANIFEST); every sample lies on its closed surface.
    points = load_points(shared_data / "graspit" / "IROS08" / "LargeCylinder03.iv",
                         num_points=3000, seed=2)
    assert points.shape == (3000, 3)
    assert np.allclose(np.sort(np.ptp(points, axis=0)), [34, 34, 58], atol=0.5)
    again = load_points(shared_data / "graspit" / "IROS08" / "LargeCylinder03.iv",
                        num_points=3000, seed=2)
    assert np.array_equal(points, again)


# ----- model dictionaries (the JSON ``jaxfit fit --json`` writes) ---------------------------


@pytest.mark.parametrize("shape", ["plane", "sphere", "cylinder", "cone", "box"])
def test_batched_model_dicts_round_trip_and_rescale_per_element(shape):
    # The documented batch contract (Model): to_dict, from_dict and rescaled take fields
    # with a leading batch axis; the geometric methods take one primitive.
    import dataclasses
    import json

    from jaxfit.evaluation.synthetic import random_model
    from jaxfit.shapes import Model

    models = [random_model(shape, np.random.default_rng(seed)) for seed in range(3)]
    fields = {f.name: np.stack([np.asarray(getattr(m, f.name), float) for m in models])
              for f in dataclasses.fields(models[0])}
    batched = type(models[0])(**fields)
    again = Model.from_dict(json.loads(json.dumps(batched.to_dict())))
    for name, value in fields.items():
        np.testing.assert_array_equal(getattr(again, name), value)
    shift = np.array([0.5, -1.0, 2.0])
    moved = batched.rescaled(3.0, shift)
    for i, model in enumerate(models):
        single = model.rescaled(3.0, shift)
        for name in fields:
            np.testing.assert_allclose(np.asarray(getattr(moved, name))[i],
                                       getattr(single, name), rtol=1e-15, atol=1e-15)
    with pytest.raises((TypeError, ValueError)):
        batched.distance(np.zeros((4, 3)))


# --- normals kept: load_cloud -------------------------------------------------------------


def unit_rows(pts):
    return pts / np.linalg.norm(pts, axis=1, keepdims=True)


def test_unnamed_unit_columns_4_to_6_are_normals(tmp_path, pts):
    normals = unit_rows(pts[::-1])
    np.savetxt(tmp_path / "a.xyz", np.hstack([pts, normals]), fmt="%.6f")  # 6 digits
    out, found = load_cloud(tmp_path / "a.xyz")
    np.testing.assert_allclose(out, pts, atol=1e-6)
    np.testing.assert_allclose(found, normals, atol=1e-6)
    assert load_cloud(tmp_path / "a.xyz", with_normals=False)[1] is None
    np.save(tmp_path / "a.npy", np.hstack([pts, normals, pts[:, :1]]))  # 7 columns
    np.testing.assert_array_equal(load_cloud(tmp_path / "a.npy")[1], normals)
    # load_points reads the points as before
    np.testing.assert_array_equal(load_points(tmp_path / "a.npy"), pts)


def test_colours_and_intensities_are_not_taken_for_normals(tmp_path, pts):
    colours = np.random.default_rng(0).integers(0, 256, size=(len(pts), 3))
    np.savetxt(tmp_path / "rgb.xyz", np.hstack([pts, colours]))
    assert load_cloud(tmp_path / "rgb.xyz")[1] is None
    text = f"{len(pts)}\n" + "\n".join(fmt(p) + " 0 255 0 0" for p in pts)  # .pts layout
    assert load_cloud(write(tmp_path / "a.pts", text))[1] is None
    np.savetxt(tmp_path / "three.csv", pts, delimiter=",")
    assert load_cloud(tmp_path / "three.csv")[1] is None


def test_named_normal_columns_are_read_wherever_they_are(tmp_path, pts):
    normals = 2.0 * unit_rows(pts[::-1])  # not unit: named columns are taken as they are
    data = np.hstack([pts, np.ones((len(pts), 1)), normals])
    text = "x,y,z,intensity,nx,ny,nz\n" + "\n".join(fmt(r, ",") for r in data)
    np.testing.assert_array_equal(load_cloud(write(tmp_path / "a.csv", text))[1], normals)
    np.savetxt(tmp_path / "b.txt", data[:, [0, 1, 2, 4, 5, 6, 3]],
               header="x y z normal_x normal_y normal_z i")  # a commented header
    np.testing.assert_allclose(load_cloud(tmp_path / "b.txt")[1], normals, rtol=1e-15)


def test_a_ply_cloud_keeps_its_vertex_normals(tmp_path, pts):
    normals = unit_rows(pts)
    header = ["ply", "format ascii 1.0", f"element vertex {len(pts)}"]
    header += [f"property double {c}" for c in ("x", "y", "z", "nx", "ny", "nz")]
    rows = [fmt(r) for r in np.hstack([pts, normals])]
    path = write(tmp_path / "cloud.ply", "\n".join(header + ["end_header"] + rows) + "\n")
    out, found = load_cloud(path)
    np.testing.assert_array_equal(out, pts)
    np.testing.assert_array_equal(found, normals)


def test_a_mesh_gives_the_normals_of_the_faces_its_points_lie_on(tmp_path):
    path = tmp_path / "box.stl"
    trimesh.creation.box(extents=BOX_EXTENTS).export(path)
    out, normals = load_cloud(path, num_points=2000, seed=1)
    np.testing.assert_array_equal(out, load_points(path, num_points=2000, seed=1))
    # Outward axis normals, on the face each point lies on.
    axis = np.argmax(np.abs(normals), axis=1)
    np.testing.assert_allclose(np.abs(normals).max(axis=1), 1.0)
    rows = np.arange(len(out))
    np.testing.assert_allclose(np.abs(out[rows, axis]), BOX_EXTENTS[axis] / 2, atol=1e-9)
    assert (np.sign(normals[rows, axis]) == np.sign(out[rows, axis])).all()
