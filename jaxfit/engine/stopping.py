"""Stopping rules: when the host loop stops drawing hypotheses for a cloud.

A rule runs on the host after every batch, once per searching cloud; a new rule is one
new class with ``status`` of the same contract. The hypothesis budget
(``max_hypotheses``) is the loop's own and applies to every rule.
"""

from __future__ import annotations

import dataclasses
import enum
import math

import numpy as np

#: ``AdaptiveStopping.status_many`` asks ``status`` for a cloud whose quotient T lies
#: within this relative distance of an integer (far above NumPy's few-ulp differences).
NEAR_INTEGER = 1e-9
#: Clouds from which ``AdaptiveStopping.status_many`` uses array code.
ARRAY_MIN = 32


class Status(str, enum.Enum):
    """Why the hypothesis loop stopped."""

    CONVERGED = "converged"  # the confidence-based hypothesis count T was reached
    MAX_HYPOTHESES = "max_hypotheses"  # the max_hypotheses budget ran out first
    STALLED = "stalled"  # max_stall hypotheses in a row brought no better model


def required_hypotheses(inlier_ratio: float, sample_size: int, confidence: float) -> float:
    """T = log(1 - p) / log(1 - w^k): hypotheses needed to draw one all-inlier sample
    with probability ``confidence`` (p) when a fraction w of the points are inliers."""
    if inlier_ratio <= 0:
        return math.inf
    if inlier_ratio >= 1:
        return 1.0
    all_inlier = inlier_ratio**sample_size
    if all_inlier <= 0:
        return math.inf
    return math.ceil(math.log1p(-confidence) / math.log1p(-all_inlier))


class StoppingRule:
    """Interface (frozen and hashable).

    status(inliers, points, drawn, since_best, sample_size, options) -> Status or None
        (go on), for one cloud: ``inliers`` of its best model so far among ``points``,
        ``drawn`` hypotheses so far, ``since_best`` of them since the best improved,
        the estimator's ``sample_size``, and the checked ``FitOptions``.
    """

    def status(self, inliers: int, points: int, drawn: int, since_best: int,
               sample_size: int, options) -> Status | None:  # pragma: no cover
        raise NotImplementedError

    def status_many(self, inliers, points, drawn, since_best, sample_size: int,
                    options) -> list:
        """``status`` of several clouds at once: inliers, points, drawn, since_best (C,)
        -> C Status or None. This default asks ``status`` cloud by cloud; a rule may
        override it with array code (the host loop asks every searching cloud after
        every batch: a Python call each was ~4 us, 1000 clouds ~4 ms a batch)."""
        return [self.status(*values, sample_size, options)
                for values in zip(inliers.tolist(), points.tolist(), drawn.tolist(),
                                  since_best.tolist(), strict=True)]


@dataclasses.dataclass(frozen=True)
class AdaptiveStopping(StoppingRule):
    """RANSAC's adaptive rule: converged once ``drawn`` reaches T for the best model's
    inlier ratio (``required_hypotheses`` at ``options.confidence``, floored at
    ``options.min_hypotheses``); stalled after ``options.max_stall`` without a better one."""

    def status(self, inliers, points, drawn, since_best, sample_size, options):
        needed = max(required_hypotheses(inliers / points, sample_size, options.confidence),
                     options.min_hypotheses)
        if drawn >= needed:
            return Status.CONVERGED
        if since_best >= options.max_stall:
            return Status.STALLED
        return None

    def status_many(self, inliers, points, drawn, since_best, sample_size, options):
        """``status`` for arrays (C,), with the same answers: NumPy's SIMD ``log1p`` and
        ``power`` differ from the math module's by a few ulp, which moves T only where
        the quotient lies within that of an integer; those clouds ask ``status``. Fewer
        than ``ARRAY_MIN`` clouds ask ``status`` one by one (~4 us each, where the array
        code costs ~40 us whatever the count)."""
        if len(inliers) < ARRAY_MIN:
            return super().status_many(inliers, points, drawn, since_best, sample_size,
                                       options)
        ratio = np.asarray(inliers, np.float64) / np.asarray(points, np.float64)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            all_inlier = ratio**sample_size
            quotient = math.log1p(-options.confidence) / np.log1p(-all_inlier)
            near = (ratio > 0) & (ratio < 1) & (all_inlier > 0) & ~(
                np.abs(quotient - np.rint(quotient)) > NEAR_INTEGER * np.abs(quotient))
        needed = np.where(ratio >= 1, 1.0, np.where((ratio <= 0) | (all_inlier <= 0), np.inf,
                                                    np.ceil(quotient)))
        needed = np.maximum(needed, options.min_hypotheses)
        stops = np.where(drawn >= needed, 1, np.where(since_best >= options.max_stall, 2, 0))
        out = [None, Status.CONVERGED, Status.STALLED]
        answers = [out[s] for s in stops.tolist()]
        for i in np.flatnonzero(near).tolist():
            answers[i] = self.status(float(inliers[i]), int(points[i]), int(drawn[i]),
                                     int(since_best[i]), sample_size, options)
        return answers
