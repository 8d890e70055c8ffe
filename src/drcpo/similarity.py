"""The candidate index's first stage: for every object of a class, the ``s`` objects whose boxes
are most alike (canonical IoU), found exactly by a grid search over box sizes or approximately;
:func:`similarity_recall` measures how much of the exact answer the approximate
mode keeps. See :mod:`drcpo.index_build` for the whole method."""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from drcpo.errors import ConfigError

__all__ = ["SimilaritySearch", "similarity_recall"]

_BOUND_SLACK = 1e-9  # relative safety margin on IoU upper bounds against rounding
_OCCUPANCY_DIVISOR = 48.0  # typical cell holds s / this objects
_MAX_CELLS = 1 << 22  # cap on the u-space grid (the cell table costs 8 bytes per cell)


class _Boxes(NamedTuple):
    """Every object of the search, by local id."""

    u: np.ndarray  # (M, 3) log box sizes
    dims: np.ndarray  # (M, 3) box sizes
    vol: np.ndarray  # (M,) volumes
    cells: np.ndarray  # (M, 3) int64: the grid cell of each


class _Grid(NamedTuple):
    """The grid over log-size space; the searchable objects sorted by cell."""

    origin: np.ndarray  # (3,) lower corner
    h: float  # cell size
    shape: np.ndarray  # (3,) int64 cells per axis
    cell_start: np.ndarray  # (cells + 1,) int64: cell c's objects are at [start[c], start[c + 1])
    ids: np.ndarray  # int32 local ids in cell order
    dims: np.ndarray  # (n, 3) their sizes
    vol: np.ndarray  # (n,) their volumes


class _Heap(NamedTuple):
    """The best ``s`` (IoU, id) pairs so far, worst at the root."""

    iou: np.ndarray  # (s,) float64
    id: np.ndarray  # (s,) int32


