"""Vectorised box and point geometry in the LiDAR frame (see :mod:`drcpo.frame` for conventions).

All functions take numpy arrays, never loop in Python over points, and do not modify their inputs.
Boxes are ``(M, 7)``: x, y, z (centre), dx, dy, dz, heading (radians about +z, from +x to +y).
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = [
    "TWO_PI",
    "bev_corners",
    "bev_iou",
    "bev_overlap_area",
    "box_corners",
    "box_diagonal",
    "box_holding",
    "box_members",
    "boxes_iou3d",
    "canonical_iou3d",
    "from_canonical",
    "heading_terms",
    "in_box",
    "points_in_boxes",
    "rotate_points_z",
    "rotation_matrix_z",
    "rows_in_box",
    "to_canonical",
    "wrap_angle",
]

TWO_PI = 2.0 * np.pi

# Corner order of box_corners: bottom face counter-clockwise seen from above, starting at the
# front-left (+x, +y) corner, then the top face in the same order.
_UNIT_CORNERS = np.array(
    [
        [0.5, 0.5, -0.5],
        [-0.5, 0.5, -0.5],
        [-0.5, -0.5, -0.5],
        [0.5, -0.5, -0.5],
        [0.5, 0.5, 0.5],
        [-0.5, 0.5, 0.5],
        [-0.5, -0.5, 0.5],
        [0.5, -0.5, 0.5],
    ]
)


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Wrap angles (radians) into ``[-pi, pi)``."""
    return (np.asarray(angle, dtype=np.float64) + np.pi) % TWO_PI - np.pi


def rotation_matrix_z(angle: np.ndarray | float) -> np.ndarray:
    """Rotation matrices about +z: ``(..., 3, 3)`` for angles of shape ``(...)`` (radians)."""
    angle = np.asarray(angle, dtype=np.float64)
    cos, sin = np.cos(angle), np.sin(angle)
    zeros, ones = np.zeros_like(angle), np.ones_like(angle)
    rows = [
        np.stack([cos, -sin, zeros], axis=-1),
        np.stack([sin, cos, zeros], axis=-1),
        np.stack([zeros, zeros, ones], axis=-1),
    ]
    return np.stack(rows, axis=-2)


def rotate_points_z(points: np.ndarray, angle: float) -> np.ndarray:
    """Rotate the x, y columns of ``(N, 2+)`` points by ``angle`` radians about the z axis.

    Returns a new array of the same dtype; columns after the second are copied unchanged.
    """
    points = np.asarray(points)
    out = points.copy()
    angle = np.float64(angle)
    # One compiled pass: the float64 products, with numpy's cos and sin, stored as numpy would.
    _rotate_rows(points, np.cos(angle), np.sin(angle), out)
    return out


@nb.njit(cache=True, nogil=True)
def _rotate_rows(points, cos, sin, out):  # pragma: no cover - numba
    for i in range(points.shape[0]):
        x, y = np.float64(points[i, 0]), np.float64(points[i, 1])
        out[i, 0] = cos * x - sin * y
        out[i, 1] = sin * x + cos * y


def _check_boxes(boxes: np.ndarray) -> np.ndarray:
    boxes = np.asarray(boxes, dtype=np.float64)
    if boxes.ndim == 1 and boxes.shape[0] == 7:
        boxes = boxes[None]
    if boxes.ndim != 2 or boxes.shape[1] != 7:
        raise ValueError(f"boxes must have shape (M, 7), got {boxes.shape}")
    return boxes


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """Corners ``(M, 8, 3)`` of ``(M, 7)`` boxes; order documented at ``_UNIT_CORNERS``."""
    boxes = _check_boxes(boxes)
    local = _UNIT_CORNERS[None] * boxes[:, None, 3:6]
    rotation = rotation_matrix_z(boxes[:, 6])
    return np.einsum("mij,mkj->mki", rotation, local) + boxes[:, None, 0:3]


def bev_corners(boxes: np.ndarray) -> np.ndarray:
    """Bird's-eye-view corners ``(M, 4, 2)``, counter-clockwise, of ``(M, 7)`` boxes."""
    return box_corners(boxes)[:, :4, :2]


