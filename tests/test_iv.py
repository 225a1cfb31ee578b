"""The Open Inventor reader: grammar, transforms, shapes, errors, and the real GraspIt! files."""

import math
import re
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from jaxfit.io import iv
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


def test_repeated_warnings_are_one_warning():
    # A hostile file could hold millions of stray braces or undefined USEs.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loads_iv("Cube { }\n}\n}\n} USE a USE b USE c")
    messages = sorted(str(w.message) for w in caught)
    assert messages == [
        "USE of undefined name 'a' on line 4 of <string> ignored (and 2 more)",
        "ignoring unmatched '}' on line 2 of <string> (and 2 more)",
    ]


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


# ----- hostile input: budgets, counts, nesting, fuzzing ---------------------------------------
def doubling_chain(leaf, levels):
    """``DEF L0 leaf``, then one line per level ``DEF Li Separator { USE Li-1 USE Li-1 }``:
    level i holds 2**i leaves (the 655-byte file of issue 14 took 51 s and 744 MB)."""
    lines = [f"DEF L0 {leaf}"]
    lines += [f"DEF L{i} Separator {{ USE L{i - 1} USE L{i - 1} }}" for i in range(1, levels + 1)]
    return "\n".join(lines)


def test_use_doubling_chain_is_refused_before_traversal():
    # 2**40 spheres of 642 vertices and 1280 faces. Every level is also drawn at the top:
    # the scene passes 10 million at level 12, on line 13 (1922 * (2**13 - 1) > 1e7).
    with pytest.raises(IVError, match=r"^DEF L12 Separator on line 13 of <string> takes the "
                                      r"scene past 10,000,000 vertices and faces"):
        loads_iv(doubling_chain("Sphere { }", 40))
    # Defined in a Switch that shows nothing and drawn once: level 13 itself passes it.
    text = "Switch {\n" + doubling_chain("Sphere { }", 40) + "\n}\nUSE L40"
    with pytest.raises(IVError, match=r"^USE L12 on line 15 of <string> takes DEF L13 "
                                      r"Separator \(line 15\) past 10,000,000 vertices"):
        loads_iv(text)


def test_use_chain_of_nodes_is_refused():
    # The chain of issue 14 (cubes), and one without geometry at all: 2**40 node visits.
    for leaf in ("Cube { }", "Material { }"):
        with pytest.raises(IVError, match=r"^DEF L17 Separator on line 18 .* past 500,000 "
                                          "node visits"):
            loads_iv(doubling_chain(leaf, 40) + "\nCube { }")
    # A big coordinate list repeated: each repeat is one visit (it is read once).
    points = " ".join(["1 2 3"] * 10_000)
    with pytest.raises(IVError, match="node visits"):
        loads_iv(doubling_chain(f"Coordinate3 {{ point [ {points} ] }}", 40))


def test_budgets_are_the_module_constants(monkeypatch):
    monkeypatch.setattr(iv, "MAX_GEOMETRY", 100)
    assert len(loads_iv("Cube { }").faces) == 12  # 8 vertices + 12 faces
    with pytest.raises(IVError, match="Sphere on line 1 .* past 100 vertices and faces"):
        loads_iv("Cube { } Sphere { }")  # 642 + 1280
    loads_iv("DEF C Cube { }\n" + "USE C\n" * 4)  # 5 cubes: 100
    with pytest.raises(IVError, match="USE C on line 6 .* past 100 vertices and faces"):
        loads_iv("DEF C Cube { }\n" + "USE C\n" * 5)
    # An indexed set counts its triangles and the vertices they can use.
    square = "Coordinate3 { point [0 0 0, 1 0 0, 1 1 0, 0 1 0] }\n"
    loads_iv(square + "DEF F IndexedFaceSet { coordIndex [0 1 2 3 -1] }" + " USE F" * 15)
    with pytest.raises(IVError, match="USE F on line 2 of <string> takes the scene past"):
        loads_iv(square + "DEF F IndexedFaceSet { coordIndex [0 1 2 3 -1] }" + " USE F" * 16)
    monkeypatch.setattr(iv, "MAX_NODES", 3)
    with pytest.raises(IVError, match="Cube on line 1 .* takes Separator .line 1. past 3 node"):
        loads_iv("Separator { Cube { } Cube { } Cube { } }")


