"""BEV footprint collisions: whether boxes' footprints overlap (placement's and ground-truth
sampling's test), by a separating-axis test on the edge normals."""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from drcpo.geometry import heading_terms

__all__ = ["bev_collisions", "first_come"]


class _Footprints(NamedTuple):
    boxes: np.ndarray  # (K, 7)
    cos: np.ndarray  # (K,) of the headings, as drcpo.geometry.heading_terms gives them
    sin: np.ndarray


def _footprints(boxes: np.ndarray) -> _Footprints:
    return _Footprints(boxes, *heading_terms(boxes))


def bev_collisions(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """``bool (A, B)``: whether the BEV footprints of ``(A, 7)`` and ``(B, 7)`` boxes overlap,
    i.e. their interiors intersect (:func:`drcpo.geometry.bev_overlap_area` ``> 0``; boxes that
    only touch do not collide).

    A separating-axis test on the four edge normals, exact up to float rounding (footprints
    within about 1e-12 m of touching may go either way, as the overlap area's own rounding does).
    """
    boxes_a = np.asarray(boxes_a, dtype=np.float64).reshape(-1, 7)
    boxes_b = np.asarray(boxes_b, dtype=np.float64).reshape(-1, 7)
    out = np.zeros((len(boxes_a), len(boxes_b)), dtype=bool)
    if out.size:
        _collisions(_footprints(boxes_a), _footprints(boxes_b), out)
    return out


def first_come(boxes: np.ndarray, objects: np.ndarray) -> np.ndarray:
    """``bool (K,)``: each of the ``(K, 7)`` boxes kept unless its footprint overlaps an earlier
    kept box of another object (``objects`` ``(K,)``: an object's own boxes are alternative
    poses, at most one of them placed)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    kept = np.zeros(len(boxes), dtype=bool)
    if len(boxes):
        _first_come(_footprints(boxes), np.asarray(objects, dtype=np.int64), kept)
    return kept


@numba.njit(cache=True, nogil=True, inline="always")
def _projected_half(u_x, u_y, length, width, c, s):  # pragma: no cover - numba
    # Half the extent along the unit axis (u_x, u_y) of a length x width footprint whose
    # length runs along (c, s).
    return length / 2.0 * abs(u_x * c + u_y * s) + width / 2.0 * abs(-u_x * s + u_y * c)


@numba.njit(cache=True, nogil=True, inline="always")
def _overlap(a, i, b, j):  # pragma: no cover - numba
    # Interiors of footprint i of a and j of b intersect <=> on every edge normal of either
    # the projections overlap by more than zero (convex polygons: a separating line can be
    # taken along an edge).
    box_a, box_b = a.boxes[i], b.boxes[j]
    al, aw, ca, sa = box_a[3], box_a[4], a.cos[i], a.sin[i]
    bl, bw, cb, sb = box_b[3], box_b[4], b.cos[j], b.sin[j]
    dx, dy = box_b[0] - box_a[0], box_b[1] - box_a[1]
    reach = math.sqrt(al * al + aw * aw) / 2.0 + math.sqrt(bl * bl + bw * bw) / 2.0
    if dx * dx + dy * dy >= reach * reach:
        return False
    if abs(dx * ca + dy * sa) >= al / 2.0 + _projected_half(ca, sa, bl, bw, cb, sb):
        return False
    if abs(-dx * sa + dy * ca) >= aw / 2.0 + _projected_half(-sa, ca, bl, bw, cb, sb):
        return False
    if abs(dx * cb + dy * sb) >= bl / 2.0 + _projected_half(cb, sb, al, aw, ca, sa):
        return False
    return abs(-dx * sb + dy * cb) < bw / 2.0 + _projected_half(-sb, cb, al, aw, ca, sa)


@numba.njit(cache=True, nogil=True)
def _collisions(a, b, out):  # pragma: no cover - numba
    for i in range(a.boxes.shape[0]):
        for j in range(b.boxes.shape[0]):
            out[i, j] = _overlap(a, i, b, j)


@numba.njit(cache=True, nogil=True)
def _first_come(footprints, objects, kept):  # pragma: no cover - numba
    # Each box is kept unless it overlaps an earlier box of another object that was kept (an
    # object's own poses are alternatives: at most one is placed).
    for i in range(footprints.boxes.shape[0]):
        kept[i] = True
        for j in range(i):
            if kept[j] and objects[j] != objects[i] and _overlap(footprints, i, footprints, j):
                kept[i] = False
                break