def to_canonical(points: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Move ``(N, 3+)`` points from the LiDAR frame into the canonical pose of one ``(7,)`` box.

    The box centre goes to the origin and its heading to 0; features are copied unchanged.
    """
    box = np.asarray(box, dtype=np.float64)
    out = np.array(points, copy=True)
    shifted = np.asarray(points)[:, :3].astype(np.float64) - box[:3]
    out[:, :3] = rotate_points_z(shifted, -box[6])
    return out


def from_canonical(points: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Inverse of :func:`to_canonical`: place canonical ``(N, 3+)`` points at ``box``'s pose."""
    box = np.asarray(box, dtype=np.float64)
    out = np.array(points, copy=True)
    rotated = rotate_points_z(np.asarray(points)[:, :3].astype(np.float64), box[6])
    out[:, :3] = rotated + box[:3]
    return out


def heading_terms(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """numpy's cos and sin ``(M,)`` of the headings of ``(M, 7)`` boxes, as the points-in-box
    rule (:func:`in_box`) and every kernel working in a box's frame take them: numba's (libm's)
    cos and sin may differ from numpy's in the last bit."""
    heading = np.ascontiguousarray(np.asarray(boxes, dtype=np.float64).reshape(-1, 7)[:, 6])
    return np.cos(heading), np.sin(heading)


@nb.njit(cache=True, nogil=True, inline="always")
def in_box(px, py, pz, box, cos, sin, margin):  # pragma: no cover - numba
    """THE points-in-box rule: whether the float64 point ``(px, py, pz)`` lies in ``box`` (a
    ``(7,)`` row or a tuple: centre x, y, z, sizes dx, dy, dz; its heading given by ``cos`` and
    ``sin`` from :func:`heading_terms`), grown by ``margin`` metres on every side (negative
    shrinks it).

    Closed boxes: in the box's own frame ``|x| <= dx/2 + margin``, ``|y| <= dy/2 + margin`` and
    ``|z| <= dz/2 + margin``, all in float64, so points exactly on a face count as inside (NaN
    never does). Every exact points-in-box test of drcpo calls this one; numba kernels inline
    it (once inlined, a box row passed in costs nothing measurable: :func:`points_in_boxes`,
    :func:`box_members` and :func:`rows_in_box` time the same as with the six values passed
    one by one). numba's disk cache only notices changes
    to a kernel's own file: after changing this rule, delete the cached kernels
    (``__pycache__/*.nbi``) of the modules that call it.
    """
    ox, oy, oz = px - box[0], py - box[1], pz - box[2]
    local_x = ox * cos + oy * sin
    local_y = -ox * sin + oy * cos
    return (
        abs(local_x) <= box[3] / 2.0 + margin
        and abs(local_y) <= box[4] / 2.0 + margin
        and abs(oz) <= box[5] / 2.0 + margin
    )


def _check_points(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"points must have shape (N, 3+), got {points.shape}")
    if points.dtype not in (np.float32, np.float64):  # the kernels' two specialisations
        points = points.astype(np.float64)
    return points


def points_in_boxes(points: np.ndarray, boxes: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Which points lie in which rotated boxes: ``bool (N, M)``.

    Args:
        points: ``(N, 3+)`` points, metres.
        boxes: ``(M, 7)`` boxes.
        margin: metres added to every half-size (negative shrinks the boxes).

    Boundary rule: :func:`in_box` (closed boxes, float64), so points exactly on a face count
    as inside. The pairs come from :func:`box_members`.
    """
    boxes = _check_boxes(boxes)
    points = _check_points(points)
    out = np.zeros((len(points), len(boxes)), dtype=bool)
    point, box = box_members(points, boxes, margin)
    out[point, box] = True
    return out


_MEMBER_CELLS = 256  # most BEV cells along a side of the grid that finds points near boxes


def box_members(
    points: np.ndarray, boxes: np.ndarray, margin: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Every (point, box) pair with the point inside the box grown by ``margin`` metres
    (:func:`in_box`): ``int64 (P,)`` point indices (ascending; a point's boxes in ascending
    order) and ``int64 (P,)`` box indices.

    One pass over the ``(N, 3+)`` points: each point looks up the boxes whose axis-aligned BEV
    bounds cover its cell of a coarse grid, and is tested exactly against those only.
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    points = _check_points(points)
    if len(boxes) == 0 or len(points) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return _members(points, boxes, *heading_terms(boxes), float(margin), _MEMBER_CELLS)


@nb.njit(cache=True, nogil=True)
def _members(points, boxes, cos, sin, margin, max_cells):  # pragma: no cover - numba
    # A grid over the boxes' axis-aligned BEV bounds (grown by ``margin``) lists, per cell,
    # the boxes covering it. The bounds have some slack: float rounding must not push a point
    # inside a box out.
    count = boxes.shape[0]
    reach = np.empty((count, 2))
    for m in range(count):
        c, s = abs(cos[m]), abs(sin[m])
        grow = margin * (c + s)
        reach[m, 0] = ((boxes[m, 3] * c + boxes[m, 4] * s) / 2.0 + grow) * (1.0 + 1e-9) + 1e-6
        reach[m, 1] = ((boxes[m, 3] * s + boxes[m, 4] * c) / 2.0 + grow) * (1.0 + 1e-9) + 1e-6
    x0, x1 = np.min(boxes[:, 0] - reach[:, 0]), np.max(boxes[:, 0] + reach[:, 0])
    y0, y1 = np.min(boxes[:, 1] - reach[:, 1]), np.max(boxes[:, 1] + reach[:, 1])
    # Cells are found by multiplying with the inverse size (monotone, like division, so a
    # point inside a box lands in a cell its bounds cover).
    per_metre = 1.0 / max(0.5, (x1 - x0) / max_cells, (y1 - y0) / max_cells)
    nx, ny = int((x1 - x0) * per_metre) + 1, int((y1 - y0) * per_metre) + 1
    spans = np.empty((count, 4), np.int64)
    start = np.zeros(nx * ny + 1, np.int32)  # int32: fewer fresh pages to fault in
    for m in range(count):
        spans[m, 0] = int((boxes[m, 0] - reach[m, 0] - x0) * per_metre)
        spans[m, 1] = min(int((boxes[m, 0] + reach[m, 0] - x0) * per_metre), nx - 1)
        spans[m, 2] = int((boxes[m, 1] - reach[m, 1] - y0) * per_metre)
        spans[m, 3] = min(int((boxes[m, 1] + reach[m, 1] - y0) * per_metre), ny - 1)
        for i in range(spans[m, 0], spans[m, 1] + 1):
            for j in range(spans[m, 2], spans[m, 3] + 1):
                start[i * ny + j + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    listed = np.empty(start[nx * ny], np.int32)
    fill = start[:-1].copy()
    for m in range(count):
        for i in range(spans[m, 0], spans[m, 1] + 1):
            for j in range(spans[m, 2], spans[m, 3] + 1):
                listed[fill[i * ny + j]] = m
                fill[i * ny + j] += 1
    found_point = np.empty(64, np.int64)
    found_box = np.empty(64, np.int64)
    found = 0
    for i in range(points.shape[0]):
        px, py = np.float64(points[i, 0]), np.float64(points[i, 1])
        if not (x0 <= px <= x1 and y0 <= py <= y1):  # NaN fails too
            continue
        c = int((px - x0) * per_metre) * ny + int((py - y0) * per_metre)
        if start[c] == start[c + 1]:
            continue
        pz = np.float64(points[i, 2])
        for k in range(start[c], start[c + 1]):
            m = listed[k]
            if in_box(px, py, pz, boxes[m], cos[m], sin[m], margin):
                if found == found_point.shape[0]:
                    found_point = np.concatenate((found_point, np.empty_like(found_point)))
                    found_box = np.concatenate((found_box, np.empty_like(found_box)))
                found_point[found], found_box[found] = i, m
                found += 1
    return found_point[:found].copy(), found_box[:found].copy()


def rows_in_box(
    points: np.ndarray, rows: np.ndarray, box: np.ndarray, margin: float = 0.0
) -> np.ndarray:
    """The ``rows`` (``int64 (k,)``, order kept) of ``(N, 3+)`` points that lie in one ``(7,)``
    box grown by ``margin`` metres (:func:`in_box`): the exact test after a caller's own
    pre-selection of candidate rows."""
    box = np.asarray(box, dtype=np.float64).reshape(7)
    cos, sin = heading_terms(box)
    rows = np.asarray(rows, dtype=np.int64)
    return _rows_inside(_check_points(points), rows, box, cos[0], sin[0], float(margin))


@nb.njit(cache=True, nogil=True)
def _rows_inside(points, rows, box, cos, sin, margin):  # pragma: no cover - numba
    out = np.empty_like(rows)
    kept = 0
    for k in range(rows.shape[0]):
        i = rows[k]
        px, py, pz = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        if in_box(px, py, pz, box, cos, sin, margin):
            out[kept] = i
            kept += 1
    return out[:kept]


def box_holding(box: np.ndarray, points: np.ndarray, pad: float = 1e-4) -> np.ndarray:
    """The ``(7,)`` box, same heading, that holds ``box`` and every one of ``points``.

    Each face moves out only as far as the points beyond it need, plus ``pad`` metres (far
    above the rounding of :func:`points_in_boxes`, which then counts every point as inside);
    a box that already holds all points comes back unchanged.

    Args:
        box: ``(7,)`` box.
        points: ``(N, 3+)`` points, metres.
        pad: metres left between an outlying point and the moved face.
    """
    box = _check_boxes(box)[0]
    points = np.asarray(points)
    if len(points) == 0:
        return box
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"points must have shape (N, 3+), got {points.shape}")
    cos, sin = (terms[0] for terms in heading_terms(box))  # as in_box takes them
    extents = _local_extents(points, box, cos, sin)  # (2, 3): lowest, highest
    half = box[3:6] / 2.0
    if (extents[0] >= -half).all() and (extents[1] <= half).all():
        return box
    low = np.minimum(-half, extents[0] - pad)
    high = np.maximum(half, extents[1] + pad)
    shift = (low + high) / 2.0
    grown = box.copy()
    grown[0] += shift[0] * cos - shift[1] * sin
    grown[1] += shift[0] * sin + shift[1] * cos
    grown[2] += shift[2]
    grown[3:6] = high - low
    return grown


@nb.njit(cache=True, nogil=True)
def _local_extents(points, box, cos, sin):  # pragma: no cover - numba
    # Lowest and highest coordinate of the points in the box's own frame, as in_box computes
    # them (float64).
    out = np.empty((2, 3))
    out[0, :] = np.inf
    out[1, :] = -np.inf
    for i in range(points.shape[0]):
        dx = np.float64(points[i, 0]) - box[0]
        dy = np.float64(points[i, 1]) - box[1]
        local = (dx * cos + dy * sin, -dx * sin + dy * cos, np.float64(points[i, 2]) - box[2])
        for a in range(3):
            out[0, a] = min(out[0, a], local[a])
            out[1, a] = max(out[1, a], local[a])
    return out


def _cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _inside_convex(points: np.ndarray, polygon: np.ndarray, eps: float) -> np.ndarray:
    """``(P, K)`` mask: points ``(P, K, 2)`` inside counter-clockwise polygons ``(P, 4, 2)``."""
    edges = np.roll(polygon, -1, axis=1) - polygon  # (P, 4, 2)
    rel = points[:, :, None, :] - polygon[:, None, :, :]  # (P, K, 4, 2)
    return (_cross2(edges[:, None], rel) >= -eps[:, :, None]).all(axis=-1)


def _convex_intersection_area(poly_a: np.ndarray, poly_b: np.ndarray) -> np.ndarray:
    """Areas of the intersections of paired counter-clockwise quadrilaterals ``(P, 4, 2)``.

    The intersection of two convex polygons is the convex hull of the corners of each inside the
    other plus the crossings of their edges; it is ordered by angle about its centroid and
    measured with the shoelace formula, all pairs at once.
    """
    pairs = len(poly_a)
    if pairs == 0:
        return np.zeros(0)
    scale = np.maximum(np.abs(poly_a).max(axis=(1, 2)), np.abs(poly_b).max(axis=(1, 2)))
    eps = 1e-9 * np.maximum(scale, 1.0)[:, None] ** 2
    a_in_b = _inside_convex(poly_a, poly_b, eps)
    b_in_a = _inside_convex(poly_b, poly_a, eps)
    a0, a1 = poly_a, np.roll(poly_a, -1, axis=1)
    b0, b1 = poly_b, np.roll(poly_b, -1, axis=1)
    da = (a1 - a0)[:, :, None, :]  # (P, 4, 1, 2)
    db = (b1 - b0)[:, None, :, :]  # (P, 1, 4, 2)
    denom = _cross2(da, db)  # (P, 4, 4)
    offset = b0[:, None, :, :] - a0[:, :, None, :]
    parallel = np.abs(denom) < 1e-12
    safe = np.where(parallel, 1.0, denom)
    t = _cross2(offset, db) / safe
    u = _cross2(offset, da) / safe
    crossing = ~parallel & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
    cross_pts = (a0[:, :, None, :] + t[..., None] * da).reshape(pairs, 16, 2)
    candidates = np.concatenate([poly_a, poly_b, cross_pts], axis=1)  # (P, 24, 2)
    valid = np.concatenate([a_in_b, b_in_a, crossing.reshape(pairs, 16)], axis=1)
    count = valid.sum(axis=1)
    centroid = (candidates * valid[..., None]).sum(axis=1) / np.maximum(count, 1)[:, None]
    rel = candidates - centroid[:, None, :]
    angle = np.where(valid, np.arctan2(rel[..., 1], rel[..., 0]), np.inf)
    order = np.argsort(angle, axis=1, kind="stable")
    ring = np.take_along_axis(candidates, order[..., None], axis=1)
    ring_valid = np.take_along_axis(valid, order, axis=1)
    # Unused slots repeat the first vertex: they add zero-length edges and close the ring.
    ring = np.where(ring_valid[..., None], ring, ring[:, :1, :])
    area = 0.5 * _cross2(ring, np.roll(ring, -1, axis=1)).sum(axis=1)
    return np.where(count >= 3, np.abs(area), 0.0)


_PAIR_BLOCK = 65536  # pairs per vectorised block: bounds temporary memory to ~100 MB


def bev_overlap_area(boxes_a: np.ndarray, boxes_b: np.ndarray | None = None) -> np.ndarray:
    """Exact bird's-eye-view overlap areas (m^2) of rotated boxes, every pair: ``(A, B)``.

    ``boxes_b`` defaults to ``boxes_a``. Pairs whose bounding circles are apart are skipped.
    """
    boxes_a = _check_boxes(boxes_a)
    boxes_b = boxes_a if boxes_b is None else _check_boxes(boxes_b)
    out = np.zeros((len(boxes_a), len(boxes_b)))
    if out.size == 0:
        return out
    radius_a = np.hypot(boxes_a[:, 3], boxes_a[:, 4]) / 2.0
    radius_b = np.hypot(boxes_b[:, 3], boxes_b[:, 4]) / 2.0
    gap = np.hypot(
        boxes_a[:, None, 0] - boxes_b[None, :, 0], boxes_a[:, None, 1] - boxes_b[None, :, 1]
    )
    ia, ib = np.nonzero(gap <= (radius_a[:, None] + radius_b[None, :]) * (1 + 1e-9))
    corners_a, corners_b = bev_corners(boxes_a), bev_corners(boxes_b)
    for start in range(0, len(ia), _PAIR_BLOCK):
        a, b = ia[start : start + _PAIR_BLOCK], ib[start : start + _PAIR_BLOCK]
        out[a, b] = _convex_intersection_area(corners_a[a], corners_b[b])
    return out


def bev_iou(boxes_a: np.ndarray, boxes_b: np.ndarray | None = None) -> np.ndarray:
    """Bird's-eye-view IoU of rotated boxes, every pair: ``(A, B)``."""
    boxes_a = _check_boxes(boxes_a)
    boxes_b = boxes_a if boxes_b is None else _check_boxes(boxes_b)
    inter = bev_overlap_area(boxes_a, boxes_b)
    area_a = boxes_a[:, 3] * boxes_a[:, 4]
    area_b = boxes_b[:, 3] * boxes_b[:, 4]
    union = area_a[:, None] + area_b[None, :] - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)


def boxes_iou3d(boxes_a: np.ndarray, boxes_b: np.ndarray | None = None) -> np.ndarray:
    """3D IoU of rotated (yaw-only) boxes, every pair: ``(A, B)``."""
    boxes_a = _check_boxes(boxes_a)
    boxes_b = boxes_a if boxes_b is None else _check_boxes(boxes_b)
    top = np.minimum(
        boxes_a[:, None, 2] + boxes_a[:, None, 5] / 2, boxes_b[None, :, 2] + boxes_b[None, :, 5] / 2
    )
    bottom = np.maximum(
        boxes_a[:, None, 2] - boxes_a[:, None, 5] / 2, boxes_b[None, :, 2] - boxes_b[None, :, 5] / 2
    )
    inter = bev_overlap_area(boxes_a, boxes_b) * np.clip(top - bottom, 0.0, None)
    vol_a = boxes_a[:, 3:6].prod(axis=1)
    vol_b = boxes_b[:, 3:6].prod(axis=1)
    union = vol_a[:, None] + vol_b[None, :] - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)


def canonical_iou3d(dims_a: np.ndarray, dims_b: np.ndarray) -> np.ndarray:
    """3D IoU of boxes in canonical pose (same centre, heading 0), broadcasting over rows.

    Args:
        dims_a, dims_b: ``(..., 3)`` sizes dx, dy, dz in metres (broadcastable).

    Returns:
        ``prod(min dims) / (vol_a + vol_b - prod(min dims))``, shape of the broadcast.
    """
    dims_a = np.asarray(dims_a, dtype=np.float64)
    dims_b = np.asarray(dims_b, dtype=np.float64)
    inter = np.minimum(dims_a, dims_b).prod(axis=-1)
    union = dims_a.prod(axis=-1) + dims_b.prod(axis=-1) - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)


def box_diagonal(boxes: np.ndarray) -> np.ndarray:
    """Space diagonal ``(M,)`` of ``(M, 7)`` boxes, metres."""
    return np.linalg.norm(_check_boxes(boxes)[:, 3:6], axis=1)
