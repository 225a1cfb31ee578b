"""Stopping rules: when the host loop stops drawing hypotheses for a cloud.

A rule runs on the host after every batch, once per searching cloud; a new rule is one
new class with ``status`` of the same contract. The hypothesis budget
(``max_hypotheses``) is the loop's own and applies to every rule.
"""

from __future__ import annotations

import dataclasses
import enum
import math


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