# --------------------------------------------------------------------------------------------
# First stage: the best ``s`` objects by canonical IoU
# --------------------------------------------------------------------------------------------
class SimilaritySearch:
    """Top-``s`` canonical-IoU neighbours of objects of one class (see the module docstring).

    Args:
        dims: ``(M, 3)`` positive box sizes (m); local id = row of ``dims``.
        s: neighbours per object (``<= M - 1``).
        mode: ``"exact"`` (grid search) or ``"approximate"`` (L1 nearest neighbours in log-size
            space, re-ranked by IoU).
        approx_factor: the approximate mode re-ranks ``ceil(approx_factor * s)`` neighbours.
    """

    def __init__(
        self, dims: np.ndarray, s: int, mode: str = "exact", approx_factor: float = 1.5
    ) -> None:
        if mode not in ("exact", "approximate"):
            raise ConfigError(f"similarity mode must be 'exact' or 'approximate', got {mode!r}")
        self.dims = np.ascontiguousarray(dims, np.float64)
        m = len(self.dims)
        if not 0 <= s <= max(m - 1, 0):
            raise ValueError(f"s = {s} neighbours requested among {m} objects")
        self.s = int(s)
        self.mode = mode
        self.vol = (self.dims[:, 0] * self.dims[:, 1]) * self.dims[:, 2]
        self.u = np.log(self.dims)
        self.pool = _searchable(self.dims, self.s)
        self._build_grid()
        if mode == "approximate":
            from scipy.spatial import cKDTree

            self.tree = cKDTree(self.u[self.pool])
            self.neighbours = min(len(self.pool), math.ceil(approx_factor * self.s) + 1)

    def _build_grid(self) -> None:
        u = self.u[self.pool]
        m = len(u)
        lo = np.quantile(u, 0.001, axis=0) if m else np.zeros(3)
        hi = np.quantile(u, 0.999, axis=0) if m else np.zeros(3)
        extent = np.maximum(hi - lo, 1e-12)
        if m <= 16 * self.s + 256:
            # Scanning everything is cheap here; one cell avoids visiting empty ones.
            self.h = float(extent.max()) * 2 + 1.0
        else:
            self.h = _cell_size(u, lo, extent, self.s)
        shape = np.maximum(np.ceil(extent / self.h).astype(np.int64), 1)
        # More cells than objects only adds empty cells to visit.
        while shape.prod() > min(_MAX_CELLS, 2 * m):
            self.h *= 1.25
            shape = np.maximum(np.ceil(extent / self.h).astype(np.int64), 1)
        self.origin = lo
        self.shape = shape
        cells = np.floor((self.u - lo) / self.h).astype(np.int64)
        np.clip(cells, 0, shape - 1, out=cells)
        self.cells = cells
        flat = (cells[:, 0] * shape[1] + cells[:, 1]) * shape[2] + cells[:, 2]
        # Queries run in cell order so that each block's memory accesses stay local.
        self.order = np.argsort(flat, kind="stable").astype(np.int64)
        in_cells = self.pool[np.argsort(flat[self.pool], kind="stable")]
        self.cell_start = np.zeros(int(shape.prod()) + 1, np.int64)
        np.cumsum(
            np.bincount(flat[self.pool], minlength=int(shape.prod())), out=self.cell_start[1:]
        )
        self.sorted_ids = in_cells.astype(np.int32)
        self.sorted_dims = np.ascontiguousarray(self.dims[in_cells])
        self.sorted_vol = np.ascontiguousarray(self.vol[in_cells])

    def top(self, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Local ids ``int32 (B, s)`` and IoUs ``float64 (B, s)`` of the queries' neighbours,
        ranked by IoU (descending), then id (ascending)."""
        queries = np.ascontiguousarray(queries, np.int64)
        if self.s == 0:
            return np.zeros((len(queries), 0), np.int32), np.zeros((len(queries), 0))
        if self.mode == "approximate":
            _, near = self.tree.query(self.u[queries], k=self.neighbours, p=1, workers=1)
            near = self.pool[np.asarray(near, np.int64).reshape(len(queries), -1)]
            return _rerank(queries, near, self.dims, self.vol, self.s)
        boxes = _Boxes(self.u, self.dims, self.vol, self.cells)
        grid = _Grid(
            self.origin,
            float(self.h),
            self.shape,
            self.cell_start,
            self.sorted_ids,
            self.sorted_dims,
            self.sorted_vol,
        )
        return _grid_search(queries, boxes, grid, self.s)


def _searchable(dims: np.ndarray, s: int) -> np.ndarray:
    """Ids (ascending) that can be anyone's top-``s``: all but the surplus of identical boxes.

    Objects with identical sizes tie with everyone, and ties go to the lower id, so of each
    group only the ``s + 1`` lowest ids can rank (one of them may be the query itself). Without
    this, a class of many identical boxes would cost O(M^2).
    """
    m = len(dims)
    order = np.lexsort((dims[:, 2], dims[:, 1], dims[:, 0]))  # stable: ids ascend in a group
    ordered = dims[order]
    first = np.ones(m, bool)
    first[1:] = (ordered[1:] != ordered[:-1]).any(axis=1)
    group_start = np.maximum.accumulate(np.where(first, np.arange(m), 0))
    return np.sort(order[np.arange(m) - group_start <= s])


def _cell_size(u: np.ndarray, lo: np.ndarray, extent: np.ndarray, s: int) -> float:
    """Cell edge (in log-size units) giving about ``s / 48`` objects in a typical object's cell.

    Smaller cells mean more, cheaper cell visits; larger ones more IoU evaluations. The typical
    occupancy is measured (on a sample for large classes) rather than assumed, because sizes of
    real classes are strongly clustered.
    """
    m = len(u)
    target = max(s / _OCCUPANCY_DIVISOR, 1.0)
    sample = u if m <= 50_000 else u[np.linspace(0, m - 1, 50_000).astype(np.int64)]
    scale = m / len(sample)

    def occupancy(h: float) -> float:
        cells = np.floor((sample - lo) / h).astype(np.int64)
        _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
        # Each sampled object sees itself plus a 1/scale share of its cell's other objects.
        return (float(counts[inverse.ravel()].mean()) - 1.0) * scale + 1.0

    low, high = 1e-6, float(extent.max()) * 2 + 1e-6
    if occupancy(high) <= target:
        return high
    for _ in range(30):
        mid = math.sqrt(low * high)
        if occupancy(mid) < target:
            low = mid
        else:
            high = mid
        if high / low < 1.2:
            break
    return high


@nb.njit(cache=True, nogil=True, inline="always")
def _ranks_after(iou_a: float, id_a: int, iou_b: float, id_b: int) -> bool:
    """True when (iou_a, id_a) ranks after (iou_b, id_b): lower IoU, then higher id."""
    return iou_a < iou_b or (iou_a == iou_b and id_a > id_b)


@nb.njit(cache=True, nogil=True)
def _heap_push(h_iou, h_id, size, iou, idx):  # pragma: no cover - numba
    """Insert into a heap whose root ranks last; returns the new size."""
    pos = size
    while pos > 0:
        parent = (pos - 1) >> 1
        if _ranks_after(iou, idx, h_iou[parent], h_id[parent]):
            h_iou[pos] = h_iou[parent]
            h_id[pos] = h_id[parent]
            pos = parent
        else:
            break
    h_iou[pos] = iou
    h_id[pos] = idx
    return size + 1


@nb.njit(cache=True, nogil=True)
def _heap_sift_down(h_iou, h_id, size, iou, idx):  # pragma: no cover - numba
    """Put (iou, idx) at the root of a heap of ``size`` items and restore the order."""
    pos = 0
    while True:
        child = 2 * pos + 1
        if child >= size:
            break
        right = child + 1
        if right < size and _ranks_after(h_iou[right], h_id[right], h_iou[child], h_id[child]):
            child = right
        if _ranks_after(h_iou[child], h_id[child], iou, idx):
            h_iou[pos] = h_iou[child]
            h_id[pos] = h_id[child]
            pos = child
        else:
            break
    h_iou[pos] = iou
    h_id[pos] = idx


@nb.njit(cache=True, nogil=True)
def _heap_offer(h_iou, h_id, size, cap, iou, idx):  # pragma: no cover - numba
    if size < cap:
        return _heap_push(h_iou, h_id, size, iou, idx)
    if _ranks_after(h_iou[0], h_id[0], iou, idx):
        _heap_sift_down(h_iou, h_id, size, iou, idx)
    return size


@nb.njit(cache=True, nogil=True)
def _heap_drain(h_iou, h_id, size, out_iou, out_id):  # pragma: no cover - numba
    """Write the heap's items best first (pops the worst into the last free slot)."""
    for last in range(size - 1, -1, -1):
        out_iou[last] = h_iou[0]
        out_id[last] = h_id[0]
        if last > 0:
            _heap_sift_down(h_iou, h_id, last, h_iou[last], h_id[last])


@nb.njit(cache=True, nogil=True, inline="always")
def _out_of_reach(e_p, e_q, worst, full):
    """True when no object whose ``exp(p) >= e_p`` and ``exp(q) >= e_q`` can enter the heap.

    Its IoU is at most ``1 / (e_p + e_q - 1)``, which must stay below the heap's worst.
    """
    return full and (e_p + e_q - 1.0) * worst > 1.0 + _BOUND_SLACK


@nb.njit(cache=True, nogil=True, inline="always")
def _scan_cell(grid, cell, q, boxes, heap, size):
    """Offers every object of ``cell`` but ``q`` itself to ``heap`` (``size`` items of at most
    ``len(heap.iou)``); returns the heap's new size."""
    d0, d1, d2 = boxes.dims[q, 0], boxes.dims[q, 1], boxes.dims[q, 2]
    vq, cap = boxes.vol[q], heap.iou.shape[0]
    for t in range(grid.cell_start[cell], grid.cell_start[cell + 1]):
        j = grid.ids[t]
        if j == q:
            continue
        inter = (min(d0, grid.dims[t, 0]) * min(d1, grid.dims[t, 1])) * min(d2, grid.dims[t, 2])
        iou = inter / ((vq + grid.vol[t]) - inter)
        size = _heap_offer(heap.iou, heap.id, size, cap, iou, j)
    return size


@nb.njit(cache=True, nogil=True)
def _grid_search(queries, boxes, grid, s):  # pragma: no cover - numba
    nq = len(queries)
    out_id = np.empty((nq, s), np.int32)
    out_iou = np.empty((nq, s), np.float64)
    heap = _Heap(np.empty(s, np.float64), np.empty(s, np.int32))
    h_iou = heap.iou
    u, cells, origin, h = boxes.u, boxes.cells, grid.origin, grid.h
    gx, gy, gz = grid.shape[0], grid.shape[1], grid.shape[2]
    g = max(gx, gy, gz)
    # e_lo[a, k]: exp of the least log-size gap along axis a to a cell k + 1 below q's cell
    # (such objects are smaller, so the gap adds to p); e_hi likewise above (adds to q).
    e_lo = np.empty((3, g), np.float64)
    e_hi = np.empty((3, g), np.float64)
    below = np.empty(3, np.float64)
    above = np.empty(3, np.float64)
    for b in range(nq):
        q = queries[b]
        c0, c1, c2 = cells[q, 0], cells[q, 1], cells[q, 2]
        for a in range(3):
            face = origin[a] + cells[q, a] * h
            below[a] = max(u[q, a] - face, 0.0)
            above[a] = max(face + h - u[q, a], 0.0)
        rmax = max(c0, gx - 1 - c0, c1, gy - 1 - c1, c2, gz - 1 - c2)
        size = 0
        for r in range(rmax + 1):
            if r >= 1:
                nearest = np.inf
                for a in range(3):
                    e_lo[a, r - 1] = math.exp(below[a] + (r - 1) * h)
                    e_hi[a, r - 1] = math.exp(above[a] + (r - 1) * h)
                    nearest = min(nearest, e_lo[a, r - 1], e_hi[a, r - 1])
                # Every cell of ring r is at least this far along one axis.
                if _out_of_reach(nearest, 1.0, h_iou[0], size == s):
                    break
            for x in range(max(c0 - r, 0), min(c0 + r, gx - 1) + 1):
                ex_p = e_lo[0, c0 - x - 1] if x < c0 else 1.0
                ex_q = e_hi[0, x - c0 - 1] if x > c0 else 1.0
                if _out_of_reach(ex_p, ex_q, h_iou[0], size == s):
                    continue
                for y in range(max(c1 - r, 0), min(c1 + r, gy - 1) + 1):
                    ey_p = ex_p * (e_lo[1, c1 - y - 1] if y < c1 else 1.0)
                    ey_q = ex_q * (e_hi[1, y - c1 - 1] if y > c1 else 1.0)
                    if _out_of_reach(ey_p, ey_q, h_iou[0], size == s):
                        continue
                    column = (x * gy + y) * gz
                    # Cells with |x - c0|, |y - c1| < r lie inside earlier rings, except
                    # their two z ends.
                    step = 1 if max(abs(x - c0), abs(y - c1)) == r else 2 * r
                    for z in range(c2 - r, c2 + r + 1, step):
                        if z < 0 or z >= gz:
                            continue
                        e_p = ey_p * (e_lo[2, c2 - z - 1] if z < c2 else 1.0)
                        e_q = ey_q * (e_hi[2, z - c2 - 1] if z > c2 else 1.0)
                        if _out_of_reach(e_p, e_q, h_iou[0], size == s):
                            continue
                        size = _scan_cell(grid, column + z, q, boxes, heap, size)
        _heap_drain(heap.iou, heap.id, size, out_iou[b], out_id[b])
    return out_id, out_iou


@nb.njit(cache=True, nogil=True)
def _rerank(queries, near, dims, vol, s):  # pragma: no cover - numba
    nq = len(queries)
    m = len(dims)
    out_id = np.empty((nq, s), np.int32)
    out_iou = np.empty((nq, s), np.float64)
    h_iou = np.empty(s, np.float64)
    h_id = np.empty(s, np.int32)
    for b in range(nq):
        q = queries[b]
        size = 0
        for c in range(near.shape[1]):
            j = near[b, c]
            if j == q or j >= m:
                continue
            inter = (min(dims[q, 0], dims[j, 0]) * min(dims[q, 1], dims[j, 1])) * min(
                dims[q, 2], dims[j, 2]
            )
            iou = inter / ((vol[q] + vol[j]) - inter)
            size = _heap_offer(h_iou, h_id, size, s, iou, j)
        _heap_drain(h_iou, h_id, size, out_iou[b], out_id[b])
        for c in range(size, s):
            out_iou[b, c] = -1.0
            out_id[b, c] = -1
    return out_id, out_iou


def similarity_recall(
    dims: np.ndarray, s: int, sample: np.ndarray, approx_factor: float = 1.5, block: int = 256
) -> float:
    """Mean share of each sampled object's exact top-``s`` that the approximate mode finds.

    Args:
        dims: ``(M, 3)`` box sizes of one class.
        s: neighbours (``2 k``).
        sample: local ids to check, taken ``block`` at a time.
    """
    exact = SimilaritySearch(dims, s, mode="exact")
    approx = SimilaritySearch(dims, s, mode="approximate", approx_factor=approx_factor)
    sample = np.asarray(sample, np.int64)
    found = 0
    for start in range(0, len(sample), block):
        rows = sample[start : start + block]
        for truth, guess in zip(exact.top(rows)[0], approx.top(rows)[0], strict=True):
            found += len(np.intersect1d(truth, guess, assume_unique=True))
    return found / max(len(sample) * s, 1)
