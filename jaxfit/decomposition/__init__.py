"""Whole objects as sets of primitives: BoxDecomposition (``boxdecomp``), the PSDA that
fits every primitive to every part (``psda``), the hull-depth kernel it uses to find
hollow parts (``hull``), the two-sided score (``measure``) and the split search driven
by it (``measured``: ``decompose(method="measured")``)."""

from .boxdecomp import BoxNode, BoxTree, decompose_boxes, mvbb
from .psda import Candidate, Decomposition, Part, decompose, load_source

__all__ = ["decompose", "Decomposition", "Part", "Candidate", "load_source", "decompose_boxes",
           "mvbb", "BoxTree", "BoxNode"]
