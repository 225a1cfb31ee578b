"""``FitResult``: what ``fit`` and ``fit_batch`` give back for one cloud."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..shapes import Model
from ..shapes._base import short
from .stopping import Status


@dataclasses.dataclass(frozen=True, repr=False)
class FitResult:
    """Outcome of ``jaxfit.fit``.

    model : the fitted, bounded primitive (in the input's coordinates).
    inliers : (N,) bool, points within ``threshold`` of the bounded model
        (``model.distance``); ``inlier_indices`` gives them as indices.
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

    @property
    def inlier_indices(self) -> np.ndarray:
        """(num_inliers,) ascending indices of the inliers into the fitted points."""
        return np.flatnonzero(self.inliers)

    @property
    def num_points(self) -> int:
        """N, the number of points fitted."""
        return int(np.size(self.inliers))

    def to_dict(self) -> dict:
        """JSON-ready: the model (``Model.to_dict``), the inliers as ascending indices
        with the number of points (so ``from_dict`` rebuilds the mask), and the scalars,
        the status by its value ("converged", ...)."""
        return {"model": self.model.to_dict(), "num_points": self.num_points,
                "num_inliers": int(self.num_inliers),
                "inlier_indices": self.inlier_indices.tolist(), "cost": float(self.cost),
                "num_hypotheses": int(self.num_hypotheses), "status": Status(self.status).value,
                "threshold": float(self.threshold)}

    @classmethod
    def from_dict(cls, data: dict) -> FitResult:
        """Inverse of ``to_dict``; ValueError naming what is missing or out of range."""
        missing = [k for k in ("model", "num_points", "inlier_indices", "cost",
                               "num_hypotheses", "status", "threshold") if k not in data]
        if missing:
            raise ValueError(f"FitResult dictionary is missing {', '.join(missing)}")
        n = int(data["num_points"])
        indices = np.asarray(data["inlier_indices"], dtype=np.int64).reshape(-1)
        if indices.size and (indices.min() < 0 or indices.max() >= n):
            raise ValueError(f"inlier_indices must lie in 0...{n - 1}")
        inliers = np.zeros(n, bool)
        inliers[indices] = True
        return cls(Model.from_dict(data["model"]), inliers, int(inliers.sum()),
                   float(data["cost"]), int(data["num_hypotheses"]), Status(data["status"]),
                   float(data["threshold"]))

    def __repr__(self):
        """One line: the model, the inlier count (not the mask), the scalars as plain
        floats."""
        return (f"FitResult(model={self.model!r}, inliers={int(self.num_inliers)} of "
                f"{self.num_points}, cost={short(self.cost)}, "
                f"num_hypotheses={int(self.num_hypotheses)}, "
                f"status={Status(self.status).value!r}, threshold={short(self.threshold)})")
