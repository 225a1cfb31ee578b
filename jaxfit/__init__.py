"""jaxfit: batched RANSAC/MSAC fitting of primitive shapes to 3-D point clouds, in JAX."""

import importlib
import importlib.abc
import importlib.util
import sys

from . import _cache
from ._cache import compilation_cache_dir
from ._checks import FitError
from .batch import run_batch
from .decomposition import Decomposition, Part, decompose
from .detect import Detection, Scene, detect
from .engine import Bounds, FitOptions, FitResult, Status, fit, fit_batch
from .grasping import Grasps, ParallelJaw, grasps
from .io import SourceTypeError, as_cloud, load_cloud, load_points
from .normals import estimate_normals
from .shapes import Box, Cone, Cylinder, Model, Plane, Sphere, allclose
from .warmup import warmup

__all__ = [
    "fit", "fit_batch", "FitOptions", "Bounds", "FitResult", "Status", "FitError", "decompose",
    "Decomposition", "Part",
    "Model", "Plane", "Sphere", "Cylinder", "Cone", "Box", "compilation_cache_dir",
    "estimate_normals", "detect", "Detection", "Scene", "grasps", "Grasps", "ParallelJaw",
    "as_cloud", "load_points", "load_cloud", "SourceTypeError", "allclose", "run_batch",
    "warmup",
]

#: Modules of the flat layout of jaxfit 0.1 -> where they live now. ``import
#: jaxfit.scenarios`` and ``from jaxfit import scenarios`` still work and give the new
#: module itself, imported only when first asked for (most pull in trimesh or matplotlib).
MOVED = {
    "ransac": "engine",
    "boxdecomp": "decomposition.boxdecomp",
    "decompose": "decomposition.psda",
    "iv": "io.iv",
    "preview": "io.preview",
    "scenarios": "evaluation.scenarios",
    "synthetic": "evaluation.synthetic",
    "reference": "evaluation.reference",
    "evaluate": "evaluation.evaluate",
}


class _MovedFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Resolves ``jaxfit.<old name>`` to the module ``MOVED`` names."""

    def find_spec(self, name, path=None, target=None):
        old = name.removeprefix(__name__ + ".")
        return importlib.util.spec_from_loader(name, self) if old in MOVED else None

    def create_module(self, spec):
        return importlib.import_module(f"{__name__}.{MOVED[spec.name.rpartition('.')[2]]}")

    def exec_module(self, module):
        pass  # the module is the moved one, already executed


sys.meta_path.append(_MovedFinder())
# The function ``decompose`` shadows its old module's name on the package; the module is
# registered now so that a later ``import jaxfit.decompose`` does not replace the function.
sys.modules[f"{__name__}.decompose"] = sys.modules[f"{__name__}.decomposition.psda"]


def __getattr__(name):
    if name in MOVED:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# Before any jit compiles: later processes load our kernels from disk (see _cache.py).
_cache.enable()
__version__ = "0.1.0"
