"""Points and meshes in and out: point and mesh files as (N, 3) float64 clouds
(``points``), GraspIt!'s Open Inventor models (``iv``), and headless previews
(``preview``). None of them uses jax; trimesh and matplotlib are imported only where a
mesh is read or a picture drawn (``import jaxfit`` itself loads jax)."""

from .points import SUPPORTED_EXTENSIONS, LoadError, load_points, sample_surface

__all__ = ["load_points", "sample_surface", "LoadError", "SUPPORTED_EXTENSIONS"]