@pytest.mark.parametrize(
    "shape, message",
    [
        ("FaceSet { numVertices [ 3000000000 ] }", "asks for 3000000000 coordinates"),
        ("TriangleStripSet { numVertices [ 3, 3000000000 ] }",
         "asks for 3000000000 coordinates from coordinate 3"),
        ("FaceSet { numVertices [ 1e300 ] }", "asks for 1000000"),
        ("FaceSet { numVertices [ 3, inf ] }", "non-finite count"),
        ("FaceSet { startIndex 1e300  numVertices [ 3 ] }", "startIndex 1000000"),
        ("FaceSet { startIndex -1  numVertices [ 3 ] }", "startIndex -1"),
        ("FaceSet { startIndex nan }", "'startIndex' of FaceSet .* is nan"),
        ("Switch { whichChild inf  Cube { } }", "'whichChild' of Switch .* is inf"),
    ],
)
def test_counts_are_checked_against_the_coordinates_before_allocating(shape, message):
    # Before, numVertices [3000000000] made a 24 GB index array before any range check.
    text = f"Coordinate3 {{ point [ 0 0 0, 1 0 0, 0 1 0, 1 1 0 ] }}\n{shape}"
    with pytest.raises(IVError) as error:
        loads_iv(text)
    assert re.search(message, str(error.value)) and "on line 2 of <string>" in str(error.value)


def test_deep_nesting_needs_no_recursion():
    depth = 2000  # 500 raised RecursionError before
    text = "Separator { Translation { translation 1 0 0 }\n" * depth
    mesh = loads_iv(text + "Cube { }\n" + "}\n" * depth + "Cube { }")
    np.testing.assert_allclose(mesh.bounds, [[-1, -1, -1], [depth + 1, 1, 1]])
    # Nodes nested in fields, and an unclosed one named by its line.
    fields = "IndexedFaceSet { vertexProperty " * depth + "VertexProperty { }" + " }" * depth
    assert len(loads_iv(fields + " Cube { }").faces) == 12
    with pytest.raises(IVError, match=f"Separator on line {depth} is never closed"):
        loads_iv(text)
    # Nested through USE: neither the budget's pass nor the traversal recurses.
    chain = "".join(f"DEF S{i} Separator {{ USE S{i - 1} }}\n" for i in range(1, depth))
    mesh = loads_iv(f"Switch {{ DEF S0 Cube {{ }}\n{chain} }} USE S{depth - 1}")
    assert len(mesh.faces) == 12


# Tokens a fuzzed file is made of: the grammar's punctuation, node and field names, and
# numbers that are awkward as counts or indices.
_FIELDS = ["point", "vertex", "coordIndex", "numVertices", "startIndex", "whichChild",
           "translation", "rotation", "scaleFactor", "scaleOrientation", "center", "matrix",
           "axis", "angle", "radius", "height", "bottomRadius", "width", "vertexProperty"]
_WORDS = sorted(iv._PARSED) + _FIELDS + ["Material", "Info", "DEF", "USE", "a", "b", "X",
                                         "TRUE", "NULL"]
_NUMBERS = ["0", "1", "2", "3", "4", "-1", "-2", "-3", "0.5", "1e300", "-1e300", "3000000000",
            "nan", "inf", "-inf", "1e-300", "2.5e2", "1e"]
_PUNCTUATION = ["{", "}", "[", "]", "(", ")", ",", "|", "=", '"s"', '"', "# c\n", "\n", "\\"]
_TOKENS = st.sampled_from(_WORDS + _NUMBERS + _PUNCTUATION)

