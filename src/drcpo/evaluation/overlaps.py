"""Overlaps of KITTI boxes, pair by pair: 2D image IoU, bird's-eye-view IoU, 3D IoU.

KITTI camera boxes are ``(P, 7)`` rows ``x, y, z, l, h, w, ry`` in rectified camera
coordinates: ``(x, y, z)`` is the bottom centre (camera y points down, so the box spans
``y - h .. y``), ``l`` lies along the heading ``(cos ry, -sin ry)`` in the x-z plane and ``w``
across it. Every function takes paired rows (row i of ``a`` with row i of ``b``), so a caller
computes only the pairs it needs (those of one frame) instead of full matrices.
"""

from __future__ import annotations

import numpy as np

from drcpo.geometry import _convex_intersection_area, bev_corners

__all__ = [
    "bev_intersection",
    "bev_iou",
    "image_coverage",
    "image_intersection",
    "image_iou",
    "iou3d",
]

_PAIR_BLOCK = 65536  # pairs per vectorised block: bounds temporary memory to ~100 MB


def _paired(a: np.ndarray, b: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, dtype=np.float64).reshape(-1, width)
    b = np.asarray(b, dtype=np.float64).reshape(-1, width)
    if a.shape != b.shape:
        raise ValueError(f"paired boxes must have the same shape, got {a.shape} and {b.shape}")
    return a, b


def image_intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection areas ``(P,)`` of paired image boxes ``(P, 4)`` left, top, right, bottom.

    Widths are ``right - left`` (no +1 pixel), as the KITTI devkit's evaluation.
    """
    a, b = _paired(a, b, 4)
    iw = np.minimum(a[:, 2], b[:, 2]) - np.maximum(a[:, 0], b[:, 0])
    ih = np.minimum(a[:, 3], b[:, 3]) - np.maximum(a[:, 1], b[:, 1])
    return np.where((iw > 0) & (ih > 0), iw * ih, 0.0)


def _area(boxes: np.ndarray) -> np.ndarray:
    return (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])


def image_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU ``(P,)`` of paired image boxes ``(P, 4)``; 0 where they do not overlap."""
    a, b = _paired(a, b, 4)
    inter = image_intersection(a, b)
    union = _area(a) + _area(b) - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=inter > 0)


def image_coverage(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Share ``(P,)`` of each box of ``a`` covered by its partner in ``b`` (image boxes)."""
    a, b = _paired(a, b, 4)
    inter = image_intersection(a, b)
    return np.divide(inter, _area(a), out=np.zeros_like(inter), where=inter > 0)


def bev_intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Bird's-eye-view (x-z plane) intersection areas ``(P,)`` of paired camera boxes ``(P, 7)``.

    Pairs whose footprints' bounding circles are apart are not clipped (area 0).
    """
    a, b = _paired(a, b, 7)
    out = np.zeros(len(a))
    reach = (np.hypot(a[:, 3], a[:, 5]) + np.hypot(b[:, 3], b[:, 5])) / 2
    near = np.flatnonzero(np.hypot(a[:, 0] - b[:, 0], a[:, 2] - b[:, 2]) <= reach * (1 + 1e-9))
    for start in range(0, len(near), _PAIR_BLOCK):
        rows = near[start : start + _PAIR_BLOCK]
        out[rows] = _convex_intersection_area(_footprint(a[rows]), _footprint(b[rows]))
    return out


def _footprint(boxes: np.ndarray) -> np.ndarray:
    """Counter-clockwise x-z corners ``(P, 4, 2)`` of camera boxes.

    In the (x, z) plane the heading ``(cos ry, -sin ry)`` is the angle ``-ry``, so a footprint is
    an ordinary yaw box with yaw ``-ry``, length ``l`` and width ``w``.
    """
    planar = np.column_stack(
        [boxes[:, 0], boxes[:, 2], np.zeros(len(boxes)), boxes[:, 3], boxes[:, 5],
         np.ones(len(boxes)), -boxes[:, 6]]
    )  # fmt: skip
    return bev_corners(planar)


def bev_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Bird's-eye-view IoU ``(P,)`` of paired camera boxes ``(P, 7)``."""
    a, b = _paired(a, b, 7)
    inter = bev_intersection(a, b)
    union = a[:, 3] * a[:, 5] + b[:, 3] * b[:, 5] - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=inter > 0)


def iou3d(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """3D IoU ``(P,)`` of paired camera boxes ``(P, 7)``: footprint overlap times the overlap
    of the height ranges ``y - h .. y`` along camera y."""
    a, b = _paired(a, b, 7)
    tall = np.minimum(a[:, 1], b[:, 1]) - np.maximum(a[:, 1] - a[:, 4], b[:, 1] - b[:, 4])
    inter = np.zeros(len(a))
    rows = np.flatnonzero(tall > 0)
    inter[rows] = bev_intersection(a[rows], b[rows]) * tall[rows]
    union = a[:, 3:6].prod(axis=1) + b[:, 3:6].prod(axis=1) - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=inter > 0)
