"""Points and meshes in and out: point and mesh files as (N, 3) float64 clouds
(``points``), any source the API takes (arrays, trimesh and Open3D objects, paths) as
points and normals (``inputs``), GraspIt!'s Open Inventor models (``iv``), and headless previews
(``preview``). None of them uses jax; trimesh and matplotlib are imported only where a
mesh is read or a picture drawn (``import jaxfit`` itself loads jax)."""

from .inputs import MESH_POINTS, SourceTypeError, as_cloud
from .points import SUPPORTED_EXTENSIONS, LoadError, load_cloud, load_points, sample_surface

__all__ = ["load_points", "load_cloud", "as_cloud", "sample_surface", "LoadError",
           "SourceTypeError", "SUPPORTED_EXTENSIONS", "MESH_POINTS"]
