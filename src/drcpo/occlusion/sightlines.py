"""Which sight lines pass through boxes: an inserted object hides only what lies behind its box.

Occlusion along the rays (:mod:`~drcpo.occlusion.rays`) treats an object's returns as surface
elements sized by their spacing, and :mod:`~drcpo.occlusion.silhouettes` fills the holes
between them; near the outline an element reaches past the box that holds the object, and
would hide frame points beside it that the sensor saw. An object lies in its box, so a point
whose sight line (the segment from the sensor to it) enters no object's box is never hidden by
one: :func:`sight_lines_cross` finds the points that may be. Imports :mod:`drcpo.errors`,
:mod:`drcpo.geometry` and :mod:`drcpo.occlusion.rays` only.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from drcpo.errors import DataError
from drcpo.geometry import heading_terms
from drcpo.occlusion.rays import _slab

__all__ = ["sight_lines_cross"]


def sight_lines_cross(
    points: np.ndarray,
    origin: np.ndarray,
    boxes: np.ndarray,
    own: np.ndarray | None = None,
    margin: float = 0.0,
) -> np.ndarray:
    """``bool (N,)``: whether the segment from ``origin`` to each point enters a box before it.

    Args:
        points: ``(N, 3+)`` metres, LiDAR frame.
        origin: ``(3,)`` the sensor, metres.
        boxes: ``(K, 7)`` the boxes (x, y, z, dx, dy, dz, heading), each grown by ``margin``
            metres on every side.
        own: ``int (N,)`` the box each point belongs to, which its own sight line may cross
            (-1: none); by default none.
        margin: metres, >= 0.

    A segment enters a box when the ray from ``origin`` through the point meets it (slab
    test) at a distance less than the point's; a point inside a box is entered.
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise DataError(f"points must have shape (N, 3+), got {points.shape}")
    xyz = np.ascontiguousarray(points[:, :3], dtype=np.float64)
    if not np.isfinite(xyz).all():
        raise DataError("points hold NaN/inf coordinates")
    origin = np.asarray(origin, dtype=np.float64).reshape(-1)
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise DataError(f"origin must be 3 finite numbers, got {origin}")
    boxes = np.ascontiguousarray(np.asarray(boxes, dtype=np.float64).reshape(-1, 7))
    if not np.isfinite(boxes).all() or (boxes[:, 3:6] < 0).any():
        raise DataError("boxes must be finite with sizes >= 0")
    own = np.full(len(xyz), -1, np.int64) if own is None else np.asarray(own, dtype=np.int64)
    if own.shape != (len(xyz),):
        raise DataError(f"own must have shape ({len(xyz)},), got {own.shape}")
    if not (isinstance(margin, (int, float)) and margin >= 0.0):
        raise DataError(f"margin must be a distance >= 0, got {margin!r}")
    crossed = np.zeros(len(xyz), dtype=bool)
    _cross(xyz, origin, boxes, *heading_terms(boxes), own, float(margin), crossed)
    return crossed


@numba.njit(cache=True, nogil=True)
def _cross(xyz, origin, boxes, cos, sin, own, margin, crossed):  # pragma: no cover - numba
    # the ray's parameter t runs from the origin (0) to the point (1); a box is tested only
    # when the point lies beyond the near side of its bounding circle (seen from the origin)
    # and within the cone of azimuths that circle spans. Both tests are squared or cosine
    # forms with some slack (no atan2 per point): they only pass over boxes the slab test
    # would miss, so the answer is the slab test's.
    ox, oy, oz = origin[0], origin[1], origin[2]
    count = boxes.shape[0]
    ux, uy, cone, near2 = np.empty(count), np.empty(count), np.empty(count), np.empty(count)
    for m in range(count):
        cx, cy = boxes[m, 0] - ox, boxes[m, 1] - oy
        radius = math.hypot(boxes[m, 3] / 2.0 + margin, boxes[m, 4] / 2.0 + margin)
        reach = math.hypot(cx, cy)
        ux[m], uy[m], cone[m], near2[m] = 0.0, 0.0, -2.0, -1.0  # (the origin in the circle)
        if reach > radius * (1.0 + 1e-9) + 1e-9:
            ux[m], uy[m] = cx / reach, cy / reach
            cone[m] = math.cos(math.asin(radius / reach) + 1e-9) - 1e-12
            near2[m] = (reach - radius) ** 2 * (1.0 - 1e-12)
    for i in range(xyz.shape[0]):
        dx, dy, dz = xyz[i, 0] - ox, xyz[i, 1] - oy, xyz[i, 2] - oz
        squared = dx * dx + dy * dy
        horizontal = math.sqrt(squared)
        for m in range(count):
            if m == own[i] or squared < near2[m] or dx * ux[m] + dy * uy[m] < cone[m] * horizontal:
                continue
            b = boxes[m]
            enter, leave = _slab(
                ox, oy, oz, dx, dy, dz, b[0], b[1], b[2],
                b[3] / 2.0 + margin, b[4] / 2.0 + margin, b[5] / 2.0 + margin, cos[m], sin[m],
            )  # fmt: skip
            if enter <= leave and enter < 1.0:
                crossed[i] = True
                break