# Random scenes that follow the grammar, so that fuzzing reaches the traversal and the
# geometry: nested groups, shapes with their own fields (often small numbers), DEF/USE.
_KIND_FIELDS = {
    "Coordinate3": ["point"], "VertexProperty": ["vertex"],
    "IndexedFaceSet": ["coordIndex", "vertexProperty"],
    "IndexedTriangleStripSet": ["coordIndex", "vertexProperty"],
    "FaceSet": ["numVertices", "startIndex", "vertexProperty"],
    "TriangleStripSet": ["numVertices", "startIndex", "vertexProperty"],
    "Switch": ["whichChild"], "Transform": ["translation", "rotation", "scaleFactor",
                                            "scaleOrientation", "center"],
    "Translation": ["translation"], "Rotation": ["rotation"], "Scale": ["scaleFactor"],
    "RotationXYZ": ["axis", "angle"], "MatrixTransform": ["matrix"], "ResetTransform": [],
    "Cube": ["width", "height", "depth"], "Sphere": ["radius"],
    "Cylinder": ["radius", "height"], "Cone": ["bottomRadius", "height"],
    "Separator": [], "Selection": [], "TransformSeparator": [], "Group": [], "Material": [],
}
_SMALL = st.sampled_from(["0", "1", "2", "3", "-1"] * 4 + _NUMBERS)
_NUMBER_VALUES = st.one_of(
    st.lists(_SMALL, max_size=16).map(lambda v: "[ " + ", ".join(v) + " ]"),
    st.lists(_SMALL, min_size=1, max_size=4).map(" ".join),
    st.sampled_from(["X", '"s"', "USE a", "[ ]"]),
)
_POINTS = st.lists(st.tuples(_SMALL, _SMALL, _SMALL).map(" ".join), max_size=6).map(
    lambda p: "[ " + ", ".join(p) + " ]")
_SPECIAL_VALUES = {
    "point": _POINTS, "vertex": _POINTS,
    "vertexProperty": st.one_of(_POINTS.map(lambda p: f"VertexProperty {{ vertex {p} }}"),
                                st.sampled_from(["USE a", "VertexProperty { }", "Cube { }"])),
    "axis": st.sampled_from(["X", "Y", "Z", "W", "[ ]", "USE a"]),
}


def _field_text(kind):
    names = _KIND_FIELDS[kind] * 4 + _FIELDS
    return st.sampled_from(names).flatmap(
        lambda name: _SPECIAL_VALUES.get(name, _NUMBER_VALUES).map(lambda v: f"{name} {v}"))


_DEF = st.sampled_from(["", "", "DEF a ", "DEF b "])
_LEAF_KINDS = sorted(set(_KIND_FIELDS) - iv._GROUPS)
_LEAF = st.one_of(
    st.tuples(_DEF, st.sampled_from(_LEAF_KINDS).flatmap(
        lambda kind: st.tuples(st.just(kind), st.lists(_field_text(kind), max_size=3))))
    .map(lambda t: f"{t[0]}{t[1][0]} {{ {' '.join(t[1][1])} }}"),
    st.sampled_from(["USE a", "USE b"]),
)
_SCENE = st.recursive(
    _LEAF,
    lambda children: st.tuples(
        _DEF, st.sampled_from(sorted(iv._GROUPS)).flatmap(
            lambda kind: st.tuples(st.just(kind), st.lists(_field_text(kind), max_size=1))),
        st.lists(children, max_size=5))
    .map(lambda t: f"{t[0]}{t[1][0]} {{ {' '.join(t[1][1])}\n{chr(10).join(t[2])} }}"),
    max_leaves=15,
)

_VALID = """#Inventor V2.1 ascii
DEF Root Separator {
  Transform { translation 1 2 3  rotation 0 0 1 0.5  scaleFactor 1 2 1 }
  DEF C Coordinate3 { point [ 0 0 0, 1 0 0, 1 1 0, 0 1 0, 0 0 1 ] }
  IndexedFaceSet { coordIndex [ 0, 1, 2, 3, -1, 0, 1, 4, -1 ] }
  FaceSet { startIndex 1 numVertices [ 3, -1 ] }
  Separator { MatrixTransform { matrix 1 0 0 0 0 1 0 0 0 0 1 0 5 0 0 1 }
              IndexedTriangleStripSet { vertexProperty VertexProperty {
                  vertex [ 0 0 0, 0 1 0, 1 0 0, 1 1 0 ] } coordIndex [ 0 1 2 3 -1 ] } }
  Switch { whichChild 1 Cube { } Cylinder { radius 1 height 2 } }
  TransformSeparator { RotationXYZ { axis X angle 1 } Cone { } }
  Scale { scaleFactor -1 1 1 } USE C TriangleStripSet { numVertices [ 4 ] }
}
Separator { Translation { translation 9 0 0 } USE Root Sphere { radius 2 } }
"""
_VALID_TOKENS = re.findall(r"\S+", _VALID.split("\n", 1)[1])  # no header comment


