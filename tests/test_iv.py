"""The Open Inventor reader: grammar, transforms, shapes, errors, and the real GraspIt! files."""

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from jaxfit.io.iv import IVError, load_iv, loads_iv

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
HEADER = "#Inventor V2.1 ascii\n"

REAL_FILES = [
    "graspit/mug.iv",
    "graspit/phone.iv",
    "graspit/arizonaObject_revised.iv",
    "graspit/IROS08/LargeCylinder03.iv",
    "graspit/IROS08/ThickBox05.iv",
    "graspit/IROS08/largeCone10.iv",
    "graspit/primitives/mug.iv",
    "graspit/primitives/phone.iv",
    "misc/inventor_mentor_duck.iv",
]


def write(tmp_path, body, name="scene.iv"):
    path = tmp_path / name
    path.write_text(HEADER + body)
    return path


def real(name):
    path = DATA / name
    if not path.is_file():
        pytest.skip(f"shared data not found at {path} (it sits beside the checkout)")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # arizonaObject_revised.iv has a stray '}'
        return load_iv(path)


def extents(mesh):
    return np.ptp(np.asarray(mesh.vertices), axis=0)


# ----- hand-written scenes -----------------------------------------------------------------
def test_separator_transform_cube_and_face_set(tmp_path):
    path = write(tmp_path, """
        Separator {            # the transform stays inside
            Transform { translation 10 0 0  scaleFactor 2 1 1 }
            Cube { width 1 height 2 depth 3 }
        }
        Coordinate3 { point [ 0 0 0, 1 0 0, 1 1 0, 0 1 0 ] }
        IndexedFaceSet { coordIndex [ 0, 1, 2, 3, -1 ] }
    """)
    mesh = load_iv(path)
    assert mesh.vertices.dtype == np.float64 and mesh.faces.shape[1] == 3
    assert len(mesh.faces) == 12 + 2  # a cube and a fan-triangulated square
    verts = np.asarray(mesh.vertices)
    cube, square = verts[:8], verts[8:]
    np.testing.assert_allclose(cube.min(axis=0), [9, -1, -1.5])
    np.testing.assert_allclose(cube.max(axis=0), [11, 1, 1.5])
    np.testing.assert_allclose(np.sort(square, axis=0), np.sort(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], axis=0))
    np.testing.assert_allclose(mesh.bounds, [[0, -1, -1.5], [11, 1.0, 1.5]])
    assert mesh.area == pytest.approx(2 * (2 * 2 + 2 * 3 + 2 * 3) + 1)


def test_transforms_right_multiply_in_file_order():
    # Translation then Rotation: the cube is rotated in place, then moved.
    moved_after = loads_iv("""Translation { translation 10 0 0 }
        Rotation { rotation 0 0 1 1.5707963267948966 } Cube { width 4 height 2 depth 2 }""")
    np.testing.assert_allclose(moved_after.bounds, [[9, -2, -1], [11, 2, 1]], atol=1e-12)
    # Rotation then Translation: the translation is rotated too.
    rotated_after = loads_iv("""Rotation { rotation 0 0 1 1.5707963267948966 }
        Translation { translation 10 0 0 } Cube { width 4 height 2 depth 2 }""")
    np.testing.assert_allclose(rotated_after.bounds, [[-1, 8, -1], [1, 12, 1]], atol=1e-12)


def test_transform_node_order_and_center():
    # Transform applies scale, then rotation, then translation.
    mesh = loads_iv("""Transform { translation 1 0 0  rotation 0 0 1 1.5707963267948966
                                   scaleFactor 3 1 1 }
                       Cube { width 2 height 2 depth 2 }""")
    np.testing.assert_allclose(mesh.bounds, [[0, -3, -1], [2, 3, 1]], atol=1e-12)
    # A rotation about a centre keeps the centre fixed.
    mesh = loads_iv("""Transform { rotation 0 0 1 3.141592653589793  center 5 0 0 }
                       Cube { width 2 height 2 depth 2 }""")
    np.testing.assert_allclose(mesh.bounds, [[9, -1, -1], [11, 1, 1]], atol=1e-12)
    # scaleOrientation: scale 2 along the direction (1, 1, 0)/sqrt(2).
    mesh = loads_iv("""Transform { scaleFactor 2 1 1  scaleOrientation 0 0 1 0.7853981633974483 }
        Coordinate3 { point [ 1 1 0, 1 -1 0, 0 0 1 ] } IndexedFaceSet { coordIndex [0, 1, 2] }""")
    np.testing.assert_allclose(mesh.vertices, [[2, 2, 0], [1, -1, 0], [0, 0, 1]], atol=1e-12)


