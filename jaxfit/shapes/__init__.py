"""The five primitives. Each module holds one model class; ``REGISTRY`` maps names to them."""

from ._base import REGISTRY, Model
from .box import Box
from .cone import Cone
from .cylinder import Cylinder
from .plane import Plane
from .sphere import Sphere

__all__ = ["REGISTRY", "Model", "Plane", "Sphere", "Cylinder", "Cone", "Box"]
