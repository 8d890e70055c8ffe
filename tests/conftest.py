"""Shared fixtures. Tests that need the real data in ``../shared`` skip when it is absent."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
KITTI_SAMPLE = SHARED / "data" / "kitti_sample"
HPR_FIXTURES = SHARED / "fixtures" / "hpr"


@pytest.fixture
def kitti_sample() -> Path:
    if not (KITTI_SAMPLE / "training" / "velodyne").is_dir():
        pytest.skip(
            f"real KITTI sample not found at {KITTI_SAMPLE} (only CI and developers have it)"
        )
    return KITTI_SAMPLE


@pytest.fixture
def hpr_fixtures() -> Path:
    if not HPR_FIXTURES.is_dir():
        pytest.skip(f"HPR fixtures not found at {HPR_FIXTURES} (only CI and developers have it)")
    return HPR_FIXTURES


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


def random_boxes(rng: np.random.Generator, n: int, spread: float = 5.0) -> np.ndarray:
    """``(n, 7)`` random boxes with centres in a cube of side ``2 * spread``."""
    return np.column_stack(
        [
            rng.uniform(-spread, spread, (n, 3)),
            rng.uniform(0.2, 4.0, (n, 3)),
            rng.uniform(-2 * np.pi, 2 * np.pi, n),
        ]
    )
