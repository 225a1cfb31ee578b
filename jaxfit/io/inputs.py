"""One converter for every kind of cloud jaxfit's entry points take: ``as_cloud(source)``
gives (points (N, 3) float64, normals (N, 3) or None) from

- NumPy arrays and array-likes (lists, JAX arrays, anything with ``__array__``): the
  points as they are, no normals;
- ``trimesh.PointCloud``: its vertices (and a PLY cloud's stored normals);
- ``trimesh.Trimesh``: ``num_points`` points sampled uniformly over its surface
  (``io.points.sample_surface``, the same points for the same seed), each with its
  face's normal; a mesh without faces gives its vertices;
- ``trimesh.Scene`` (what ``trimesh.load`` returns for a glTF, e.g. the YCB models):
  its bodies moved by their transforms and merged (``io.points.merged``), then sampled;
- paths (``str`` or ``os.PathLike``): ``io.points.load_cloud`` (point files keep the
  normals in their columns 4-6, meshes and Open Inventor ``.iv`` models are sampled);
- Open3D ``geometry.PointCloud`` (its ``normals`` where it has them) and
  ``geometry.TriangleMesh`` (sampled as the trimesh mesh of its vertices and triangles,
  each point with its face's normal), and their tensor (``open3d.t.geometry``) versions.

Neither trimesh nor Open3D is imported here: an object can only be one of theirs if its
library is already in ``sys.modules``, so the check costs nothing without them.

``converted`` is what ``fit``, ``fit_batch``, ``detect``, ``estimate_normals`` and
``decompose`` call first: array-likes pass through untouched, so the entry points' own
checks name what is wrong with them as before.
"""

from __future__ import annotations

import numbers
import os
import sys

import numpy as np

from .points import LoadError, load_cloud, merged, sample_oriented

__all__ = ["MESH_POINTS", "SourceTypeError", "as_cloud", "converted", "converted_batch"]

#: Points sampled from a mesh when the caller does not say (``load_points``'s default).
#: The entry points other than ``decompose`` (which has ``num_points``) sample this many;
#: for another count, call ``as_cloud(mesh, num_points=...)`` and pass its arrays.
MESH_POINTS = 20000

ACCEPTED = ("an (N, 3) array, a trimesh PointCloud, Trimesh or Scene, an Open3D PointCloud "
            "or TriangleMesh, or a path to a point or mesh file")


class SourceTypeError(TypeError, ValueError):
    """A cloud was given as an object of a type jaxfit cannot read points from. (A
    ValueError too, as every other bad input to jaxfit is.)"""


def as_cloud(source, *, num_points: int | None = None, seed: int = 0,
             with_normals: bool = True, name: str = "points"):
    """(points (N, 3) float64, normals (N, 3) float64 or None) of any supported source
    (the module docstring lists them).

    Parameters
    ----------
    source : array-like, trimesh or Open3D geometry, or path.
    num_points : points sampled from a surface mesh (default ``MESH_POINTS``); ignored
        for point data.
    seed : int seed of the surface sampling: the same mesh and seed give the same points.
    with_normals : False: ``normals`` is None (nothing is spent on them).
    name : what the points are called in error messages.

    Returns
    -------
    points : (N, 3) float64 array, finite.
    normals : (N, 3) float64 array (unit length for meshes; as stored for point data,
        any sign), or None where the source has none.

    Raises
    ------
    SourceTypeError
        (a TypeError and a ValueError) for an object of any other type, naming it.
    ValueError
        (``io.LoadError`` for files and meshes) for points of the wrong shape,
        non-numeric or non-finite values, unreadable files.
    """
    from .._checks import cloud  # (NumPy checks; jaxfit's own, so messages match fit's)

    points, normals = converted(source, num_points=num_points, seed=seed,
                                with_normals=with_normals, name=name)
    points = cloud(points, name)
    if normals is not None:
        normals = cloud(normals, "normals", limit=None)
        if normals.shape != points.shape:  # (cannot happen for the sources above)
            raise ValueError(f"normals of shape {normals.shape} do not match the points' "
                             f"{points.shape}")
    return points, normals


