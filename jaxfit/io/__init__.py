"""Points and meshes in and out: point and mesh files (``points``), GraspIt!'s Open
Inventor models (``iv``), and headless previews (``preview``). Importing this package
loads neither jax nor trimesh: the CLI reads a ``.npy`` without them."""

from .points import SUPPORTED_EXTENSIONS, LoadError, load_points, sample_surface

__all__ = ["load_points", "sample_surface", "LoadError", "SUPPORTED_EXTENSIONS"]