def test_matrix_transform_uses_row_vectors():
    # Translation in the last row, as Inventor writes it; scale 2 in x.
    mesh = loads_iv("""MatrixTransform { matrix 2 0 0 0  0 1 0 0  0 0 1 0  5 6 7 1 }
                       Cube { width 1 height 1 depth 1 }""")
    np.testing.assert_allclose(mesh.bounds, [[4, 5.5, 6.5], [6, 6.5, 7.5]])


def test_rotation_xyz_scale_and_group_without_separation():
    mesh = loads_iv("""Group { RotationXYZ { axis X angle 1.5707963267948966 } }
                       Scale { scaleFactor 1 1 3 }
                       Cylinder { radius 1 height 2 }""")
    # The Group leaks its rotation. The later Scale acts first, in the cylinder's frame:
    # its z radius becomes 3; then the rotation turns the axis (+Y) to +Z and z to -Y.
    np.testing.assert_allclose(mesh.bounds, [[-1, -3, -1], [1, 3, 1]], atol=1e-9)


def test_transform_separator_keeps_coordinates_but_not_the_matrix():
    mesh = loads_iv("""TransformSeparator {
            Translation { translation 100 0 0 }
            Coordinate3 { point [ 0 0 0, 1 0 0, 0 1 0 ] }
        }
        IndexedFaceSet { coordIndex [ 0, 1, 2, -1 ] }""")
    np.testing.assert_allclose(mesh.bounds, [[0, 0, 0], [1, 1, 0]])


def test_def_use_and_skipped_nodes():
    mesh = loads_iv("""
        DEF Info1 Info { string "braces { inside } a string" }
        Material { diffuseColor [ 1 0 0, 0 1 0 ] }
        Texture2 { image 2 1 3 0xff0000 0x00ff00 }
        SomeExtension { fields [ SFNode child ] child Nested { deeper { 1 2 3 } } }
        ShapeHints { vertexOrdering COUNTERCLOCKWISE shapeType SOLID }
        DEF Unit Cube { width 1 height 1 depth 1 }
        Translation { translation 3 0 0 }
        USE Unit
    """)
    assert len(mesh.faces) == 24
    np.testing.assert_allclose(mesh.bounds, [[-0.5, -0.5, -0.5], [3.5, 0.5, 0.5]])


def test_primitive_defaults_and_axes():
    cube = loads_iv("Cube { }")
    np.testing.assert_allclose(extents(cube), [2, 2, 2])
    sphere = loads_iv("Sphere { }")
    np.testing.assert_allclose(np.linalg.norm(sphere.vertices, axis=1), 1.0)
    cylinder = loads_iv("Cylinder { }")
    np.testing.assert_allclose(extents(cylinder), [2, 2, 2])
    cone = loads_iv("Cone { bottomRadius 3 height 4 }")
    verts = np.asarray(cone.vertices)
    np.testing.assert_allclose(cone.bounds, [[-3, -2, -3], [3, 2, 3]], atol=1e-12)
    # The apex is at +height/2 on the Y axis, the base circle at -height/2.
    np.testing.assert_allclose(verts[np.argmax(verts[:, 1])], [0, 2, 0], atol=1e-12)
    base = verts[np.isclose(verts[:, 1], -2) & (np.linalg.norm(verts[:, [0, 2]], axis=1) > 1)]
    np.testing.assert_allclose(np.linalg.norm(base[:, [0, 2]], axis=1), 3)
    for mesh in (cube, sphere, cylinder, cone):
        assert mesh.is_watertight and mesh.volume > 0  # closed, normals outward


