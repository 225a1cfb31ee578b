"""Reader for Open Inventor ASCII scene files (``.iv``), the format of GraspIt! object models.

The thesis's PSDA read GraspIt! models (THESIS.md section 5); ``load_iv`` turns one into a
single triangle mesh in world coordinates, which ``trimesh`` can then sample.

Supported, the subset those models and the Inventor Mentor examples use:

- Grammar: ``Name { fields... children... }``, ``DEF name Node {...}``, ``USE name``,
  ``#`` comments, quoted strings, multi-value fields in ``[ ... ]`` (commas optional).
- Groups: ``Separator`` and ``Selection`` save and restore the matrix and coordinates,
  ``TransformSeparator`` only the matrix (as in Inventor), ``Group`` nothing; ``Switch``
  follows ``whichChild``.
- Coordinates: ``Coordinate3 { point }`` and ``VertexProperty { vertex }``, either in the
  graph or as a shape's ``vertexProperty`` field.
- Surfaces: ``IndexedFaceSet`` and ``FaceSet`` (polygons, fan-triangulated),
  ``IndexedTriangleStripSet`` and ``TriangleStripSet``; ``Cube``, ``Sphere``,
  ``Cylinder`` and ``Cone`` as closed meshes (Cylinder and Cone along local +Y, centred,
  the cone's apex at +height/2; their ``parts`` field is ignored).
- Transforms: ``Transform``, ``Translation``, ``Rotation``, ``RotationXYZ``, ``Scale``,
  ``MatrixTransform``, ``ResetTransform``. Each one right-multiplies the current matrix,
  so it acts on the geometry that follows before the transforms above it.

Every other node (Material, ShapeHints, Normal, Texture2, Info, lines, points, ...) is
skipped whole, braces and all. Deliberately free of jax, like ``jaxfit.io``.
"""

from __future__ import annotations

import dataclasses
import os
import re
import warnings
from pathlib import Path

import numpy as np
import trimesh

__all__ = ["IVError", "load_iv", "loads_iv"]

#: Segments around the circle of Cylinder and Cone meshes; a multiple of 4, so the
#: mesh reaches the full radius along the local x and z axes.
SECTIONS = 64
#: Icosphere subdivisions for Sphere (642 vertices, near-uniform triangles for sampling).
SPHERE_SUBDIVISIONS = 3

_HEADERS = (b"#Inventor V", b"#VRML V1.0 ascii")

# Whitespace and commas separate tokens (commas are optional in Inventor lists); a comment
# runs to the end of the line; strings are one token, so braces inside them do not count.
_TOKEN = re.compile(
    r"""(?:[\s,]+|\#[^\n]*)
      | ("(?:[^"\\]|\\.)*" | [{}\[\]()|=] | [^\s,{}\[\]()|="\#]+)
      | (.)""",
    re.VERBOSE | re.DOTALL,
)
_NUMBER = re.compile(r"[+-]?(?:\d|\.\d)")

# Nodes whose bodies are parsed; every other node's body is skipped by brace matching.
_SEPARATORS = {"Separator", "Selection", "TransformSeparator"}
_GROUPS = _SEPARATORS | {"Group", "Switch"}
_TRANSFORMS = {"Transform", "Translation", "Rotation", "RotationXYZ", "Scale",
               "MatrixTransform", "ResetTransform"}
_COORDINATES = {"Coordinate3", "VertexProperty"}
_MESH_SHAPES = {"IndexedFaceSet", "IndexedTriangleStripSet", "FaceSet", "TriangleStripSet"}
_SOLIDS = {"Cube", "Sphere", "Cylinder", "Cone"}
_PARSED = _GROUPS | _TRANSFORMS | _COORDINATES | _MESH_SHAPES | _SOLIDS

# Inventor's Cylinder and Cone run along local +Y; trimesh builds them along +Z.
# Columns are the images of x, y, z: z -> y, y -> -z (a proper rotation).
_Z_TO_Y = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


class IVError(ValueError):
    """An Inventor file is missing, not Inventor ASCII, malformed, or holds no surface."""


@dataclasses.dataclass(eq=False)
class _Node:
    """A parsed node: ``fields`` maps names to a token list or a node; ``parsed`` is False
    for skipped node types."""

    kind: str
    line: int
    fields: dict = dataclasses.field(default_factory=dict)
    children: list = dataclasses.field(default_factory=list)
    parsed: bool = True


@dataclasses.dataclass
class _State:
    """Traversal state: ``matrix`` (4, 4) maps local to world coordinates for column
    vectors; ``coords`` (K, 3) are the current local coordinates."""

    matrix: np.ndarray
    coords: np.ndarray


