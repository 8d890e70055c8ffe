"""View windows: the directions (azimuth and elevation, seen from a viewpoint) that boxes cover;
a point outside every window can be neither hidden nor revealed by the boxes. Also the samples
on the faces of boxes that look towards a viewpoint (:func:`surface_samples`: placement's
pre-build "occluded" test)."""

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
    "surface_samples",
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


def _face_grids(steps: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Unit-box grids on the four sides and the top: ``(5, K, 3)`` and the faces' outward
    ``(axis, sign)`` pairs ``(5, 2)`` (the bottom rests on the ground, no one sees it)."""
    u, v = np.meshgrid(np.linspace(-0.5, 0.5, steps[0]), np.linspace(-0.5, 0.5, steps[1]))
    faces = ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0), (2, 1.0))
    grids = np.zeros((len(faces), u.size, 3))
    for f, (axis, sign) in enumerate(faces):
        u_axis, v_axis = (a for a in range(3) if a != axis)
        grids[f, :, u_axis], grids[f, :, v_axis], grids[f, :, axis] = (
            u.ravel(),
            v.ravel(),
            0.5 * sign,
        )
    return grids, np.array(faces)


# 5 x 4 from edge to edge: an object e-HPR keeps often shows only a rim above an occluder.
_SURFACE_GRIDS, _FACES = _face_grids((5, 4))


def surface_samples(boxes: np.ndarray, viewpoint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points on the faces of each ``(M, 7)`` box that look towards ``viewpoint`` ``(3,)``:
    a 5 x 4 grid from edge to edge on each such side or top, ``(S, 3)`` metres, box ``m``'s
    being rows ``offsets[m]:offsets[m + 1]`` of ``offsets`` ``int64 (M + 1,)``."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    cos, sin = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    rel = viewpoint - boxes[:, :3]
    view = np.column_stack(
        [rel[:, 0] * cos + rel[:, 1] * sin, -rel[:, 0] * sin + rel[:, 1] * cos, rel[:, 2]]
    )
    axes, signs = _FACES[:, 0].astype(int), _FACES[:, 1]
    facing = signs * view[:, axes] > boxes[:, 3:6][:, axes] / 2.0
    local = _SURFACE_GRIDS[None] * boxes[:, None, None, 3:6]
    world = np.empty_like(local)
    c, s_ = cos[:, None, None], sin[:, None, None]
    world[..., 0] = c * local[..., 0] - s_ * local[..., 1] + boxes[:, None, None, 0]
    world[..., 1] = s_ * local[..., 0] + c * local[..., 1] + boxes[:, None, None, 1]
    world[..., 2] = local[..., 2] + boxes[:, None, None, 2]
    counts = facing.sum(axis=1) * _SURFACE_GRIDS.shape[1]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return world[facing].reshape(-1, 3), offsets
