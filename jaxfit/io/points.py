"""Loading point clouds (N, 3) float64 from mesh files, text point files and ``.npy``
arrays.

Free of jax, and trimesh (slow to import) is imported only when a mesh is read.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

__all__ = ["LoadError", "SUPPORTED_EXTENSIONS", "load_cloud", "load_points"]

MESH_EXTENSIONS = (".ply", ".obj", ".stl", ".off", ".glb", ".gltf", ".iv")
TEXT_EXTENSIONS = (".xyz", ".txt", ".csv", ".crd", ".pts")
SUPPORTED_EXTENSIONS = MESH_EXTENSIONS + TEXT_EXTENSIONS + (".npy",)
#: Column names a text file's header gives its normals (case-insensitive).
NORMAL_NAMES = (("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z"))
#: Unnamed columns 4-6 are normals when every row of them is this close to unit length
#: (six printed digits are exact to 1e-6; colours 0-255 or intensities are not unit).
UNIT_TOLERANCE = 1e-3
#: Longest .npy header read (NumPy's own limit for files it has not written itself).
NPY_MAX_HEADER = 10_000


class LoadError(ValueError):
    """A point cloud file is missing, unsupported or malformed."""


def load_points(path, *, num_points: int = 20000, seed: int = 0) -> np.ndarray:
    """Load a point cloud as an (N, 3) float64 array: ``load_cloud`` without the normals
    (see there for the formats, ``num_points``, ``seed`` and the errors)."""
    return load_cloud(path, num_points=num_points, seed=seed, with_normals=False)[0]


def load_cloud(path, *, num_points: int = 20000, seed: int = 0, with_normals: bool = True):
    """Load a point cloud as an (N, 3) float64 array, with its normals where the file
    has them.

    Parameters
    ----------
    path : str or os.PathLike
        File to read; the format is chosen by extension (case-insensitive), one of
        ``SUPPORTED_EXTENSIONS``:

        - meshes (``.ply .obj .stl .off .glb .gltf`` read with trimesh, Open Inventor
          ``.iv`` with ``jaxfit.iv``): if the file has
          faces, ``num_points`` points are sampled uniformly over the surface area
          (multi-body files and glTF scenes are merged into one mesh first). A file with
          vertices but no faces (e.g. a PLY point cloud) returns its vertices as stored.
        - text (``.xyz .txt .csv .crd .pts``): one point per row, x y z in the first three
          columns separated by whitespace or commas. Blank lines and lines starting with
          ``#`` are ignored, as is one non-numeric header line (or a lone integer point
          count, as written at the top of ``.pts`` files). Extra columns are ignored.
        - ``.npy``: a numeric array of shape (N, C) with C >= 3; the first three columns
          are used.
    num_points : int, default 20000
        Number of surface samples drawn from a mesh with faces. Must be >= 1; ignored for
        point data.
    seed : int, default 0
        Seed for surface sampling, so the same file and seed give the same points.

    with_normals : bool, default True
        Whether to return normals (False: ``normals`` is None, and nothing is spent on
        them).

    Returns
    -------
    points : np.ndarray
        C-contiguous float64 array of shape (N, 3); N == ``num_points`` for meshes with
        faces, otherwise the number of points stored in the file.
    normals : np.ndarray or None
        (N, 3) float64 normals as stored (not normalised; any sign), or None where the
        file has none: a mesh's sampled points get the normals of the faces they lie
        on; a PLY point cloud its ``nx ny nz`` vertex properties; a text file the
        columns its header names ``nx ny nz`` (or ``normal_x ...``), or without such a
        header columns 4-6 when every row of them has unit length (within
        ``UNIT_TOLERANCE``: colours and intensities are not taken for normals); a
        ``.npy`` of 6 or more columns, columns 4-6 by the same unit-length rule.

    Raises
    ------
    LoadError
        (a ``ValueError``) if the file is missing, has an unsupported extension, holds no
        points, has fewer than 3 columns or non-numeric values, contains NaN/inf
        coordinates, is malformed (for a mesh: anything its reader rejects, faces that
        index missing vertices, PLY/OFF counts or GLB chunk lengths promising more data
        than the file holds; a ``.npy`` whose header promises more), or if
        ``num_points`` < 1. A header's counts are checked against the file's size
        before anything that size is allocated.
    """
    path = Path(os.fspath(path))
    if isinstance(num_points, bool) or not isinstance(num_points, (int, np.integer)):
        raise LoadError(f"num_points must be an integer >= 1, got {num_points!r} ({path})")
    if num_points < 1:
        raise LoadError(f"num_points must be >= 1, got {num_points} ({path})")
    ext = path.suffix.lower()
    if ext not in SUPPORTED_EXTENSIONS:
        raise LoadError(
            f"unsupported file extension {path.suffix!r} for {path}; "
            f"supported: {', '.join(SUPPORTED_EXTENSIONS)}"
        )
    if not path.exists():
        raise LoadError(f"file not found: {path}")
    if not path.is_file():
        raise LoadError(f"not a regular file: {path}")
    if path.stat().st_size == 0:
        raise LoadError(f"no points found in {path}: the file is empty")

    if ext in MESH_EXTENSIONS:
        points, normals = _load_mesh(path, ext, num_points, seed, with_normals)
    elif ext == ".npy":
        points, normals = _load_npy(path, with_normals)
    else:
        points, normals = _load_text(path, with_normals)
    if normals is not None and with_normals:
        normals = np.ascontiguousarray(normals, dtype=np.float64)
    else:
        normals = None
    return np.ascontiguousarray(points, dtype=np.float64), normals


def _check_points(points: np.ndarray, path: Path, what: str = "points") -> None:
    """Reject empty or non-finite (N, 3) data with a message naming the offending rows."""
    if len(points) == 0:
        raise LoadError(f"no points found in {path} (empty file?)")
    bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if bad.size:
        raise LoadError(
            f"{bad.size} of {len(points)} {what} in {path} have non-finite (NaN/inf) "
            f"coordinates (first at row {bad[0]})"
        )


def _load_mesh(path: Path, ext: str, num_points: int, seed: int, with_normals: bool = True):
    """(points (N, 3), normals (N, 3) or None) of a mesh file (see ``load_cloud``); the
    normals only ``with_normals``."""
    import trimesh  # deferred: trimesh is slow to import and only meshes need it

    if ext == ".iv":
        from .iv import IVError, load_iv

        try:
            mesh = load_iv(path)
        except IVError as err:  # (it names the file and line already)
            raise LoadError(str(err)) from err
        return sample_oriented(mesh, num_points, seed, path, with_normals=with_normals)
    if ext == ".glb":
        _check_glb_chunks(path)
    elif ext in (".ply", ".off"):
        _check_counts(path, ext)
    try:
        # process=False keeps vertices exactly as stored (no merging or reordering).
        geom = trimesh.load(path, file_type=ext[1:], process=False)
    except Exception as first:
        # Broken or missing textures/materials (or no PIL) should not cost us the geometry.
        try:
            geom = trimesh.load(path, file_type=ext[1:], process=False, skip_materials=True)
        except Exception:
            raise LoadError(f"could not read mesh {path}: {first}") from first

    if isinstance(geom, trimesh.Scene):
        geom = merged(geom)
    return sample_oriented(geom, num_points, seed, path, with_normals=with_normals)


def merged(scene):
    """One trimesh geometry of a ``trimesh.Scene``, every body moved by its node's
    transform: its meshes with faces concatenated, or without any, a
    ``trimesh.PointCloud`` of all its vertices. (Not ``load(force="mesh")``: that turns
    a face-less cloud into an empty mesh.)"""
    import trimesh

    parts = scene.dump()  # transforms applied, so bodies land where the scene puts them
    meshes = [g for g in parts if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    if meshes:
        return trimesh.util.concatenate(meshes)
    verts = [np.asarray(g.vertices) for g in parts if hasattr(g, "vertices")]
    return trimesh.PointCloud(np.concatenate(verts) if verts else np.empty((0, 3)))


def _check_counts(path: Path, ext: str) -> None:
    """Raise LoadError if the element counts of a text PLY header (or an OFF file's
    vertex and face counts) are negative or promise more rows than the file holds:
    trimesh then reads the rows that are there as the wrong elements (face rows as
    vertices) or drops the missing faces without a word. (Binary PLY is checked by
    trimesh against the file's length.)"""
    data = path.read_bytes()
    if ext == ".ply":
        head, found, body = data.partition(b"end_header")
        lines = head.decode("latin-1").splitlines()
        if not found or not any(line.split()[:2] == ["format", "ascii"] for line in lines):
            return  # (no header, or binary: trimesh's own errors)
        counts = [line.split()[2] for line in lines
                  if line.split()[:1] == ["element"] and len(line.split()) > 2]
        rows = len(body.splitlines()) - 1  # (the first is the rest of "end_header")
        what = "PLY header"
    else:
        parts = re.split(rb"(?:C?OFF)", data, maxsplit=1)
        if len(parts) < 2:
            return
        lines = [line.split(b"#")[0].strip() for line in parts[1].splitlines()]
        lines = [line.decode("latin-1") for line in lines if line]
        counts = lines[0].split()[:2] if lines else []
        rows = len(lines) - 1
        what = "OFF counts line"
    if not all(re.fullmatch(r"[-+]?\d+", c) for c in counts):
        return  # (trimesh says what is wrong with them)
    counts = [int(c) for c in counts]
    if any(c < 0 for c in counts) or sum(counts) > rows:
        raise LoadError(f"could not read mesh {path}: its {what} promises {counts} "
                        f"elements ({sum(counts)} rows), the file has {rows} rows of data")


def _check_glb_chunks(path: Path) -> None:
    """Raise LoadError if a chunk of a binary glTF claims more bytes than follow it:
    trimesh reads each chunk with one ``read(length)``, which allocates the claimed
    length (up to 4 GB from a 32-bit field) before finding the file short."""
    size = path.stat().st_size
    with open(path, "rb") as file:
        at = 12  # after the magic, the version and the total length
        while at + 8 <= size:
            file.seek(at)
            length = int.from_bytes(file.read(4), "little")
            if length > size - at - 8:
                raise LoadError(f"could not read mesh {path}: its GLB chunk at byte {at} "
                                f"claims {length} bytes, only {size - at - 8} follow")
            at += 8 + length


def sample_surface(geom, num_points: int, seed: int = 0, path="mesh") -> np.ndarray:
    """(num_points, 3) points uniform over the area of a trimesh mesh, or the vertices
    (N, 3) as they are when it has no faces; ``path`` only names it in errors.

    Raises LoadError for non-finite vertices, faces that are not triangles of indices
    into the vertices (meshes are loaded unprocessed, so nothing else checks them), and
    a mesh without surface area.
    """
    return sample_oriented(geom, num_points, seed, path, with_normals=False)[0]


def sample_oriented(geom, num_points: int, seed: int = 0, path="mesh", *,
                    with_normals: bool = True):
    """``sample_surface``'s points (the same ones for the same seed) and their normals:
    (points (N, 3), normals (N, 3) or None). A sampled point gets the unit normal of
    its face (by the face's winding); a mesh without faces its stored vertex normals
    (``vertex_normals``: a PLY cloud's ``nx ny nz``), or None. None too if a sampled
    face has no direction (a sliver whose cross product underflows)."""
    import trimesh

    vertices = np.asarray(getattr(geom, "vertices", np.empty((0, 3))), dtype=np.float64)
    faces = getattr(geom, "faces", None)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise LoadError(f"expected 3-D vertices in {path}, got shape {vertices.shape}")
    _check_points(vertices, path, "vertices")
    if faces is None or len(faces) == 0:
        return vertices, vertex_normals(geom) if with_normals else None
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu":
        raise LoadError(f"expected triangles (F, 3) of vertex indices in {path}, got an "
                        f"array of shape {faces.shape} and dtype {faces.dtype}")
    outside = np.flatnonzero(((faces < 0) | (faces >= len(vertices))).any(axis=1))
    if outside.size:
        raise LoadError(
            f"{outside.size} of {len(faces)} faces in {path} index vertices outside 0..."
            f"{len(vertices) - 1} (first: face {outside[0]}, {faces[outside[0]].tolist()})")
    with np.errstate(over="ignore", invalid="ignore", under="ignore"):
        area = geom.area
        if np.isfinite(area) and area > 0:
            samples, where = trimesh.sample.sample_surface(geom, int(num_points), seed=seed)
        else:
            # trimesh's areas (square roots of sums of squares) overflow for coordinates
            # near 1e300 and underflow to 0 for a mesh near 1e-160 in size: such a mesh
            # is sampled in a frame where its coordinates are at most 1, by areas
            # computed without squaring, and scaled back.
            samples, where = _sample_scaled(vertices, faces, int(num_points), seed, path)
    if not np.isfinite(samples).all():
        raise LoadError(f"mesh in {path} has coordinates too large to sample (points on "
                        "its surface overflow float64)")
    return samples, face_normals(vertices, faces[where]) if with_normals else None


def face_normals(vertices, triangles) -> np.ndarray | None:
    """Unit normals (T, 3) of triangles (T, 3) of indices into vertices (V, 3), by their
    winding, computed in a frame where the coordinates are at most 1 (no overflow for
    huge meshes, no underflow for tiny ones); None if one has no direction."""
    scale = float(np.abs(vertices).max()) or 1.0
    corners = vertices[triangles] / scale
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    largest = np.abs(cross).max(axis=1, keepdims=True)
    if not np.all(largest > 0):
        return None
    cross = cross / largest
    return cross / np.linalg.norm(cross, axis=1, keepdims=True)


def vertex_normals(geom) -> np.ndarray | None:
    """(V, 3) normals stored with a face-less trimesh geometry, or None: a PLY point
    cloud's ``nx ny nz`` vertex properties (trimesh keeps them in its metadata)."""
    data = getattr(geom, "metadata", {}).get("_ply_raw", {}).get("vertex", {}).get("data")
    try:
        normals = np.column_stack([np.asarray(data[c], np.float64).reshape(-1)
                                   for c in ("nx", "ny", "nz")])
    except (KeyError, TypeError, IndexError, ValueError):
        return None
    if len(normals) != len(geom.vertices) or not np.isfinite(normals).all():
        return None
    return normals


def _sample_scaled(vertices, faces, num_points: int, seed, path):
    """sample_surface for a mesh whose areas over- or underflow (see there): the points
    and their face indices."""
    import trimesh

    scale = float(np.abs(vertices).max())
    unit = vertices / scale if scale > 0 else vertices
    corners = unit[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    largest = np.abs(cross).max(axis=1)
    ratio = cross / np.where(largest > 0, largest, 1.0)[:, None]
    weight = largest * np.sqrt((ratio**2).sum(axis=1))  # twice the area, in the unit frame
    if not weight.sum() > 0:
        raise LoadError(f"mesh in {path} has zero surface area; cannot sample points")
    mesh = trimesh.Trimesh(unit, faces, process=False)
    samples, where = trimesh.sample.sample_surface(mesh, num_points, face_weight=weight,
                                                   seed=seed)
    return samples * scale, where


def _load_npy(path: Path, with_normals: bool = True):
    """(points (N, 3), normals (N, 3) or None) of a .npy file: unit columns 4-6 are the
    normals (looked for only ``with_normals``)."""
    fmt = np.lib.format
    try:
        # The header first: its shape is believed only if the file holds that much data
        # (np.load allocates the whole array before reading, 9.6 GB for a 200-byte file
        # whose header claims 4e8 x 3 doubles).
        # NumPy reads as many header bytes as the header's length field says before it
        # checks them (a 4-byte field: up to 4 GB), so that length is checked first too.
        with open(path, "rb") as file:
            version = fmt.read_magic(file)
            if version not in ((1, 0), (2, 0), (3, 0)):
                raise ValueError(f"unsupported .npy format version {version}")
            length_bytes = 2 if version == (1, 0) else 4
            length = int.from_bytes(file.read(length_bytes), "little")
            if length > min(NPY_MAX_HEADER, path.stat().st_size - file.tell()):
                raise ValueError(f"header length {length} is past the end of the file or "
                                 f"over {NPY_MAX_HEADER} bytes")
            file.seek(-length_bytes, os.SEEK_CUR)
            read_header = fmt.read_array_header_1_0 if version == (1, 0) else \
                fmt.read_array_header_2_0  # (3.0 differs only in its text encoding)
            shape, _, dtype = read_header(file)
            data_bytes = path.stat().st_size - file.tell()
    except Exception as e:
        raise LoadError(f"could not read .npy file {path}: {e}") from e
    if dtype.kind not in "iuf":
        raise LoadError(f"non-numeric array dtype {dtype} in {path}; expected float/int")
    if len(shape) != 2:
        raise LoadError(f"expected an (N, 3) array in {path}, got shape {shape}")
    if shape[1] < 3:
        raise LoadError(f"expected at least 3 columns (x, y, z) in {path}, got {shape[1]}")
    if math.prod(shape) * dtype.itemsize > data_bytes:
        raise LoadError(f"truncated .npy file {path}: its header promises shape {shape} of "
                        f"{dtype} ({math.prod(shape) * dtype.itemsize} bytes), the file holds "
                        f"{data_bytes} bytes of data")
    try:
        # allow_pickle=False: loading object arrays could execute arbitrary code.
        arr = np.load(path, allow_pickle=False)
    except Exception as e:
        raise LoadError(f"could not read .npy file {path}: {e}") from e
    points = arr[:, :3].astype(np.float64)
    _check_points(points, path)
    return points, unit_columns(arr[:, 3:6]) if with_normals and arr.shape[1] >= 6 else None


def unit_columns(columns) -> np.ndarray | None:
    """columns (N, 3) as float64 normals if every row is finite and of unit length
    within ``UNIT_TOLERANCE`` (unnamed columns 4-6 of a point file), else None."""
    columns = np.asarray(columns, dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        length = np.linalg.norm(columns, axis=1)
    return columns if len(columns) and np.all(np.abs(length - 1) <= UNIT_TOLERANCE) else None


def _load_text(path: Path, with_normals: bool = True):
    """(points (N, 3), normals (N, 3) or None) of a text point file (see ``load_cloud``)."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise LoadError(f"non-numeric (binary or non-UTF-8) content in {path}: {e}") from e

    lines = text.splitlines()
    rows = [
        (num, line.strip())
        for num, line in enumerate(lines, start=1)
        if line.strip() and not line.lstrip().startswith("#")
    ]
    # A header is only recognised by having no number in its first three fields, so a data
    # line with one bad value is reported rather than silently dropped as a "header".
    head = re.split(r"[,\s]+", rows[0][1]) if rows else []
    header = None
    if (len(head) == 1 and head[0].isdigit()) or (head and not any(map(_is_float, head[:3]))):
        header = head if len(head) > 1 else None
        rows = rows[1:]  # a header line, or the point count that starts a .pts file
    if not rows:
        raise LoadError(f"no points found in {path} (empty file or only a header?)")

    # One delimiter per file, taken from the first data line, so that a comma-less line
    # in a CSV is reported as a column error rather than being parsed some other way.
    sep = "," if "," in rows[0][1] else None
    try:  # numpy's C parser is several times faster than the Python loop
        data = [line for _, line in rows]
        points = np.loadtxt(data, delimiter=sep, usecols=(0, 1, 2), ndmin=2, comments=None)
    except ValueError:
        points = _parse_rows(rows, sep, path)  # slower, but says what is wrong and where

    bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if bad.size:
        raise LoadError(
            f"{bad.size} of {len(points)} rows in {path} have non-finite (NaN/inf) "
            f"values (first on line {rows[bad[0]][0]})"
        )
    if not with_normals:
        return points, None
    if header is None:  # a commented header ("# x y z nx ny nz", as numpy.savetxt writes)
        named = [line.lstrip("# \t") for line in lines[:rows[0][0] - 1]
                 if line.lstrip().startswith("#")]
        header = re.split(r"[,\s]+", named[-1].strip()) if named else None
    return points, _text_normals([line for _, line in rows], sep, header)


def _text_normals(data: list[str], sep, header) -> np.ndarray | None:
    """The normals of a text file's data lines: the columns its header names (see
    ``NORMAL_NAMES``), else unnamed columns 4-6 of unit length; None if it has none or
    they are not numbers in every row."""
    names = [name.lower() for name in header or ()]
    columns = next((tuple(names.index(n) for n in trio) for trio in NORMAL_NAMES
                    if all(n in names for n in trio)), None)
    try:
        found = np.loadtxt(data, delimiter=sep, usecols=columns or (3, 4, 5), ndmin=2,
                           comments=None)
    except (ValueError, IndexError):
        return None
    if columns is None:
        return unit_columns(found)
    return found if np.isfinite(found).all() else None


def _parse_rows(rows: list[tuple[int, str]], sep: str | None, path: Path) -> np.ndarray:
    """Parse (line number, line) pairs into an (N, 3) array, raising on the first bad line."""
    points = np.empty((len(rows), 3))
    for i, (num, line) in enumerate(rows):
        row = line.split(sep)
        if len(row) < 3:
            raise LoadError(
                f"line {num} of {path} has {len(row)} column(s); expected at least 3 (x, y, z)"
            )
        try:
            points[i] = [float(v) for v in row[:3]]
        except ValueError:
            raise LoadError(f"non-numeric value on line {num} of {path}: {line!r}") from None
    return points


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True