# ----- public API -------------------------------------------------------------------------
def load_iv(path) -> trimesh.Trimesh:
    """Read an Open Inventor ASCII file as one triangle mesh in world coordinates.

    Parameters
    ----------
    path : str or os.PathLike
        A ``#Inventor V2.1 ascii`` (or V1.0, or ``#VRML V1.0 ascii``) file.

    Returns
    -------
    mesh : trimesh.Trimesh
        All surfaces of the scene, transformed to world coordinates and concatenated:
        vertices (V, 3) float64 and triangles (F, 3) with F >= 1. Not processed (no
        vertex merging), but triangles that repeat a vertex index are dropped.

    Raises
    ------
    IVError
        (a ``ValueError``) if the file is missing, is not Inventor ASCII, is malformed
        (unclosed braces or brackets, bad field values, indices out of range) or holds
        no surface geometry.
    """
    path = Path(os.fspath(path))
    if not path.is_file():
        raise IVError(f"file not found: {path}" if not path.exists() else f"not a file: {path}")
    data = path.read_bytes()
    header = data.split(b"\n", 1)[0].strip()
    if not header.startswith(_HEADERS):
        raise IVError(f"not an Open Inventor file (no '#Inventor V...' header): {path}")
    if b"binary" in header:
        raise IVError(f"binary Inventor files are not supported, only ASCII: {path}")
    # latin-1 never fails; the grammar is ASCII and bytes >= 128 only occur in strings.
    return loads_iv(data.decode("latin-1"), source=str(path))


def loads_iv(text: str, *, source: str = "<string>") -> trimesh.Trimesh:
    """``load_iv`` for the text of a file (the header line is not checked here).

    ``source`` names the text in error messages.
    """
    nodes = _Parser(text, source).parse()
    vertices, faces = [], []
    state = _State(np.eye(4), np.empty((0, 3)))
    for node in nodes:
        _traverse(node, state, vertices, faces, source)
    if not faces:
        raise IVError(f"no surface geometry (no faces) found in {source}")
    offsets = np.cumsum([0] + [len(v) for v in vertices[:-1]])
    all_faces = np.concatenate([f + o for f, o in zip(faces, offsets, strict=True)])
    return trimesh.Trimesh(np.concatenate(vertices), all_faces, process=False)


# ----- tokenizer and parser ---------------------------------------------------------------
def _tokenize(text: str, source: str) -> tuple[list[str], list[int]]:
    """Tokens and their character offsets (for line numbers in errors)."""
    tokens, offsets = [], []
    for match in _TOKEN.finditer(text):
        token, bad = match.group(1), match.group(2)
        if bad is not None:
            line = text.count("\n", 0, match.start()) + 1
            what = "unterminated string" if bad == '"' else f"unexpected character {bad!r}"
            raise IVError(f"{what} on line {line} of {source}")
        if token is not None:
            tokens.append(token)
            offsets.append(match.start())
    return tokens, offsets


def _is_word(token: str | None) -> bool:
    return token is not None and token not in "{}[]()|=" and not token.startswith('"')


