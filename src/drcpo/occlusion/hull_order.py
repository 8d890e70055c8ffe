"""The order in which :mod:`~drcpo.occlusion.hull`'s certified hull takes its points.

The hull is built one point at a time, with the viewpoint as apex. The order decides how much
work each insertion costs: the first three points (the extremes across the points' mean
direction, then the point farthest from their line) span the first tetrahedron with the apex;
then come the nearest point of each cell of a coarse grid across the mean direction (rows in
alternating directions), so that the visible surface is built early and most later points fall
inside it; then the others along a Hilbert curve over a fine grid, so that each point is found
near the last one. Points not all within 84 degrees of the mean direction get no order (the hull
then gives up).
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__: list[str] = []  # internal to drcpo.occlusion.hull

# Every point must be within this cosine of the mean direction (84 degrees), so that the
# viewpoint is a vertex seen clearly from every far facet.
_MIN_COSINE = 0.1
_POINTS_PER_CELL = 16.0  # coarse grid of the first points (each cell's nearest); tuned by timing


def _hilbert_rank(side: int) -> np.ndarray:
    """``(side * side,)`` position on the Hilbert curve of cell ``row * side + col`` (``side`` a
    power of two): consecutive cells are neighbours, so walks from one point to the next are
    short."""
    rank = np.empty(side * side, dtype=np.int64)
    for row in range(side):
        for col in range(side):
            x, y, d, s = row, col, 0, side // 2
            while s > 0:
                rx = 1 if x & s else 0
                ry = 1 if y & s else 0
                d += s * s * ((3 * rx) ^ ry)
                if ry == 0:
                    if rx == 1:
                        x, y = s - 1 - x, s - 1 - y
                    x, y = y, x
                s //= 2
            rank[row * side + col] = d
    return rank


_HILBERT_SIDE = 32
_HILBERT_RANK = _hilbert_rank(_HILBERT_SIDE)


@nb.njit(cache=True, nogil=True)
def _insertion_order(flipped, ranges, radius, axis):  # pragma: no cover - numba
    """``(N,)`` the flipped points in insertion order (the first three span the first
    tetrahedron), or an empty array when they do not all lie within 84 degrees of ``axis``
    (``(3,)``, any length). ``ranges``: the points' ranges before the flip.

    On the points' projection across ``axis``: first the nearest point of each cell of a
    coarse grid (rows in alternating directions), then the others along the Hilbert curve of a
    fine grid (:data:`_HILBERT_SIDE` cells a side).
    """
    n = len(ranges)
    norm = np.sqrt(axis[0] ** 2 + axis[1] ** 2 + axis[2] ** 2)
    if not norm > 0.0:
        return np.empty(0, dtype=np.int64)
    ax = axis[0] / norm
    ay = axis[1] / norm
    az = axis[2] / norm
    # e1: the coordinate axis least aligned with the mean direction, made orthogonal to it.
    if abs(ax) <= abs(ay) and abs(ax) <= abs(az):
        e1x, e1y, e1z = 1.0 - ax * ax, -ax * ay, -ax * az
    elif abs(ay) <= abs(az):
        e1x, e1y, e1z = -ay * ax, 1.0 - ay * ay, -ay * az
    else:
        e1x, e1y, e1z = -az * ax, -az * ay, 1.0 - az * az
    norm = np.sqrt(e1x * e1x + e1y * e1y + e1z * e1z)
    e1x /= norm
    e1y /= norm
    e1z /= norm
    e2x = ay * e1z - az * e1y
    e2y = az * e1x - ax * e1z
    e2z = ax * e1y - ay * e1x
    u = np.empty(n, dtype=np.float64)
    v = np.empty(n, dtype=np.float64)
    a = 0
    b = 0
    for i in range(n):
        depth = flipped[i, 0] * ax + flipped[i, 1] * ay + flipped[i, 2] * az
        if not depth > _MIN_COSINE * (2.0 * radius - ranges[i]):  # its flipped range
            return np.empty(0, dtype=np.int64)
        u[i] = flipped[i, 0] * e1x + flipped[i, 1] * e1y + flipped[i, 2] * e1z
        v[i] = flipped[i, 0] * e2x + flipped[i, 1] * e2y + flipped[i, 2] * e2z
        if u[i] < u[a]:
            a = i
        if u[i] > u[b]:
            b = i
    # The first tetrahedron: the extremes in u, then the point farthest from their line.
    c = a
    best = -1.0
    du = u[b] - u[a]
    dv = v[b] - v[a]
    v_lo = v[0]
    v_hi = v[0]
    for i in range(n):
        off = abs(du * (v[i] - v[a]) - dv * (u[i] - u[a]))
        if off > best:
            best = off
            c = i
        v_lo = min(v_lo, v[i])
        v_hi = max(v_hi, v[i])
    if a == b or c == a or c == b:
        return np.empty(0, dtype=np.int64)
    # Coarse cells pick the first points; the others follow the fine cells' Hilbert curve.
    side = max(1, int(np.sqrt(n / _POINTS_PER_CELL)))
    fine = _HILBERT_SIDE
    su = 1.0 / max(du, 1e-300) * (1.0 - 1e-9)
    sv = 1.0 / max(v_hi - v_lo, 1e-300) * (1.0 - 1e-9)
    cell = np.empty(n, dtype=np.int64)  # rank of the fine cell on the curve
    coarse = np.empty(n, dtype=np.int64)
    start = np.zeros(fine * fine + 2, dtype=np.int64)  # first slot of each fine cell, shifted
    nearest = np.full(side * side, -1, dtype=np.int64)
    for i in range(n):
        x = (u[i] - u[a]) * su
        y = (v[i] - v_lo) * sv
        row = min(side - 1, int(x * side))
        col = min(side - 1, int(y * side))
        if row & 1:
            col = side - 1 - col
        k = row * side + col
        coarse[i] = k
        if nearest[k] < 0 or ranges[i] < ranges[nearest[k]]:
            nearest[k] = i
        k = _HILBERT_RANK[min(fine - 1, int(x * fine)) * fine + min(fine - 1, int(y * fine))]
        cell[i] = k
        start[k + 2] += 1
    order = np.empty(n, dtype=np.int64)
    order[0] = a
    order[1] = b
    order[2] = c
    head = 3
    for k in range(side * side):  # first each coarse cell's nearest point...
        i = nearest[k]
        if i >= 0 and i != a and i != b and i != c:
            order[head] = i
            head += 1
    for i in range(n):
        if nearest[coarse[i]] == i or i == a or i == b or i == c:
            start[cell[i] + 2] -= 1
    start[1] = head
    for k in range(fine * fine):  # ... then the others along the curve
        start[k + 2] += start[k + 1]
    for i in range(n):
        if nearest[coarse[i]] != i and i != a and i != b and i != c:
            k = cell[i]
            order[start[k + 1]] = i
            start[k + 1] += 1
    return order
