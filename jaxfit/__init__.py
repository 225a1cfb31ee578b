"""jaxfit: batched RANSAC/MSAC fitting of primitive shapes to 3-D point clouds, in JAX."""

from ._checks import FitError

# The function shadows its module's name on the package, so that jaxfit.decompose(...)
# is the PSDA; `from jaxfit.decompose import ...` still reaches the module.
from .decompose import Decomposition, Part, decompose
from .ransac import FitResult, Status, fit, fit_batch
from .shapes import Box, Cone, Cylinder, Model, Plane, Sphere

__all__ = [
    "fit", "fit_batch", "decompose", "Decomposition", "Part", "FitResult", "Status", "FitError",
    "Model", "Plane", "Sphere", "Cylinder", "Cone", "Box",
]
__version__ = "0.1.0"