class _Parser:
    """Recursive-descent parser of the generic Inventor grammar.

    Without a schema, a field's value is read by its form: ``[...]``, ``(...)``, a node,
    a run of numbers and strings, or one word (an enum, TRUE/FALSE, NULL).
    """

    def __init__(self, text: str, source: str):
        self.text, self.source = text, source
        self.tokens, self.offsets = _tokenize(text, source)
        self.pos = 0
        self.defs: dict[str, _Node] = {}

    def parse(self) -> list[_Node]:
        nodes = []
        while self.peek() is not None:
            if self.peek() == "}":
                # GraspIt!'s arizonaObject_revised.iv ends with one '}' too many; Inventor
                # readers stop at it, so we warn and go on rather than reject the model.
                warnings.warn(f"ignoring unmatched '}}' on line {self.line()} of {self.source}",
                              stacklevel=4)
                self.pos += 1
                continue
            node = self.node()
            if node is not None:
                nodes.append(node)
        return nodes

    # -- helpers --
    def peek(self, ahead: int = 0) -> str | None:
        i = self.pos + ahead
        return self.tokens[i] if i < len(self.tokens) else None

    def line(self, pos: int | None = None) -> int:
        pos = min(self.pos if pos is None else pos, len(self.tokens) - 1)
        return self.text.count("\n", 0, self.offsets[pos]) + 1 if pos >= 0 else 1

    def take(self, what: str) -> str:
        token = self.peek()
        if token is None:
            raise IVError(f"unexpected end of file in {self.source}: expected {what}")
        self.pos += 1
        return token

    def error(self, message: str) -> IVError:
        return IVError(f"{message} on line {self.line()} of {self.source}")

    # -- grammar --
    def node(self) -> _Node | None:
        """``[DEF name] Kind { body }`` or ``USE name``; None for a USE of an unknown name."""
        token = self.take("a node")
        if token == "USE":
            name = self.take("a name after USE")
            if name not in self.defs:
                warnings.warn(f"USE of undefined name {name!r} on line {self.line(self.pos - 1)} "
                              f"of {self.source} ignored", stacklevel=5)
            return self.defs.get(name)
        name = None
        if token == "DEF":
            name, token = self.take("a name after DEF"), self.take("a node after DEF")
        if not _is_word(token) or self.peek() != "{":
            self.pos -= 1
            raise self.error(f"expected a node name followed by '{{', got {token!r}")
        start = self.pos
        self.pos += 1
        node = _Node(token, self.line(start))
        if token in _PARSED:
            self.body(node, start)
        else:
            self.skip_body(token, start)
            node.parsed = False
        if name is not None:
            self.defs[name] = node
        return node

    def body(self, node: _Node, start: int) -> None:
        while True:
            token = self.peek()
            if token is None:
                raise IVError(f"unbalanced braces in {self.source}: the '{{' of {node.kind} "
                              f"on line {self.line(start)} is never closed")
            if token == "}":
                self.pos += 1
                return
            if token in ("DEF", "USE") or self.peek(1) == "{":
                child = self.node()
                if child is not None:
                    node.children.append(child)
            elif _is_word(token):
                self.pos += 1
                node.fields[token] = self.value(token)
            else:
                raise self.error(f"unexpected {token!r} in {node.kind}")

    def skip_body(self, kind: str, start: int) -> None:
        depth = 1
        while depth:
            token = self.peek()
            if token is None:
                raise IVError(f"unbalanced braces in {self.source}: the '{{' of {kind} "
                              f"on line {self.line(start)} is never closed")
            depth += (token == "{") - (token == "}")
            self.pos += 1

    def value(self, field: str):
        token = self.peek()
        if token in ("[", "("):
            close, start = "]" if token == "[" else ")", self.pos
            self.pos += 1
            values = []
            while (t := self.peek()) != close:
                if t is None or t in "{}[]":
                    raise IVError(f"unclosed '{token}' in field {field!r} on line "
                                  f"{self.line(start)} of {self.source}")
                values.append(t)
                self.pos += 1
            self.pos += 1
            return values
        if token in ("DEF", "USE") or (_is_word(token) and self.peek(1) == "{"):
            return self.node()
        if token is not None and (_NUMBER.match(token) or token.startswith('"')):
            values = []
            while (t := self.peek()) is not None and (_NUMBER.match(t) or t.startswith('"')):
                values.append(t)
                self.pos += 1
            return values
        if _is_word(token):
            self.pos += 1
            return [token]
        raise self.error(f"missing value for field {field!r}")


# ----- field access -----------------------------------------------------------------------
def _numbers(node: _Node, field: str, default, source: str, count: int | None = None):
    """Field as a float64 array (default if absent); ``count`` numbers if given."""
    value = node.fields.get(field)
    if value is None:
        return np.asarray(default, dtype=np.float64)
    if isinstance(value, _Node):
        raise IVError(f"field {field!r} of {node.kind} on line {node.line} of {source} "
                      "holds a node, expected numbers")
    try:
        arr = np.array(value, dtype=np.float64)
    except ValueError:
        raise IVError(f"non-numeric value in field {field!r} of {node.kind} on line "
                      f"{node.line} of {source}") from None
    if count is not None and arr.size != count:
        raise IVError(f"field {field!r} of {node.kind} on line {node.line} of {source} has "
                      f"{arr.size} numbers, expected {count}")
    return arr


def _vec3s(node: _Node, field: str, source: str) -> np.ndarray:
    """Multi-value SFVec3f field as (K, 3)."""
    arr = _numbers(node, field, [], source)
    if arr.size % 3:
        raise IVError(f"field {field!r} of {node.kind} on line {node.line} of {source} has "
                      f"{arr.size} numbers, not a multiple of 3")
    return arr.reshape(-1, 3)