def test_triangle_strips_keep_one_winding():
    mesh = loads_iv("""IndexedTriangleStripSet {
        vertexProperty VertexProperty { vertex [ 0 0 0, 0 1 0, 1 0 0, 1 1 0, 2 0 0, 2 1 0 ] }
        coordIndex [ 0, 1, 2, 3, 4, 5, -1, 0, 0, 1, -1 ] }""")
    assert len(mesh.faces) == 4  # the second strip is degenerate and dropped
    normals = np.asarray(mesh.face_normals)
    np.testing.assert_allclose(normals, np.tile(normals[0], (4, 1)))
    assert mesh.area == pytest.approx(2.0)


def test_face_set_and_strip_set_with_num_vertices():
    faces = loads_iv("""Coordinate3 { point [ 0 0 0, 1 0 0, 1 1 0, 0 1 0, 5 5 5, 6 5 5, 5 6 5 ] }
                        FaceSet { numVertices [ 4, 3 ] }""")
    assert len(faces.faces) == 3
    strips = loads_iv("""Coordinate3 { point [ 0 0 0, 0 1 0, 1 0 0, 1 1 0 ] }
                         TriangleStripSet { }""")
    assert len(strips.faces) == 2 and strips.area == pytest.approx(1.0)


def test_switch_selects_its_child():
    mesh = loads_iv("""Switch { whichChild 1  Cube { width 1 height 1 depth 1 }
                                Sphere { radius 2 } }""")
    assert extents(mesh).max() > 3
    with pytest.raises(IVError, match="no surface"):
        loads_iv("Switch { Cube { } }")  # whichChild -1: no child


# ----- errors -------------------------------------------------------------------------------
def test_missing_file(tmp_path):
    with pytest.raises(IVError, match="not found"):
        load_iv(tmp_path / "nope.iv")
    assert issubclass(IVError, ValueError)


def test_not_an_inventor_file(tmp_path):
    path = tmp_path / "scene.iv"
    path.write_text("solid cube\nfacet normal 0 0 1\n")
    with pytest.raises(IVError, match="not an Open Inventor file"):
        load_iv(path)
    path.write_bytes(b"#Inventor V2.1 binary\n\x00\x01")
    with pytest.raises(IVError, match="binary"):
        load_iv(path)


def test_unbalanced_braces(tmp_path):
    with pytest.raises(IVError, match="unbalanced braces.*Material on line 3"):
        load_iv(write(tmp_path, "Separator {\n  Material { diffuseColor 1 0 0 \n Cube { }\n"))
    with pytest.raises(IVError, match="unclosed"):
        loads_iv("Coordinate3 { point [ 0 0 0, 1 0 0 }")


def test_stray_closing_brace_warns_but_loads(tmp_path):
    with pytest.warns(UserWarning, match="unmatched"):
        mesh = load_iv(write(tmp_path, "Separator { Cube { } }\n}\n"))
    assert len(mesh.faces) == 12


def test_no_geometry(tmp_path):
    with pytest.raises(IVError, match="no surface geometry"):
        load_iv(write(tmp_path, "Separator { Material { diffuseColor 1 0 0 } }"))


@pytest.mark.parametrize(
    "body, message",
    [
        ("Coordinate3 { point [ 0 0 0 ] } IndexedFaceSet { coordIndex [ 0, 1, 2 ] }",
         "only 1 are defined"),
        ("IndexedFaceSet { coordIndex [ 0, 1, 2 ] }", "only 0 are defined"),
        ("Coordinate3 { point [ 0 0 0, 1 0 ] }", "multiple of 3"),
        ("Translation { translation 1 2 }  Cube { }", "expected 3"),
        ("RotationXYZ { axis W angle 1 }  Cube { }", "X, Y or Z"),
        ('Cube { width "wide" }', "non-numeric"),
        ("Cube { width 1 } ]", "expected a node"),
        ('Info { string "never closed }', "unterminated string"),
    ],
)
def test_malformed_content(body, message):
    with pytest.raises(IVError, match=message):
        loads_iv(body)


