"""View windows: the directions (azimuth and elevation, seen from a viewpoint) that boxes cover;
a point outside every window can be neither hidden nor revealed by the boxes."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba as nb
import numpy as np

from drcpo.geometry import bev_corners, wrap_angle

__all__ = [
    "WINDOW_SLACK",
    "box_windows",
    "grown_boxes",
    "in_windows",
    "view_windows",
    "window_spans",
]

WINDOW_SLACK = 0.1  # metres added around inserted boxes (construction keeps points 5 cm out)


def grown_boxes(boxes: Sequence[np.ndarray], slack: float = WINDOW_SLACK) -> np.ndarray:
    """Boxes ``(M, 7)`` grown by ``slack`` metres on every side (for view windows)."""
    grown = np.array(boxes, dtype=np.float64).reshape(-1, 7)
    grown[:, 3:6] += 2.0 * slack
    return grown


def view_windows(
    points: np.ndarray, boxes: np.ndarray, viewpoint: np.ndarray, behind: bool = False
) -> np.ndarray:
    """``bool (N,)``: points in the view window of some box seen from ``viewpoint``.

    A box's view window is the range of azimuth (about z) and elevation its volume covers seen
    from the viewpoint; a point in none of them can be neither hidden nor revealed by the box.
    With ``behind``, only points at least as far from the viewpoint as the box's nearest point
    count (nothing nearer can be occluded by it).
    """
    return in_windows(points, window_spans(boxes, viewpoint, behind), viewpoint)


def window_spans(
    boxes: np.ndarray | Sequence[np.ndarray],
    viewpoint: np.ndarray,
    behind: bool = False,
    known: tuple[np.ndarray, ...] | None = None,
) -> np.ndarray | None:
    """The view windows of ``(M, 7)`` boxes (see :func:`view_windows`; ``known``: their
    :func:`box_windows`, if computed already) as ``(K, 5)`` rows (azimuth from, azimuth to,
    elevation from, elevation to, nearest distance), radians and metres: a window across the
    azimuth seam at +-pi is split in two, and the nearest distance is ``-inf`` unless
    ``behind``. ``None`` when the viewpoint lies inside a footprint (every direction)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    if len(boxes) == 0:
        return np.zeros((0, 5))
    if known is None:
        known = box_windows(boxes, viewpoint)
    centre, az_low, az_high, el_low, el_high, nearest = known
    if not np.isfinite(nearest).all():
        return None
    low, high = centre + az_low, centre + az_high
    if not behind:
        nearest = np.full(len(boxes), -np.inf)
    spans = []
    for m in range(len(boxes)):
        parts = [(low[m], high[m])]
        if low[m] < -math.pi:  # the window crosses the azimuth seam at +-pi
            parts = [(-math.pi, high[m]), (low[m] + 2 * math.pi, math.pi)]
        elif high[m] > math.pi:
            parts = [(low[m], math.pi), (-math.pi, high[m] - 2 * math.pi)]
        spans += [(start, stop, el_low[m], el_high[m], nearest[m]) for start, stop in parts]
    return np.array(spans, dtype=np.float64)


def in_windows(points: np.ndarray, windows: np.ndarray | None, viewpoint: np.ndarray) -> np.ndarray:
    """``bool (N,)``: points ``(N, 3+)`` in any of ``windows`` (:func:`window_spans`; ``None``:
    every direction) seen from ``viewpoint`` ``(3,)``."""
    if windows is None:
        return np.ones(len(points), dtype=bool)
    inside = np.zeros(len(points), dtype=bool)
    if len(points) and len(windows):
        _window_scan(np.asarray(points), np.asarray(viewpoint, dtype=np.float64), windows, inside)
    return inside


@nb.njit(cache=True, nogil=True)
def _window_scan(points, viewpoint, windows, inside):  # pragma: no cover - numba
    # Per point, its direction and distance as FrameGrid's (libm's atan2: numpy's vectorised
    # arctan2 may differ in the last bit on some CPUs), then the windows in order until one
    # holds it (radians, metres).
    for i in range(points.shape[0]):
        x = np.float64(points[i, 0]) - viewpoint[0]
        y = np.float64(points[i, 1]) - viewpoint[1]
        z = np.float64(points[i, 2]) - viewpoint[2]
        azimuth, elevation = math.atan2(y, x), math.atan2(z, math.sqrt(x * x + y * y))
        distance = math.sqrt(x * x + y * y + z * z)
        for w in range(windows.shape[0]):
            if (
                azimuth >= windows[w, 0]
                and azimuth <= windows[w, 1]
                and elevation >= windows[w, 2]
                and elevation <= windows[w, 3]
                and distance >= windows[w, 4]
            ):
                inside[i] = True
                break


def box_windows(boxes: np.ndarray, viewpoint: np.ndarray) -> tuple[np.ndarray, ...]:
    """View windows of ``(M, 7)`` boxes seen from ``viewpoint``, each ``(M,)``: centre
    azimuth, azimuth low and high relative to it, elevation low and high (radians), and the
    distance of the box's nearest point (metres; ``inf`` when the viewpoint lies inside the
    footprint, whose window is then every direction)."""
    corners = bev_corners(boxes) - viewpoint[:2]  # (M, 4, 2)
    cos, sin = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    dx, dy = viewpoint[0] - boxes[:, 0], viewpoint[1] - boxes[:, 1]
    local = np.column_stack([dx * cos + dy * sin, -dx * sin + dy * cos])
    gap = np.maximum(np.abs(local) - boxes[:, 3:5] / 2.0, 0.0)
    near = np.hypot(gap[:, 0], gap[:, 1])  # nearest footprint point, horizontally
    far = np.hypot(corners[..., 0], corners[..., 1]).max(axis=1)
    centre = np.arctan2(boxes[:, 1] - viewpoint[1], boxes[:, 0] - viewpoint[0])
    spread = wrap_angle(np.arctan2(corners[..., 1], corners[..., 0]) - centre[:, None])
    top = boxes[:, 2] + boxes[:, 5] / 2.0 - viewpoint[2]
    bottom = boxes[:, 2] - boxes[:, 5] / 2.0 - viewpoint[2]
    el_high = np.arctan2(top, np.where(top > 0, near, far))
    el_low = np.arctan2(bottom, np.where(bottom < 0, near, far))
    vertical = np.maximum(np.maximum(bottom, 0.0), -top)
    nearest = np.where(near > 0, np.hypot(near, vertical), np.inf)
    return centre, spread.min(axis=1), spread.max(axis=1), el_low, el_high, nearest