def _indices(node: _Node, field: str, source: str) -> np.ndarray:
    arr = _numbers(node, field, [], source)
    if np.any(arr != np.round(arr)):
        raise IVError(f"non-integer index in {field!r} of {node.kind} on line {node.line} "
                      f"of {source}")
    return arr.astype(np.int64)


# ----- transforms ---------------------------------------------------------------------------
def _translate(t) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def _rotate(rotation) -> np.ndarray:
    """4x4 from an SFRotation (axis x y z, angle in radians); a zero axis is no rotation."""
    axis, angle = np.asarray(rotation[:3], dtype=np.float64), float(rotation[3])
    if not np.linalg.norm(axis) > 0:
        return np.eye(4)
    return trimesh.transformations.rotation_matrix(angle, axis / np.linalg.norm(axis))


def _scale(s) -> np.ndarray:
    return np.diag([*np.asarray(s, dtype=np.float64), 1.0])


def _transform_matrix(node: _Node, source: str) -> np.ndarray | None:
    """The node's local 4x4 (column vectors), or None for ResetTransform."""
    kind = node.kind
    if kind == "Translation":
        return _translate(_numbers(node, "translation", [0, 0, 0], source, 3))
    if kind == "Rotation":
        return _rotate(_numbers(node, "rotation", [0, 0, 1, 0], source, 4))
    if kind == "Scale":
        return _scale(_numbers(node, "scaleFactor", [1, 1, 1], source, 3))
    if kind == "RotationXYZ":
        axis = node.fields.get("axis", ["X"])
        names = {"X": [1, 0, 0], "Y": [0, 1, 0], "Z": [0, 0, 1]}
        if isinstance(axis, _Node) or len(axis) != 1 or axis[0] not in names:
            raise IVError(f"RotationXYZ axis must be X, Y or Z (line {node.line} of {source})")
        angle = _numbers(node, "angle", [0.0], source, 1)[0]
        return _rotate([*names[axis[0]], angle])
    if kind == "MatrixTransform":
        # Written row-major for row vectors (p_row @ M): the column-vector form is M.T.
        return _numbers(node, "matrix", np.eye(4).ravel(), source, 16).reshape(4, 4).T
    if kind == "Transform":
        # Inventor's order: T C R SO S SO^-1 C^-1 (column vectors).
        t = _numbers(node, "translation", [0, 0, 0], source, 3)
        r = _numbers(node, "rotation", [0, 0, 1, 0], source, 4)
        s = _numbers(node, "scaleFactor", [1, 1, 1], source, 3)
        so = _rotate(_numbers(node, "scaleOrientation", [0, 0, 1, 0], source, 4))
        c = _numbers(node, "center", [0, 0, 0], source, 3)
        return _translate(t + c) @ _rotate(r) @ so @ _scale(s) @ so.T @ _translate(-c)
    return None  # ResetTransform


# ----- geometry -----------------------------------------------------------------------------
def _runs(index: np.ndarray):
    """For an index list with -1 separators: a mask of real entries, each entry's position
    within its run, and the position where its run starts."""
    n = len(index)
    real = index >= 0
    last_sep = np.maximum.accumulate(np.where(real, -1, np.arange(n))) if n else index
    start = last_sep + 1
    return real, np.arange(n) - start, start


def _fan_triangles(index: np.ndarray) -> np.ndarray:
    """(T, 3) triangles fanning each polygon of ``index`` (-1 separated) from its first
    vertex."""
    real, within, start = _runs(index)
    j = np.flatnonzero(real & (within >= 2))
    return np.stack([index[start[j]], index[j - 1], index[j]], axis=1).reshape(-1, 3)


def _strip_triangles(index: np.ndarray) -> np.ndarray:
    """(T, 3) triangles of the strips of ``index`` (-1 separated); every second triangle
    is flipped so that all keep the strip's winding."""
    real, within, _ = _runs(index)
    j = np.flatnonzero(real & (within >= 2))
    a, b, c = index[j - 2], index[j - 1], index[j]
    odd = (within[j] % 2) == 1
    return np.stack([np.where(odd, b, a), np.where(odd, a, b), c], axis=1).reshape(-1, 3)


def _counts_to_index(counts: np.ndarray, available: int, start: int) -> np.ndarray:
    """-1-separated consecutive indices for FaceSet/TriangleStripSet ``numVertices``; a
    count of -1 takes all remaining coordinates."""
    pieces, at = [], start
    for count in counts.astype(np.int64):
        count = available - at if count < 0 else count
        pieces += [np.arange(at, at + count), [-1]]
        at += count
    return np.concatenate(pieces).astype(np.int64) if pieces else np.empty(0, np.int64)


