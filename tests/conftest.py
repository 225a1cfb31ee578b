"""Shared fixtures. Kernels compile once per (shape, batch size, point bucket): tests use
the default batch size and clouds of 2000 points (bucket 2048) or fewer than 1024
points (bucket 1024), so the whole suite compiles each kernel at most twice."""

from pathlib import Path

import numpy as np
import pytest

from jaxfit.shapes import REGISTRY

SHAPES = sorted(REGISTRY)
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def data_dir():
    if not DATA.is_dir():
        pytest.skip(f"shared data not found at {DATA} (it sits beside the checkout)")
    return DATA


def axis_angle_deg(a, b):
    """Angle in degrees between two lines (signs ignored)."""
    c = abs(float(np.dot(a, b))) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(min(1.0, c))))


def matches(fitted, true, tolerance):
    """Whether a fitted primitive is within ``tolerance`` of the true one: every relative
    size error, and every direction error in radians."""
    from jaxfit.evaluation.measures import errors

    if type(fitted) is not type(true):
        return False
    e = errors(true, fitted)
    rel = [v for k, v in e.items() if k.endswith("_rel") or k == "side_rel_max"]
    angles = [np.radians(v) for k, v in e.items() if k.endswith("_deg")]
    return all(v <= tolerance for v in rel + angles)
