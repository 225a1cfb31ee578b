"""The fitting engine: RANSAC as stages that can be swapped, one fused kernel, one loop.

Stages (each a small interface with today's choice as default, passed to the kernels as
a static, hashable object; ``FitOptions`` holds them):

- ``sampling``: which points form each minimal sample (``UniformSampler``);
- the shape's estimator (``jaxfit.shapes``): closed-form hypotheses from samples, under
  ``vmap``;
- ``scoring``: what a point costs a hypothesis (``MSAC``), scanned in chunks;
- ``refine``: local optimisation of a new best hypothesis (``LevenbergMarquardt``);
- ``stopping``: when a cloud has enough hypotheses (``AdaptiveStopping``).

Around them: ``options`` (``FitOptions`` checked once, ``Bounds``), ``cloud`` (input
preparation), ``keys`` (where randomness comes from), ``kernel`` (the jitted entry
points), ``backend`` (every device-specific choice), ``loop`` (the host loop), ``fit``
(``fit``, ``fit_batch`` and result building), ``result`` (``FitResult``).
"""

from .cloud import DEFAULT_THRESHOLD_FRACTION, bucket_size, default_threshold
from .fit import fit, fit_batch
from .options import Bounds, FitOptions
from .refine import LevenbergMarquardt, LocalOptimizer
from .result import FitResult
from .sampling import Sampler, UniformSampler
from .scoring import MSAC, Scorer
from .stopping import AdaptiveStopping, Status, StoppingRule, required_hypotheses

__all__ = [
    "fit", "fit_batch", "FitResult", "FitOptions", "Bounds", "Status", "Sampler",
    "UniformSampler", "Scorer", "MSAC", "LocalOptimizer", "LevenbergMarquardt",
    "StoppingRule", "AdaptiveStopping", "required_hypotheses", "bucket_size",
    "DEFAULT_THRESHOLD_FRACTION", "default_threshold",
]
