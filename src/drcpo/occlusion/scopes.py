"""s-HPR, the paper's self-occlusion of each placed object (:func:`self_occlusion`); e-HPR is in
:mod:`drcpo.occlusion.external`. Imports the other
:mod:`drcpo.occlusion` modules.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from drcpo.errors import DataError
from drcpo.occlusion.checks import _check_radius
from drcpo.occlusion.hpr import hidden_point_removal

__all__ = ["self_occlusion"]


def self_occlusion(
    points: np.ndarray,
    box: np.ndarray,
    radius_factor: float = 200.0,
    *,
    viewpoint: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    method: str = "auto",
) -> np.ndarray:
    """s-HPR: the paper's self-occlusion of one placed object, seen from the sensor.

    Args:
        points: ``(N, 3 + C)`` the object's points in the LiDAR frame (metres).
        box: ``(7,)`` (or ``(1, 7)``) the object's box; ``R = diagonal * radius_factor``.
        radius_factor: the paper uses 200.
        viewpoint: ``(3,)`` the sensor position, metres (the origin in the paper).
        method: as in :func:`hidden_point_removal`.

    Returns:
        ``bool (N,)``: points kept (visible).
    """
    box = np.asarray(box, dtype=np.float64)
    if box.size != 7:
        raise DataError(f"self_occlusion: box must have 7 values, got shape {box.shape}")
    # geometry.box_diagonal's sum, in the same order, without its array overhead (per object)
    dx, dy, dz = box.reshape(7)[3:6].tolist()
    diagonal = math.sqrt(dx * dx + dy * dy + dz * dz)
    factor = _check_radius(radius_factor, "radius_factor")
    if not diagonal > 0.0:
        raise DataError(f"self_occlusion: the box has no extent (diagonal {diagonal})")
    return hidden_point_removal(points, viewpoint, diagonal * factor, method=method)
