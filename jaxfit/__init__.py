"""jaxfit: batched RANSAC/MSAC fitting of primitive shapes to 3-D point clouds, in JAX."""

from . import _cache
from ._cache import compilation_cache_dir
from ._checks import FitError

# The function shadows its module's name on the package, so that jaxfit.decompose(...)
# is the PSDA; `from jaxfit.decompose import ...` still reaches the module.
from .decompose import Decomposition, Part, decompose
from .detect import Detection, Scene, detect
from .normals import estimate_normals
from .ransac import FitResult, Status, fit, fit_batch
from .shapes import Box, Cone, Cylinder, Model, Plane, Sphere

__all__ = [
    "fit", "fit_batch", "decompose", "Decomposition", "Part", "FitResult", "Status", "FitError",
    "Model", "Plane", "Sphere", "Cylinder", "Cone", "Box", "compilation_cache_dir",
    "estimate_normals", "detect", "Detection", "Scene",
]

# Before any jit compiles: later processes load our kernels from disk (see _cache.py).
_cache.enable()
__version__ = "0.1.0"
