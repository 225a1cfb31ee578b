"""The primitives: one model class per module, registered in ``REGISTRY`` (name -> class)
when its module is imported here. The rest of jaxfit reads what it needs about a primitive
from its class (``Model``; docs/shapes.md), so a new one is its file plus one line here."""

from ._base import REGISTRY, Cut, Model, allclose, mass_properties, trimesh_scene
from .box import Box
from .cone import Cone
from .cylinder import Cylinder
from .plane import Plane
from .sphere import Sphere

__all__ = ["REGISTRY", "Model", "Cut", "Plane", "Sphere", "Cylinder", "Cone", "Box",
           "mass_properties", "allclose", "trimesh_scene"]
