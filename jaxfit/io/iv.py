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

Hostile input: any text either gives a mesh or raises ``IVError`` (a ``ValueError``)
naming the line, in time and memory bounded by the file's size plus the budgets below.
Before anything is traversed, the scene's expansion (every ``USE`` counted as a copy of
its target) is bounded: at most ``MAX_GEOMETRY`` vertices plus faces and ``MAX_NODES``
node visits. Every count and index is checked against the coordinates present before an
array of that size is made. Nesting is parsed and traversed with explicit stacks, so it
is limited only by the file's size, never by Python's recursion limit. See docs/iv.md.
"""

from __future__ import annotations

import dataclasses
import functools
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
#: Budget on the scene's vertices plus faces once every USE is expanded, checked before
#: traversal from what each shape can produce at most (docs/iv.md).
MAX_GEOMETRY = 10_000_000
#: Budget on node visits once every USE is expanded: it bounds the traversal time of
#: scenes whose repeated nodes make little or no geometry (docs/iv.md).
MAX_NODES = 500_000

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
    """An Inventor file is missing, not Inventor ASCII, malformed, holds no surface, or
    expands past a budget."""


@dataclasses.dataclass(eq=False, repr=False, slots=True)
class _Node:
    """A parsed node: ``fields`` maps names to a token list or a node; ``parsed`` is False
    for skipped node types."""

    kind: str
    line: int
    fields: dict = dataclasses.field(default_factory=dict)
    children: list = dataclasses.field(default_factory=list)
    parsed: bool = True
    name: str | None = None  # the DEF name, for error messages
    # {position in children: (line, name)} of the children that are a USE, for errors.
    uses: dict | None = None
    # What traversal derived from this node alone (coordinates, matrix, local mesh), so a
    # node that USE repeats is read once.
    cache: dict = dataclasses.field(default_factory=dict)

    def __repr__(self) -> str:  # not the dataclass's: that one recurses into children
        return f"<{_label(self)} on line {self.line}: {len(self.children)} children>"


@dataclasses.dataclass
class _State:
    """Traversal state: ``matrix`` (4, 4) maps local to world coordinates for column
    vectors; ``coords`` (K, 3) are the current local coordinates."""

    matrix: np.ndarray
    coords: np.ndarray
    _mirrors: tuple = (None, False)  # (matrix, whether it mirrors), computed once per matrix

    def mirrors(self) -> bool:
        matrix, mirrors = self._mirrors
        if matrix is not self.matrix:
            mirrors = bool(np.linalg.det(self.matrix[:3, :3]) < 0)
            self._mirrors = (self.matrix, mirrors)
        return mirrors


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
        (unclosed braces or brackets, bad field values, counts or indices out of range),
        holds no surface geometry, or expands (through USE) past ``MAX_GEOMETRY``
        vertices plus faces or ``MAX_NODES`` node visits.
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
    parser = _Parser(text, source)
    scene = parser.parse()
    _check_budget(scene, parser.max_coords, source)
    pieces = _traverse(scene, source)
    if not pieces:
        raise IVError(f"no surface geometry (no faces) found in {source}")
    # Each piece goes to world coordinates straight into the result (no copy of it all).
    vertices = np.empty((sum(len(piece[0]) for piece in pieces), 3))
    faces = np.empty((sum(len(piece[1]) for piece in pieces), 3), dtype=np.int64)
    v = f = 0
    for homogeneous, triangles, matrix, mirrors in pieces:
        world = homogeneous @ matrix.T
        np.divide(world[:, :3], world[:, 3:], out=vertices[v:v + len(world)])
        # A mirroring transform would turn the normals inward.
        np.add(triangles[:, ::-1] if mirrors else triangles, v,
               out=faces[f:f + len(triangles)])
        v, f = v + len(world), f + len(triangles)
    return trimesh.Trimesh(vertices, faces, process=False)


# ----- tokenizer and parser ---------------------------------------------------------------
def _tokenize(text: str, source: str) -> tuple[list[str], list[int]]:
    """Tokens and their line numbers (for errors)."""
    tokens, lines = [], []
    line = 1
    for match in _TOKEN.finditer(text):
        token, bad = match.group(1), match.group(2)
        if bad is not None:
            what = "unterminated string" if bad == '"' else f"unexpected character {bad!r}"
            raise IVError(f"{what} on line {line} of {source}")
        if token is not None:
            tokens.append(token)
            lines.append(line)
        line += match.group(0).count("\n")
    return tokens, lines


def _is_word(token: str | None) -> bool:
    return token is not None and token not in "{}[]()|=" and not token.startswith('"')


class _Parser:
    """Parser of the generic Inventor grammar, with an explicit stack of open nodes (no
    recursion, so any nesting depth the file holds).

    Without a schema, a field's value is read by its form: ``[...]``, ``(...)``, a node,
    a run of numbers and strings, or one word (an enum, TRUE/FALSE, NULL). A DEF name is
    bound when its node closes, so a USE can only name a finished node: the scene graph
    has no cycles.
    """

    def __init__(self, text: str, source: str):
        self.source = source
        self.tokens, self.lines = _tokenize(text, source)
        self.pos = 0
        self.defs: dict[str, _Node] = {}
        #: The most coordinates any Coordinate3 or VertexProperty holds (for the budget).
        self.max_coords = 0
        # Open nodes, innermost last: (node, DEF name, field it fills or None for a child).
        self.open: list[tuple[_Node, str | None, str | None]] = []
        self.scene = _Node("scene", 1)  # the top-level nodes are its children
        # Stray '}' and USEs of undefined names, for one warning each however many there
        # are (a hostile file could hold millions): (first line, name), count.
        self.stray: tuple[int | None, int] = (None, 0)
        self.undefined: tuple[tuple[int, str] | None, int] = (None, 0)

    def parse(self) -> _Node:
        """The scene: a group of the top-level nodes."""
        while True:
            token = self.peek()
            if not self.open:
                if token is None:
                    break
                if token == "}":
                    # GraspIt!'s arizonaObject_revised.iv ends with one '}' too many;
                    # Inventor readers stop at it, so we warn and go on rather than
                    # reject the model.
                    self.stray = (self.stray[0] or self.line(), self.stray[1] + 1)
                    self.pos += 1
                else:
                    self.node(None)
                continue
            node = self.open[-1][0]
            if token is None:
                raise IVError(f"unbalanced braces in {self.source}: the '{{' of {node.kind} "
                              f"on line {node.line} is never closed")
            if token == "}":
                self.pos += 1
                self.close()
            elif token in ("DEF", "USE") or self.peek(1) == "{":
                self.node(None)
            elif _is_word(token):
                self.pos += 1
                self.value(token)
            else:
                raise self.error(f"unexpected {token!r} in {node.kind}")
        if self.stray[1]:
            line, n = self.stray
            warnings.warn(f"ignoring unmatched '}}' on line {line} of {self.source}"
                          + (f" (and {n - 1} more)" if n > 1 else ""), stacklevel=3)
        if self.undefined[1]:
            (line, name), n = self.undefined
            warnings.warn(f"USE of undefined name {name!r} on line {line} of {self.source} "
                          "ignored" + (f" (and {n - 1} more)" if n > 1 else ""), stacklevel=3)
        return self.scene

    # -- helpers --
    def peek(self, ahead: int = 0) -> str | None:
        i = self.pos + ahead
        return self.tokens[i] if i < len(self.tokens) else None

    def line(self, pos: int | None = None) -> int:
        pos = min(self.pos if pos is None else pos, len(self.tokens) - 1)
        return self.lines[pos] if pos >= 0 else 1

    def take(self, what: str) -> str:
        token = self.peek()
        if token is None:
            raise IVError(f"unexpected end of file on line {self.line()} of {self.source}: "
                          f"expected {what}")
        self.pos += 1
        return token

    def error(self, message: str) -> IVError:
        return IVError(f"{message} on line {self.line()} of {self.source}")

    def attach(self, node: _Node | None, field: str | None, use: tuple | None = None):
        """Put a finished node (None: a USE of an unknown name) where it was found;
        ``use`` is (line, name) if it came from a USE."""
        parent = self.open[-1][0] if self.open else self.scene
        if field is not None:
            parent.fields[field] = node
        elif node is not None:
            if use is not None:
                if parent.uses is None:
                    parent.uses = {}
                parent.uses[len(parent.children)] = use
            parent.children.append(node)

    # -- grammar --
    def node(self, field: str | None) -> None:
        """``[DEF name] Kind { body }`` or ``USE name``, filling ``field`` of the open
        node (its child list if None). A parsed kind stays open until its '}'."""
        token = self.take("a node")
        if token == "USE":
            name = self.take("a name after USE")
            use = (self.line(self.pos - 1), name)
            if name not in self.defs:
                self.undefined = (self.undefined[0] or use, self.undefined[1] + 1)
            self.attach(self.defs.get(name), field, use)
            return
        name = None
        if token == "DEF":
            name, token = self.take("a name after DEF"), self.take("a node after DEF")
        if not _is_word(token) or self.peek() != "{":
            self.pos -= 1
            raise self.error(f"expected a node name followed by '{{', got {token!r}")
        start = self.pos
        self.pos += 1
        node = _Node(token, self.line(start), name=name)
        if token in _PARSED:
            self.open.append((node, name, field))
            return
        self.skip_body(node)
        node.parsed = False
        if name is not None:
            self.defs[name] = node
        self.attach(node, field)

    def close(self) -> None:
        node, name, field = self.open.pop()
        if name is not None:
            self.defs[name] = node
        if node.kind in _COORDINATES:
            points = node.fields.get("point" if node.kind == "Coordinate3" else "vertex")
            if isinstance(points, list):
                self.max_coords = max(self.max_coords, len(points) // 3)
        self.attach(node, field)

    def skip_body(self, node: _Node) -> None:
        depth = 1
        while depth:
            token = self.peek()
            if token is None:
                raise IVError(f"unbalanced braces in {self.source}: the '{{' of {node.kind} "
                              f"on line {node.line} is never closed")
            depth += (token == "{") - (token == "}")
            self.pos += 1

    def value(self, field: str) -> None:
        """Read the value of ``field`` of the open node."""
        fields = self.open[-1][0].fields
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
            fields[field] = values
        elif token in ("DEF", "USE") or (_is_word(token) and self.peek(1) == "{"):
            self.node(field)
        elif token is not None and (_NUMBER.match(token) or token.startswith('"')):
            values = []
            while (t := self.peek()) is not None and (_NUMBER.match(t) or t.startswith('"')):
                values.append(t)
                self.pos += 1
            fields[field] = values
        elif _is_word(token):
            self.pos += 1
            fields[field] = [token]
        else:
            raise self.error(f"missing value for field {field!r}")


# ----- the budget ---------------------------------------------------------------------------
@functools.cache
def _solid_size(kind: str) -> int:
    """Vertices plus faces of a solid: its default mesh is the largest (degenerate sizes
    merge vertices or drop faces)."""
    mesh = _solid(_Node(kind, 0), "")
    return len(mesh.vertices) + len(mesh.faces)


def _field_size(node: _Node, field: str) -> int:
    value = node.fields.get(field)
    return len(value) if isinstance(value, list) else 0


def _shape_size(node: _Node, max_coords: int, source: str) -> int:
    """The most vertices plus faces a shape can produce, whatever coordinates traversal
    gives it (a face or strip set adds one per ``numVertices`` entry, which it reads)."""
    if not node.parsed or node.kind not in _SOLIDS | _MESH_SHAPES:
        return 0
    if node.kind in _SOLIDS:
        return _solid_size(node.kind)
    prop = node.fields.get("vertexProperty")
    if isinstance(prop, _Node) and "vertex" in prop.fields:
        max_coords = _field_size(prop, "vertex") // 3  # the shape's own coordinates
    if node.kind.startswith("Indexed"):
        try:
            index = _index_values(node, source)
        except IVError:  # traversal reports it when it gets there
            return 2 * _field_size(node, "coordIndex")
        real, within, _ = _runs(index)
        return int(np.count_nonzero(real & (within >= 2))
                   + min(np.count_nonzero(real), max_coords))
    # FaceSet, TriangleStripSet: polygons or strips of consecutive distinct coordinates.
    vertices = faces = max_coords
    counts = node.fields.get("numVertices")
    if isinstance(counts, list):
        try:
            counts = np.trunc(np.array(counts, dtype=np.float64))
        except ValueError:
            counts = None  # traversal reports it
        if counts is not None and np.all(counts >= 0) and np.all(np.isfinite(counts)):
            vertices = min(vertices, counts.sum())
            faces = min(faces, np.maximum(counts - 2, 0).sum())
    return int(vertices + faces) + max(_field_size(node, "numVertices"), 1)


def _label(node: _Node) -> str:
    return f"DEF {node.name} {node.kind}" if node.name is not None else node.kind


def _over_budget(budget: str, group: _Node, position: int, source: str) -> IVError:
    """The error for the child at ``position`` of ``group`` taking it past ``budget``."""
    child = group.children[position]
    use = group.uses.get(position) if group.uses else None
    line, entry = (use[0], f"USE {use[1]}") if use else (child.line, _label(child))
    inside = "the scene" if group.kind == "scene" else f"{_label(group)} (line {group.line})"
    what = "vertices and faces" if budget == "MAX_GEOMETRY" else "node visits"
    return IVError(f"{entry} on line {line} of {source} takes {inside} past "
                   f"{globals()[budget]:,} {what} (jaxfit.io.iv.{budget}; every USE counts "
                   "as a copy of its node, see docs/iv.md)")


def _check_budget(scene: _Node, max_coords: int, source: str) -> None:
    """Raise IVError at the first USE or node that takes a group, or the scene, past
    ``MAX_NODES`` visits or ``MAX_GEOMETRY`` vertices plus faces once USE is expanded.

    One pass over the distinct nodes, without recursion: a group's totals are kept, so
    each USE of it adds them without walking it again.
    """
    max_nodes, max_geometry = MAX_NODES, MAX_GEOMETRY
    totals: dict[int, tuple[int, int]] = {}  # id(node) -> (visits, vertices + faces)
    # Each frame: [group, positions of the children it shows, next one, visits, geometry].
    frames: list[list] = [[scene, range(len(scene.children)), 0, 0, 0]]
    while frames:
        frame = frames[-1]
        group, shown, i = frame[0], frame[1], frame[2]
        if i == len(shown):
            frames.pop()
            if not frames:
                return
            totals[id(group)] = visits, geometry = frame[3], frame[4]
            frame = frames[-1]
            position = frame[1][frame[2] - 1]
        else:
            frame[2] += 1
            position = shown[i]
            child = group.children[position]
            known = totals.get(id(child))
            if known is not None:
                visits, geometry = known
            elif child.parsed and child.kind in _GROUPS:
                frames.append([child, _shown(child, source, lenient=True), 0, 1, 0])
                continue
            else:
                totals[id(child)] = visits, geometry = 1, _shape_size(child, max_coords, source)
        frame[3] += visits
        frame[4] += geometry
        if frame[4] > max_geometry:
            raise _over_budget("MAX_GEOMETRY", frame[0], position, source)
        if frame[3] > max_nodes:
            raise _over_budget("MAX_NODES", frame[0], position, source)


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


def _index_values(node: _Node, source: str) -> np.ndarray:
    """``coordIndex`` as float64 numbers, each an integer >= -1 (-1 separates), read once
    per node; the range is checked against the coordinates at each use."""
    if "index" not in node.cache:
        arr = _numbers(node, "coordIndex", [], source)
        if np.any(arr != np.round(arr)):  # also NaN
            raise IVError(f"non-integer index in 'coordIndex' of {node.kind} on line "
                          f"{node.line} of {source}")
        if np.any(arr < -1):
            raise IVError(f"negative index other than -1 in {node.kind} on line {node.line} "
                          f"of {source}")
        node.cache["index"] = arr
    return node.cache["index"]


def _integer(node: _Node, field: str, default: int, source: str) -> int:
    """A single-number field truncated to an int (Python's, so never an overflow)."""
    value = float(_numbers(node, field, [default], source, 1)[0])
    if not np.isfinite(value):
        raise IVError(f"field {field!r} of {node.kind} on line {node.line} of {source} is "
                      f"{value}, expected an integer")
    return int(value)


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
        axis = node.fields.get("axis")
        axis = ["X"] if axis is None else axis  # None also for a USE of an undefined name
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


def _counts_to_index(node: _Node, available: int, source: str) -> np.ndarray:
    """-1-separated consecutive indices for FaceSet/TriangleStripSet ``numVertices`` from
    ``startIndex``; a negative count takes all remaining coordinates. The counts are
    checked against the ``available`` coordinates before any index array is made."""
    start = _integer(node, "startIndex", 0, source)
    counts = _numbers(node, "numVertices", [-1], source)
    if not 0 <= start <= available:
        raise IVError(f"startIndex {start} of {node.kind} on line {node.line} of {source} "
                      f"is outside the {available} coordinates defined")
    if not np.all(np.isfinite(counts)):
        raise IVError(f"non-finite count in 'numVertices' of {node.kind} on line "
                      f"{node.line} of {source}")
    resolved, at = [], start
    for count in counts.tolist():
        count = int(count)
        count = available - at if count < 0 else count
        if count > available - at:
            raise IVError(f"{node.kind} on line {node.line} of {source} asks for {count} "
                          f"coordinates from coordinate {at}, but only {available} are "
                          "defined")
        resolved.append(count)
        at += count
    pieces, at = [], start
    for count in resolved:
        pieces += [np.arange(at, at + count), [-1]]
        at += count
    return np.concatenate(pieces).astype(np.int64) if pieces else np.empty(0, np.int64)


def _coordinates(node: _Node, field: str, source: str) -> np.ndarray:
    """A node's coordinate field as (K, 3), read once per node."""
    key = ("coords", field)
    if key not in node.cache:
        node.cache[key] = _vec3s(node, field, source)
    return node.cache[key]


def _shape_coords(node: _Node, state: _State, source: str) -> np.ndarray:
    prop = node.fields.get("vertexProperty")
    if isinstance(prop, _Node) and "vertex" in prop.fields:
        return _coordinates(prop, "vertex", source)
    return state.coords


def _topology(faces):
    """The non-degenerate triangles of ``faces`` as (used, triangles): the vertex indices
    they use, sorted, and (T, 3) indices into ``used``; None if no triangle is left."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
                  & (faces[:, 0] != faces[:, 2])]
    if not len(faces):
        return None
    used, faces = np.unique(faces, return_inverse=True)
    return used, faces.reshape(-1, 3)


def _mesh_topology(node: _Node, available: int, source: str):
    """``_topology`` of a face or strip set given ``available`` coordinates; kept on the
    node (an indexed set's does not depend on them once they suffice)."""
    if node.kind.startswith("Indexed"):
        index = _index_values(node, source)
        if index.size and index.max() >= available:
            raise IVError(f"{node.kind} on line {node.line} of {source} uses coordinate "
                          f"{index.max():.0f} but only {available} are defined")
        key = None
    else:
        key = available
    cached = node.cache.get("topology")
    if cached is None or cached[0] != key:
        index = (index.astype(np.int64) if key is None
                 else _counts_to_index(node, available, source))
        faces = _strip_triangles(index) if "Strip" in node.kind else _fan_triangles(index)
        cached = node.cache["topology"] = (key, _topology(faces))
    return cached[1]


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


def _placed(vertices, topology):
    """A ``_topology`` with its used vertices in homogeneous coordinates (K, 4)."""
    if topology is None:
        return None
    used, faces = topology
    local = np.asarray(vertices, dtype=np.float64)[used]
    return np.c_[local, np.ones(len(local))], faces


def _shape_mesh(node: _Node, state: _State, source: str):
    """A shape's local mesh for ``_emit`` (None if it has no triangle), kept on the node
    for as long as traversal gives it the same coordinates (a solid's never change)."""
    if node.kind in _SOLIDS:
        if "mesh" not in node.cache:
            mesh = _solid(node, source)
            node.cache["mesh"] = _placed(mesh.vertices, _topology(mesh.faces))
        return node.cache["mesh"]
    coords = _shape_coords(node, state, source)
    cached = node.cache.get("mesh")
    if cached is None or cached[0] is not coords:
        topology = _mesh_topology(node, len(coords), source)
        cached = node.cache["mesh"] = (coords, _placed(coords, topology))
    return cached[1]


def _emit(mesh, state: _State, pieces: list) -> None:
    """Keep a ``_shape_mesh`` with the matrix to world coordinates (applied at the end,
    into the result)."""
    if mesh is not None:
        pieces.append((*mesh, state.matrix, state.mirrors()))


def _shown(node: _Node, source: str, lenient: bool = False) -> range:
    """The positions of the children a group shows: a Switch follows ``whichChild`` (-1,
    the default, shows none, -3 all). ``lenient``: all of a Switch's children if that
    field is bad (the budget's upper bound; traversal then reports the error)."""
    count = len(node.children)
    if node.kind != "Switch":
        return range(count)
    if "shown" not in node.cache:
        try:
            which = _integer(node, "whichChild", -1, source)
        except IVError:
            if lenient:
                return range(count)
            raise
        if which == -3:
            node.cache["shown"] = range(count)
        else:
            node.cache["shown"] = range(which, min(which + 1, count)) if which >= 0 else range(0)
    return node.cache["shown"]


def _local_matrix(node: _Node, source: str) -> np.ndarray | None:
    if "matrix" not in node.cache:
        node.cache["matrix"] = _transform_matrix(node, source)
    return node.cache["matrix"]


def _traverse(scene: _Node, source: str) -> list:
    """Walk the scene in order with an explicit stack (any depth); the ``_emit`` pieces of
    its shapes."""
    pieces: list = []
    root = _State(np.eye(4), np.empty((0, 3)))
    # Each frame: (children left, the state they see, the state outside the group, group).
    stack = [(iter(scene.children), root, root, scene)]
    while stack:
        children, state, outer, group = stack[-1]
        node = next(children, None)
        if node is None:
            stack.pop()
            if group.kind == "TransformSeparator":
                outer.coords = state.coords  # only the matrix is restored
            continue
        kind = node.kind
        if not node.parsed:
            continue
        if kind in _GROUPS:
            inner = (_State(state.matrix, state.coords, state._mirrors) if kind in _SEPARATORS
                     else state)
            shown = _shown(node, source)
            children = (iter(node.children) if len(shown) == len(node.children)
                        else (node.children[i] for i in shown))
            stack.append((children, inner, state, node))
        elif kind in _TRANSFORMS:
            local = _local_matrix(node, source)
            state.matrix = np.eye(4) if local is None else state.matrix @ local
        elif kind == "Coordinate3":
            state.coords = _coordinates(node, "point", source)
        elif kind == "VertexProperty":
            if "vertex" in node.fields:
                state.coords = _coordinates(node, "vertex", source)
        elif kind in _MESH_SHAPES or kind in _SOLIDS:
            _emit(_shape_mesh(node, state, source), state, pieces)
    return pieces