def _loads_or_iv_error(text):
    """Parse ``text``: a trimesh or an IVError naming the line, nothing else. Small budgets
    keep each example fast (and reach the budget errors often)."""
    with warnings.catch_warnings(), pytest.MonkeyPatch.context() as patch:
        warnings.simplefilter("ignore")  # stray braces, undefined USE, NaN arithmetic
        patch.setattr(iv, "MAX_GEOMETRY", 100_000, raising=False)
        patch.setattr(iv, "MAX_NODES", 10_000, raising=False)
        try:
            mesh = loads_iv(text)
        except IVError as error:
            assert "line" in str(error) or "no surface geometry" in str(error)
            return
    assert isinstance(mesh, trimesh.Trimesh) and len(mesh.faces) >= 1
    assert mesh.faces.min() >= 0 and mesh.faces.max() < len(mesh.vertices)


_FUZZ = settings(max_examples=150, deadline=None,
                 suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])


def test_the_valid_fuzz_seed_loads():
    assert len(loads_iv(_VALID).faces) > 1000


@_FUZZ
@given(st.lists(_TOKENS, max_size=60))
@example(["Separator", "{"] * 600)  # RecursionError before
def test_fuzz_token_soup(tokens):
    _loads_or_iv_error(" ".join(tokens))


@settings(_FUZZ, max_examples=100)
@given(st.lists(_SCENE, min_size=1, max_size=4), st.integers(0, 1000), st.integers(0, 40))
@example(["Cube { }"], 600, 0)  # RecursionError before
@example(["FaceSet { numVertices [ 3000000000 ] }"], 0, 0)  # MemoryError before
def test_fuzz_random_scenes(nodes, depth, doublings):
    # Inside ``depth`` Separators; then ``doublings`` lines that each double the scene.
    text = "Separator {\n" * depth + "DEF a Separator {\n" + "\n".join(nodes) + "\n}"
    text += "\nDEF a Separator { USE a USE a }" * doublings + "\n}" * depth
    _loads_or_iv_error(text)


@_FUZZ
@given(st.lists(st.tuples(st.sampled_from(["delete", "insert", "replace", "repeat"]),
                          st.integers(0, len(_VALID_TOKENS) - 1), st.integers(1, 8), _TOKENS),
                min_size=1, max_size=4))
@example([("replace", _VALID_TOKENS.index("whichChild") + 1, 1, "nan")])  # ValueError before
@example([("replace", _VALID_TOKENS.index("startIndex") + 1, 1, "inf")])  # OverflowError
def test_fuzz_mutated_valid_file(mutations):
    tokens = list(_VALID_TOKENS)
    for op, at, length, token in mutations:
        at = min(at, len(tokens))
        if op == "delete":
            del tokens[at:at + length]
        elif op == "insert":
            tokens[at:at] = [token] * length
        elif op == "replace":
            tokens[at:at + 1] = [token]
        else:  # repeat a span, as a careless edit or a USE-happy generator would
            tokens[at:at] = tokens[at:at + length] * 3
    _loads_or_iv_error(" ".join(tokens))


@_FUZZ
@given(st.lists(st.tuples(st.integers(0, len(_VALID) - 1), st.binary(max_size=4)),
                min_size=1, max_size=6))
@example([(_VALID.index("whichChild") + 11, b"inf ")])  # OverflowError before
def test_fuzz_bytes_of_a_file(edits):
    # Byte-level damage through load_iv (the header check and the latin-1 decoding).
    data = bytearray(_VALID.encode())
    for at, new in edits:
        data[at:at + len(new)] = new
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "fuzz.iv"
        path.write_bytes(bytes(data))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                mesh = load_iv(path)
            except IVError:
                return
    assert len(mesh.faces) >= 1
