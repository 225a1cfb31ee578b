"""The five primitives. Each module holds one model class; ``REGISTRY`` maps names to them."""

from ._base import REGISTRY, Cut, Model
from .box import Box
from .cone import Cone
from .cylinder import Cylinder
from .plane import Plane
from .sphere import Sphere

__all__ = ["REGISTRY", "Model", "Cut", "Plane", "Sphere", "Cylinder", "Cone", "Box"]