def _shape_coords(node: _Node, state: _State, source: str) -> np.ndarray:
    prop = node.fields.get("vertexProperty")
    if isinstance(prop, _Node) and "vertex" in prop.fields:
        return _vec3s(prop, "vertex", source)
    return state.coords


def _mesh_shape(node: _Node, state: _State, source: str):
    """Local vertices (K, 3) and triangles (T, 3) of a face or strip set."""
    coords = _shape_coords(node, state, source)
    strips = "Strip" in node.kind
    if node.kind.startswith("Indexed"):
        index = _indices(node, "coordIndex", source)
    else:
        start = int(_numbers(node, "startIndex", [0], source, 1)[0])
        counts = _numbers(node, "numVertices", [-1], source)
        index = _counts_to_index(counts, len(coords), start)
    if np.any(index < -1):
        raise IVError(f"negative index other than -1 in {node.kind} on line {node.line} "
                      f"of {source}")
    if index.size and index.max() >= len(coords):
        raise IVError(f"{node.kind} on line {node.line} of {source} uses coordinate "
                      f"{index.max()} but only {len(coords)} are defined")
    faces = _strip_triangles(index) if strips else _fan_triangles(index)
    return coords, faces


def _solid(node: _Node, source: str) -> trimesh.Trimesh:
    """Closed mesh of a Cube, Sphere, Cylinder or Cone in its local frame."""
    def number(field, default):
        return float(_numbers(node, field, [default], source, 1)[0])

    if node.kind == "Cube":
        extents = [number("width", 2.0), number("height", 2.0), number("depth", 2.0)]
        return trimesh.creation.box(extents=extents)
    if node.kind == "Sphere":
        return trimesh.creation.icosphere(SPHERE_SUBDIVISIONS, radius=number("radius", 1.0))
    to_y = np.eye(4)
    to_y[:3, :3] = _Z_TO_Y
    if node.kind == "Cylinder":
        mesh = trimesh.creation.cylinder(number("radius", 1.0), number("height", 2.0),
                                         sections=SECTIONS)
        return mesh.apply_transform(to_y)
    # trimesh's cone has its base at z = 0 and apex at z = height: centre it first.
    height = number("height", 2.0)
    mesh = trimesh.creation.cone(number("bottomRadius", 1.0), height, sections=SECTIONS)
    return mesh.apply_transform(to_y @ _translate([0.0, 0.0, -0.5 * height]))


def _emit(vertices, faces, matrix, out_vertices, out_faces) -> None:
    """Transform local vertices (K, 3) to world and keep the non-degenerate triangles."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
                  & (faces[:, 0] != faces[:, 2])]
    if not len(faces):
        return
    used, faces = np.unique(faces, return_inverse=True)
    faces = faces.reshape(-1, 3)
    local = np.asarray(vertices, dtype=np.float64)[used]
    world = np.c_[local, np.ones(len(local))] @ matrix.T
    world = world[:, :3] / world[:, 3:]
    if np.linalg.det(matrix[:3, :3]) < 0:
        faces = faces[:, ::-1]  # a mirroring transform would turn the normals inward
    out_vertices.append(world)
    out_faces.append(faces)


def _traverse(node: _Node, state: _State, out_vertices, out_faces, source: str) -> None:
    kind = node.kind
    if not node.parsed:
        return
    if kind in _GROUPS:
        inner = _State(state.matrix, state.coords) if kind in _SEPARATORS else state
        children = node.children
        if kind == "Switch":
            # whichChild: -1 (the default) shows no child, -3 all of them.
            which = int(_numbers(node, "whichChild", [-1], source, 1)[0])
            if which != -3:
                children = children[which:which + 1] if which >= 0 else []
        for child in children:
            _traverse(child, inner, out_vertices, out_faces, source)
        if kind == "TransformSeparator":
            state.coords = inner.coords  # only the matrix is restored
    elif kind in _TRANSFORMS:
        local = _transform_matrix(node, source)
        state.matrix = np.eye(4) if local is None else state.matrix @ local
    elif kind == "Coordinate3":
        state.coords = _vec3s(node, "point", source)
    elif kind == "VertexProperty":
        if "vertex" in node.fields:
            state.coords = _vec3s(node, "vertex", source)
    elif kind in _MESH_SHAPES:
        vertices, faces = _mesh_shape(node, state, source)
        _emit(vertices, faces, state.matrix, out_vertices, out_faces)
    elif kind in _SOLIDS:
        mesh = _solid(node, source)
        _emit(mesh.vertices, mesh.faces, state.matrix, out_vertices, out_faces)
