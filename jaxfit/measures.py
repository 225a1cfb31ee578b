"""Measures: the single-shape errors of the evaluation (``evaluation.measures``) and the
two-sided measures of a set of primitives against an object (``evaluation.twosided``:
volumetric IoU, Chamfer and Hausdorff distances, surface coverage; docs/measures.md)."""

from .evaluation.measures import *  # noqa: F403
from .evaluation.measures import __all__ as _single
from .evaluation.twosided import *  # noqa: F403
from .evaluation.twosided import __all__ as _twosided

__all__ = [*_single, *_twosided]
