"""``FitResult``: what ``fit`` and ``fit_batch`` give back for one cloud."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..shapes import Model
from .stopping import Status


@dataclasses.dataclass(frozen=True)
class FitResult:
    """Outcome of ``jaxfit.fit``.

    model : the fitted, bounded primitive (in the input's coordinates).
    inliers : (N,) bool, points within ``threshold`` of the bounded model
        (``model.distance``).
    num_inliers : int.
    cost : MSAC cost sum(min(e^2, threshold^2)) of the final model over all points.
    num_hypotheses : hypotheses drawn and scored.
    status : a ``Status``.
    threshold : the inlier threshold used (the default if none was given).
    """

    model: Model
    inliers: np.ndarray
    num_inliers: int
    cost: float
    num_hypotheses: int
    status: Status
    threshold: float