def converted(source, *, num_points: int | None = None, seed=0, with_normals: bool = True,
              name: str = "points"):
    """(points, normals or None) of ``source`` for an entry point: a recognised geometry
    or path converted as ``as_cloud`` does; an array-like returned untouched (the entry
    point checks it); anything else a ``SourceTypeError``. ``seed`` may be a callable
    giving the int seed, called only when a mesh is sampled (an entry point's seed comes
    from its key)."""
    if isinstance(source, np.ndarray | list | tuple | numbers.Number) or _array_like(source):
        return source, None
    count = MESH_POINTS if num_points is None else num_points

    def sampled(mesh):
        return sample_oriented(mesh, _count(count), _seed(seed), _label(mesh),
                               with_normals=with_normals)

    if isinstance(source, str | os.PathLike):
        return load_cloud(source, num_points=count, seed=_seed(seed), with_normals=with_normals)
    trimesh = sys.modules.get("trimesh")
    if trimesh is not None:
        if isinstance(source, trimesh.Scene):
            return sampled(merged(source))
        if isinstance(source, trimesh.Trimesh | trimesh.PointCloud):
            return sampled(source)
    o3d = sys.modules.get("open3d")
    if o3d is not None and type(source).__module__.startswith("open3d"):
        if hasattr(source, "to_legacy") and not isinstance(source, o3d.geometry.Geometry):
            source = source.to_legacy()  # a tensor geometry (open3d.t.geometry)
        if isinstance(source, o3d.geometry.PointCloud):
            points = np.asarray(source.points, dtype=np.float64)
            normals = (np.asarray(source.normals, dtype=np.float64)
                       if with_normals and source.has_normals() else None)
            return points, normals
        if isinstance(source, o3d.geometry.TriangleMesh):
            return _open3d_mesh(source, _count(count), _seed(seed), with_normals)
    raise SourceTypeError(f"{name} must be {ACCEPTED}; got {_type_name(source)}")


def converted_batch(clouds, normals, *, seed=0):
    """``converted`` for each of several clouds (``fit_batch``): (clouds, normals) as
    lists, a cloud's own normals filling in where ``normals`` (None or one entry per
    cloud) gives none. Errors name the cloud when there are several."""
    clouds = list(clouds)
    given = [None] * len(clouds) if normals is None else list(normals)
    if len(given) != len(clouds):
        raise ValueError(f"normals must be one array per cloud ({len(clouds)}), got {len(given)}")
    out, found = [], []
    for i, (source, mine) in enumerate(zip(clouds, given, strict=True)):
        try:
            points, own = converted(source, seed=seed, with_normals=mine is None)
        except ValueError as err:
            if len(clouds) == 1:
                raise
            raise type(err)(f"cloud {i}: {err}") from None
        out.append(points)
        found.append(own if mine is None else mine)
    if normals is None and all(n is None for n in found):
        return out, None
    return out, found


def _open3d_mesh(mesh, count: int, seed: int, with_normals: bool):
    """An Open3D TriangleMesh sampled as the trimesh mesh of its vertices and triangles
    (the same points and face normals for the same seed); its vertices if it has no
    triangles."""
    import trimesh

    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    triangles = np.asarray(mesh.triangles)
    if not len(triangles):
        return vertices, None
    return sample_oriented(trimesh.Trimesh(vertices, triangles, process=False), count, seed,
                           _label(mesh), with_normals=with_normals)


def _array_like(source) -> bool:
    return any(hasattr(source, a) for a in ("__array__", "__array_interface__",
                                              "__array_struct__"))


def _count(count) -> int:
    if isinstance(count, bool) or not isinstance(count, numbers.Integral) or count < 1:
        raise LoadError(f"num_points must be an integer >= 1, got {count!r}")
    return int(count)


def _seed(seed):
    return seed() if callable(seed) else seed


def _label(geometry) -> str:
    """How a geometry is named in errors: by its type."""
    return f"the {_type_name(geometry)} given"


def _type_name(obj) -> str:
    kind = type(obj)
    module = kind.__module__
    return kind.__qualname__ if module == "builtins" else f"{module}.{kind.__qualname__}"