# ----- the real files -----------------------------------------------------------------------
@pytest.mark.parametrize("name", REAL_FILES)
def test_real_files_load(name):
    mesh = real(name)
    assert len(mesh.faces) > 0 and len(mesh.vertices) >= 3
    assert np.all(np.isfinite(mesh.vertices))
    assert mesh.faces.max() < len(mesh.vertices)
    assert mesh.area > 0


def test_large_cylinder_ground_truth():
    # Cylinder r17 h58; the file rotates it 90 deg about X, so its axis lies along Z.
    mesh = real("graspit/IROS08/LargeCylinder03.iv")
    np.testing.assert_allclose(np.sort(extents(mesh)), [34, 34, 58], atol=1e-6)
    np.testing.assert_allclose(extents(mesh), [34, 34, 58], atol=1e-6)
    assert mesh.volume == pytest.approx(math.pi * 17**2 * 58, rel=0.01)


def test_thick_box_ground_truth():
    mesh = real("graspit/IROS08/ThickBox05.iv")
    np.testing.assert_allclose(np.sort(extents(mesh)), [22, 39, 39], atol=0.01)  # angle 1.5707
    assert mesh.volume == pytest.approx(39 * 39 * 22)


def test_large_cone_ground_truth():
    # Cone bottomRadius 20 h52 along +Y, rotated -90 deg about Z: the axis runs along +X.
    mesh = real("graspit/IROS08/largeCone10.iv")
    np.testing.assert_allclose(extents(mesh), [52, 40, 40], atol=0.01)  # angle -1.5707
    verts = np.asarray(mesh.vertices)
    np.testing.assert_allclose(verts[np.argmax(verts[:, 0])], [26, 0, 0], atol=0.01)
    assert mesh.volume == pytest.approx(math.pi * 20**2 * 52 / 3, rel=0.01)


def test_primitive_mug_ground_truth():
    # Body: cylinder r50 h100, axis Y, centred (3, -10, 0); handle: r25 h18, axis Z,
    # centred (-52, -10, 0).
    mesh = real("graspit/primitives/mug.iv")
    np.testing.assert_allclose(mesh.bounds, [[-77, -60, -50], [53, 40, 50]], atol=1e-3)
    verts = np.asarray(mesh.vertices)
    rim = np.isclose(verts[:, 1], -60) | np.isclose(verts[:, 1], 40)
    radial = np.linalg.norm(verts[rim][:, [0, 2]] - [3, 0], axis=1)
    assert np.sum(np.isclose(radial, 50)) >= 64  # both rims of the body
    handle = np.isclose(np.abs(verts[:, 2]), 9)  # the handle's caps at z = +-9
    np.testing.assert_allclose(verts[handle].mean(axis=0), [-52, -10, 0], atol=1e-6)


def test_arizona_object_ground_truth():
    # Base cylinder r90 h5, post r17.2 h89.79, sphere r34.4 on top; Z up after the file's
    # RotationXYZ X 90 deg.
    mesh = real("graspit/arizonaObject_revised.iv")
    lo, hi = mesh.bounds
    np.testing.assert_allclose(lo, [-90, -90, -2.5], atol=1e-3)
    np.testing.assert_allclose(hi[:2], [90, 90], atol=1e-3)
    assert hi[2] == pytest.approx(89.79 + 34.4, abs=0.5)  # icosphere: not quite the pole


def test_triangle_strip_mug_is_closed():
    # graspit/mug.iv: IndexedTriangleStripSet with VertexProperty, under a Translation
    # and a 180 deg RotationXYZ about Z; same size as its primitive decomposition.
    mesh = real("graspit/mug.iv")
    assert len(mesh.faces) > 3000
    assert mesh.is_watertight and mesh.volume > 0
    np.testing.assert_allclose(extents(mesh), [133.4, 100.0, 104.7], atol=0.5)
