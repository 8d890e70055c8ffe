"""Input checks shared by the occlusion modules: points, viewpoint, radius, query.

Each raises :class:`~drcpo.errors.DataError` (bad data) or :class:`~drcpo.errors.ConfigError`
(bad setting) naming the culprit. Imports only :mod:`drcpo.errors`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from drcpo.errors import ConfigError, DataError

__all__ = ["MAX_RADIUS"]

MAX_RADIUS = 1e150  # keeps 2R (and R squared terms) finite in float64


def _check_points(points: np.ndarray) -> np.ndarray:
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] < 3:
        raise DataError(f"points must have shape (N, 3 + C), got {array.shape}")
    if not np.issubdtype(array.dtype, np.number) or np.issubdtype(array.dtype, np.complexfloating):
        raise DataError(f"points must be real numbers, got dtype {array.dtype}")
    xyz = np.ascontiguousarray(array[:, :3], dtype=np.float64)
    if not np.isfinite(xyz).all():
        bad = np.flatnonzero(~np.isfinite(xyz).all(axis=1))
        raise DataError(
            f"points hold NaN/inf coordinates in {len(bad)} rows (first: row {int(bad[0])})"
        )
    return xyz


def _check_viewpoint(viewpoint: Sequence[float] | np.ndarray) -> np.ndarray:
    try:
        center = np.asarray(viewpoint, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as error:
        raise DataError(f"viewpoint must be 3 numbers, got {viewpoint!r}") from error
    # math.isfinite on three floats: a tenth of np.isfinite's call overhead (once per object)
    if center.shape != (3,) or not all(map(math.isfinite, center.tolist())):
        raise DataError(f"viewpoint must be 3 finite numbers, got {viewpoint!r}")
    return center


def _check_radius(radius: float, name: str = "radius") -> float:
    try:
        value = float(radius)
    except (TypeError, ValueError) as error:
        raise ConfigError(f"{name} must be a number, got {radius!r}") from error
    if not (math.isfinite(value) and 0.0 < value <= MAX_RADIUS):
        raise ConfigError(f"{name} must be a finite number in (0, {MAX_RADIUS:g}], got {radius}")
    return value


def _check_query(query: np.ndarray | None, count: int) -> np.ndarray:
    if query is None:
        return np.ones(count, dtype=bool)
    array = np.asarray(query)
    if array.dtype == bool:
        if array.shape != (count,):
            raise DataError(f"query mask must have shape ({count},), got {array.shape}")
        return array
    if array.size and not np.issubdtype(array.dtype, np.integer):
        raise DataError(f"query must be a bool mask or integer indices, got dtype {array.dtype}")
    index = array.astype(np.int64).ravel()
    if index.size and (index.min() < -count or index.max() >= count):
        raise DataError(f"query indices out of range for {count} points")
    mask = np.zeros(count, dtype=bool)
    mask[index] = True
    return mask
