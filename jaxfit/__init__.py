"""jaxfit: batched RANSAC/MSAC fitting of primitive shapes to 3-D point clouds, in JAX."""

import importlib
import importlib.abc
import importlib.util
import sys
import types

from . import _cache, _malloc
from ._cache import compilation_cache_dir
from ._checks import FitError
from .engine import Bounds, FitOptions, FitResult, Status, fit, fit_batch
from .shapes import Box, Cone, Cylinder, Model, Plane, Sphere, allclose

_malloc.keep_freed_memory()

#: Public names imported from their module on first use (PEP 562 ``__getattr__``), not by
#: ``import jaxfit``: a process that only fits skips their imports (docs/engine.md,
#: "Compile cost, this round"). name -> module, relative to this package.
LAZY = {
    "run_batch": "batch",
    "Decomposition": "decomposition", "Part": "decomposition", "decompose": "decomposition",
    "Detection": "detect", "Scene": "detect", "detect": "detect",
    "Grasps": "grasping", "ParallelJaw": "grasping", "grasps": "grasping",
    "SourceTypeError": "io", "as_cloud": "io", "load_cloud": "io", "load_points": "io",
    "estimate_normals": "normals",
    "warmup": "warmup",
}
#: Subpackages and modules ``import jaxfit`` used to import, still given as attributes
#: (``jaxfit.grasping.clears_support``): imported on first use too.
SUBMODULES = frozenset({"batch", "decomposition", "grasping", "io", "normals"})

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


class _Package(types.ModuleType):
    """This package's module type: a public name (``LAZY``) that is also a moved module's
    old name (the function ``decompose``, the module ``jaxfit.decompose``) stays the
    public object when ``import jaxfit.decompose`` sets the module on the package."""

    def __setattr__(self, name, value):
        if name in LAZY and isinstance(value, types.ModuleType):
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package


def __getattr__(name):
    if name in LAZY:
        value = getattr(importlib.import_module(f"{__name__}.{LAZY[name]}"), name)
        globals()[name] = value
        return value
    if name in MOVED or name in SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(LAZY) | SUBMODULES)


# Before any jit compiles: later processes load our kernels from disk (see _cache.py).
_cache.enable()
__version__ = "0.1.0"
