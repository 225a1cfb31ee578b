"""Loading point clouds (N, 3) float64 from mesh files, text point files and ``.npy``
arrays.

Free of jax, and trimesh (slow to import) is imported only when a mesh is read.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

__all__ = ["LoadError", "SUPPORTED_EXTENSIONS", "load_points"]

MESH_EXTENSIONS = (".ply", ".obj", ".stl", ".off", ".glb", ".gltf", ".iv")
TEXT_EXTENSIONS = (".xyz", ".txt", ".csv", ".crd", ".pts")
SUPPORTED_EXTENSIONS = MESH_EXTENSIONS + TEXT_EXTENSIONS + (".npy",)


class LoadError(ValueError):
    """A point cloud file is missing, unsupported or malformed."""


def load_points(path, *, num_points: int = 20000, seed: int = 0) -> np.ndarray:
    """Load a point cloud as an (N, 3) float64 array.

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

    Returns
    -------
    points : np.ndarray
        C-contiguous float64 array of shape (N, 3); N == ``num_points`` for meshes with
        faces, otherwise the number of points stored in the file.

    Raises
    ------
    LoadError
        (a ``ValueError``) if the file is missing, has an unsupported extension, holds no
        points, has fewer than 3 columns or non-numeric values, contains NaN/inf
        coordinates, or if ``num_points`` < 1.
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
        points = _load_mesh(path, ext, num_points, seed)
    elif ext == ".npy":
        points = _load_npy(path)
    else:
        points = _load_text(path)
    return np.ascontiguousarray(points, dtype=np.float64)


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


def _load_mesh(path: Path, ext: str, num_points: int, seed: int) -> np.ndarray:
    import trimesh  # deferred: trimesh is slow to import and only meshes need it

    if ext == ".iv":
        from .iv import load_iv

        return sample_surface(load_iv(path), num_points, seed, path)
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
        parts = geom.dump()  # transforms applied, so bodies land where the scene puts them
        meshes = [g for g in parts if isinstance(g, trimesh.Trimesh) and len(g.faces)]
        # Not load(force="mesh"): that turns a face-less cloud into an empty mesh.
        if meshes:
            geom = trimesh.util.concatenate(meshes)
        else:
            verts = [np.asarray(g.vertices) for g in parts if hasattr(g, "vertices")]
            geom = trimesh.PointCloud(np.concatenate(verts) if verts else np.empty((0, 3)))

    return sample_surface(geom, num_points, seed, path)


def sample_surface(geom, num_points: int, seed: int = 0, path="mesh") -> np.ndarray:
    """(num_points, 3) points uniform over the area of a trimesh mesh, or the vertices
    (N, 3) as they are when it has no faces; ``path`` only names it in errors."""
    import trimesh

    vertices = np.asarray(getattr(geom, "vertices", np.empty((0, 3))), dtype=np.float64)
    faces = getattr(geom, "faces", None)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise LoadError(f"expected 3-D vertices in {path}, got shape {vertices.shape}")
    _check_points(vertices, path, "vertices")
    if faces is None or len(faces) == 0:
        return vertices
    if not geom.area > 0:
        raise LoadError(f"mesh in {path} has zero surface area; cannot sample points")
    samples, _ = trimesh.sample.sample_surface(geom, int(num_points), seed=seed)
    return samples


def _load_npy(path: Path) -> np.ndarray:
    try:
        # allow_pickle=False: loading object arrays could execute arbitrary code.
        arr = np.load(path, allow_pickle=False)
    except Exception as e:
        raise LoadError(f"could not read .npy file {path}: {e}") from e
    if arr.dtype.kind not in "iuf":
        raise LoadError(f"non-numeric array dtype {arr.dtype} in {path}; expected float/int")
    if arr.ndim != 2:
        raise LoadError(f"expected an (N, 3) array in {path}, got shape {arr.shape}")
    if arr.shape[1] < 3:
        raise LoadError(f"expected at least 3 columns (x, y, z) in {path}, got {arr.shape[1]}")
    points = arr[:, :3].astype(np.float64)
    _check_points(points, path)
    return points


def _load_text(path: Path) -> np.ndarray:
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise LoadError(f"non-numeric (binary or non-UTF-8) content in {path}: {e}") from e

    rows = [
        (num, line.strip())
        for num, line in enumerate(text.splitlines(), start=1)
        if line.strip() and not line.lstrip().startswith("#")
    ]
    # A header is only recognised by having no number in its first three fields, so a data
    # line with one bad value is reported rather than silently dropped as a "header".
    head = re.split(r"[,\s]+", rows[0][1]) if rows else []
    if (len(head) == 1 and head[0].isdigit()) or (head and not any(map(_is_float, head[:3]))):
        rows = rows[1:]  # a header line, or the point count that starts a .pts file
    if not rows:
        raise LoadError(f"no points found in {path} (empty file or only a header?)")

    # One delimiter per file, taken from the first data line, so that a comma-less line
    # in a CSV is reported as a column error rather than being parsed some other way.
    sep = "," if "," in rows[0][1] else None
    try:  # numpy's C parser is several times faster than the Python loop
        lines = [line for _, line in rows]
        points = np.loadtxt(lines, delimiter=sep, usecols=(0, 1, 2), ndmin=2, comments=None)
    except ValueError:
        points = _parse_rows(rows, sep, path)  # slower, but says what is wrong and where

    bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if bad.size:
        raise LoadError(
            f"{bad.size} of {len(points)} rows in {path} have non-finite (NaN/inf) "
            f"values (first on line {rows[bad[0]][0]})"
        )
    return points


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
