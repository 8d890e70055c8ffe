"""Points sorted into (elevation, azimuth) cells for cone queries (numba): the generic grid
of the per-point test (:class:`_Grid`) and the one-pass build of :class:`FrameGrid`'s arrays,
with the memory they are built in (:class:`GridMemory`). Imports nothing from drcpo.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import NamedTuple

import numba as nb
import numpy as np

__all__ = ["GridMemory", "thread_grid_memory"]


@dataclass(frozen=True)
class _Grid:
    """Points sorted into (elevation, azimuth) cells of ``size`` radians, for cone queries."""

    order: np.ndarray  # (M,) set-up index of the k-th sorted point
    starts: np.ndarray  # (cells + 1,) first sorted position of each cell
    elevation: np.ndarray  # (M,) sorted, radians
    azimuth: np.ndarray  # (M,) sorted, radians
    origin: float  # elevation of the first row's lower edge
    size: float  # row height, radians
    rows: int
    columns: int


def _build_grid(rays: np.ndarray, cone: np.ndarray) -> _Grid:
    elevation = np.arcsin(np.clip(rays[:, 2], -1.0, 1.0))
    azimuth = np.arctan2(rays[:, 1], rays[:, 0])
    low, high = float(elevation.min()), float(elevation.max())
    # Cells about as wide as a typical first neighbourhood, but never many more cells than
    # points (sparse sets) nor so wide that a query scans most of the set.
    area = max(high - low, 1e-3) * 2 * math.pi
    size = float(np.clip(np.median(cone), math.sqrt(area / max(len(rays), 1)), 0.25))
    rows = int((high - low) / size) + 1
    columns = max(1, int(2 * math.pi / size))
    row = np.minimum(((elevation - low) / size).astype(np.int64), rows - 1)
    column = ((azimuth + np.pi) * (columns / (2 * math.pi))).astype(np.int64) % columns
    cell = row * columns + column
    counts = np.bincount(cell, minlength=rows * columns)
    starts = np.zeros(rows * columns + 1, dtype=np.int64)
    np.cumsum(counts, out=starts[1:])
    order = _counting_sort(cell, starts)
    return _Grid(order, starts, elevation[order], azimuth[order], low, size, rows, columns)


@nb.njit(cache=True, nogil=True)
def _counting_sort(cell, starts):  # pragma: no cover - numba
    # The stable argsort of the cell numbers in linear time (cells are few and known).
    order = np.empty(len(cell), dtype=np.int64)
    position = starts[:-1].copy()
    for i in range(len(cell)):
        order[position[cell[i]]] = i
        position[cell[i]] += 1
    return order


@nb.njit(cache=True, nogil=True)
def _counting_sort_into(cell, starts, offset):  # pragma: no cover - numba
    # _counting_sort that also counts the cells, writing their first sorted positions plus
    # ``offset`` into ``starts`` (in place: no scratch array as large as the grid).
    order = np.empty(len(cell), dtype=np.int64)
    _counting_sort_to(cell, starts, offset, order)
    return order


@nb.njit(cache=True, nogil=True)
def _counting_sort_to(cell, starts, offset, order):  # pragma: no cover - numba
    # _counting_sort_into, writing the order into ``order``.
    cells = starts.shape[0] - 1
    starts[:] = 0
    for c in cell:
        starts[c + 1] += 1
    starts[0] = offset
    for c in range(cells):
        starts[c + 1] += starts[c]
    for i in range(len(cell) - 1, -1, -1):  # backwards from each cell's end: stable
        c = cell[i]
        starts[c + 1] -= 1
        order[starts[c + 1] - offset] = i
    for c in range(cells):  # starts[c + 1] now holds cell c's first position
        starts[c] = starts[c + 1]
    starts[cells] = offset + len(cell)


@nb.njit(cache=True, nogil=True)
def _directions(points, center, rel, azimuth, elevation):  # pragma: no cover - numba
    # Per point (x, y, z in float64) relative to ``center``, into the given arrays: its
    # offset, ``arctan2(y, x)`` and ``arctan2(z, sqrt(x x + y y))`` (libm's atan2; numpy's
    # vectorised arctan2 may differ in the last bit on some CPUs). Returns the first row
    # holding a NaN or infinite coordinate (-1: none).
    bad = -1
    for i in range(points.shape[0]):
        x = np.float64(points[i, 0]) - center[0]
        y = np.float64(points[i, 1]) - center[1]
        z = np.float64(points[i, 2]) - center[2]
        if bad < 0 and not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            bad = i
        rel[i, 0], rel[i, 1], rel[i, 2] = x, y, z
        azimuth[i] = math.atan2(y, x)
        elevation[i] = math.atan2(z, math.sqrt(x * x + y * y))
    return bad


@nb.njit(cache=True, nogil=True)
def _norms(rel):  # pragma: no cover - numba
    out = np.empty(rel.shape[0])
    _norms_to(rel, out)
    return out


@nb.njit(cache=True, nogil=True)
def _norms_to(rel, out):  # pragma: no cover - numba
    # |rel| per row as (x x + y y) + z z: the ranges of _Setup.build and FrameGrid alike.
    for i in range(rel.shape[0]):
        x, y, z = rel[i, 0], rel[i, 1], rel[i, 2]
        out[i] = math.sqrt(x * x + y * y + z * z)


class GridMemory:
    """Memory a :class:`FrameGrid` is built in, kept for the next grid: fresh memory costs a
    page fault per 4 KiB on first use, which slows down a frame's grid built on a second
    thread markedly (docs/measurements.md). A grid built in it is valid until the next one
    is."""

    def __init__(self) -> None:
        self.floats = np.empty(0)
        self.ints = np.empty(0, dtype=np.int64)

    def reserve(self, count: int, spare: int) -> tuple[np.ndarray, np.ndarray]:
        """Buffers for a grid of ``count`` points with ``spare`` rows (the int64 one may
        still be too short for the cells; the build then replaces it)."""
        floats = 6 * count + 10 * (count + spare)
        ints = 7 * count + 2
        if len(self.floats) < floats:
            self.floats = np.empty(floats + floats // 4)
        if len(self.ints) < ints:
            self.ints = np.empty(ints + ints // 4, dtype=np.int64)
        return self.floats, self.ints


_THREAD_MEMORY = threading.local()


def thread_grid_memory() -> GridMemory:
    """The calling thread's :class:`GridMemory` (one grid at a time per thread)."""
    memory = getattr(_THREAD_MEMORY, "grid", None)
    if memory is None:
        memory = _THREAD_MEMORY.grid = GridMemory()
    return memory


@nb.njit(cache=True, nogil=True)
def _build_frame_grid(
    points, center, radius, spare, row_height, column_width, floats, ints
):  # pragma: no cover
    # FrameGrid's arrays in one pass over its steps: directions and ranges, the cell geometry
    # (cells about a typical first neighbourhood wide, never smaller than an even share of the
    # covered directions, at most 0.25 rad), the points sorted by cell and by range within a
    # cell, and the sorted copies with ``spare`` zeroed rows after them, all in ``floats`` and
    # ``ints`` (GridMemory.reserve's; ``ints`` is replaced when too short for the cells).
    # Returns the first non-finite row and the first row too far for float64 (-1: none), the
    # smallest and largest range, the geometry (origin, row height, rows, columns), then the
    # arrays and the int64 buffer used.
    n = points.shape[0]
    total = n + spare
    rel = floats[: 3 * n].reshape((n, 3))
    azimuth = floats[3 * n : 4 * n]
    elevation = floats[4 * n : 5 * n]
    ranges = floats[5 * n : 6 * n]
    base = 6 * n
    out_rel = floats[base : base + 3 * total].reshape((total, 3))
    out_rays = floats[base + 3 * total : base + 6 * total].reshape((total, 3))
    out_ranges = floats[base + 6 * total : base + 7 * total]
    out_rho = floats[base + 7 * total : base + 8 * total]
    out_elevation = floats[base + 8 * total : base + 9 * total]
    out_azimuth = floats[base + 9 * total : base + 10 * total]
    bad = _directions(points, center, rel, azimuth, elevation)
    _norms_to(rel, ranges)
    far = -1
    r_min, r_max = np.inf, 0.0
    for i in range(n):
        r = ranges[i]
        if not math.isfinite(r):
            if far < 0 and bad < 0:
                far = i
            continue
        r_min, r_max = min(r_min, r), max(r_max, r)
    origin, height, rows, columns = 0.0, 1.0, 1, 1
    if n and bad < 0 and far < 0:
        low, high = elevation.min(), elevation.max()
        size = math.sqrt(max(high - low, 1e-3) * 2 * math.pi / n)
        if 2.0 * radius > r_max * (1.0 + 1e-12):
            rho_max = 2.0 * radius - r_min
            typical = np.median(ranges[:: max(1, n // 4096)])  # a sample is enough here
            cone = min(max((typical - r_min) / rho_max, 0.0), 2.0) / 2.0
            size = max(size, 2.0 * math.asin(math.sqrt(cone)))
        size = min(size, 0.25)
        origin, height = low, size * row_height
        rows = int((high - low) / height) + 1
        columns = max(1, int(2 * math.pi / (size * column_width)))
    cells_count = rows * columns + 1
    if ints.shape[0] < 3 * n + 2 * cells_count:
        ints = np.empty(3 * n + 2 * cells_count + n, dtype=np.int64)
    cells = ints[:n]
    position = ints[n : 2 * n]
    order = ints[2 * n : 3 * n]
    starts = ints[3 * n : 3 * n + 2 * cells_count].reshape((2, cells_count))
    starts[:] = 0
    if bad < 0 and far < 0:
        _cell_numbers(elevation, azimuth, origin, height, rows, columns, cells)
        _counting_sort_to(cells, starts[0], 0, order)
        _sort_cells(order, ranges, starts[0], 0)
        sorted_out = _Sorted(out_rel, out_ranges, out_rho, out_rays, out_elevation, out_azimuth)
        points = _Directions(rel, ranges, elevation, azimuth)
        _scatter_sorted(order, points, 2.0 * radius, sorted_out, position)
    else:
        order = order[:0]
    return (
        bad,
        far,
        r_min,
        r_max,
        origin,
        height,
        rows,
        columns,
        starts,
        order,
        out_rel,
        out_ranges,
        out_rho,
        out_rays,
        out_elevation,
        out_azimuth,
        position,
        ints,
    )


class _Directions(NamedTuple):
    """The frame's points as seen from the viewpoint, in input order."""

    rel: np.ndarray  # (n, 3) offsets from the viewpoint
    ranges: np.ndarray  # (n,)
    elevation: np.ndarray  # (n,)
    azimuth: np.ndarray  # (n,)


class _Sorted(NamedTuple):
    """FrameGrid's copies of the points in cell order (rows beyond the frame's are zeroed)."""

    rel: np.ndarray
    ranges: np.ndarray
    rho: np.ndarray  # the HPR diameter minus the range
    rays: np.ndarray  # unit directions
    elevation: np.ndarray
    azimuth: np.ndarray


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _scatter_sorted(order, points, diameter, out, position):  # pragma: no cover - numba
    # FrameGrid's sorted copies in one pass (rays rel / range: NaN at the viewpoint, as numpy
    # would give), and each point's sorted position; the rows after the frame's are zeroed.
    rel, ranges, elevation, azimuth = points
    out_rel, out_ranges, out_rho, out_rays, out_elevation, out_azimuth = out
    for k in range(order.shape[0]):
        i = order[k]
        r = ranges[i]
        for c in range(3):
            out_rel[k, c] = rel[i, c]
            out_rays[k, c] = rel[i, c] / r
        out_ranges[k] = r
        out_rho[k] = diameter - r
        out_elevation[k] = elevation[i]
        out_azimuth[k] = azimuth[i]
        position[i] = k
    for k in range(order.shape[0], out_ranges.shape[0]):
        for c in range(3):
            out_rel[k, c] = 0.0
            out_rays[k, c] = 0.0
        out_ranges[k] = out_rho[k] = out_elevation[k] = out_azimuth[k] = 0.0


@nb.njit(cache=True, nogil=True)
def _cell_numbers(elevation, azimuth, origin, height, rows, columns, out):  # pragma: no cover
    # FrameGrid's cell of each direction: row floor((elevation - origin) / height) clamped to
    # the rows, column floor((azimuth + pi) * columns / 2 pi) modulo the columns.
    per_radian = columns / (2 * math.pi)
    for i in range(elevation.shape[0]):
        row = min(max(math.floor((elevation[i] - origin) / height), 0), rows - 1)
        out[i] = row * columns + int((azimuth[i] + math.pi) * per_radian) % columns


@nb.njit(cache=True, nogil=True)
def _sort_cells(order, keys, starts, offset):  # pragma: no cover - numba
    # Each cell's run of ``order`` (positions ``starts`` minus ``offset``) sorted by ``keys``;
    # cells are small, so an insertion sort, except for the odd crowded one.
    for c in range(starts.shape[0] - 1):
        lo, hi = starts[c] - offset, starts[c + 1] - offset
        if hi - lo > 64:
            run = order[lo:hi].copy()
            order[lo:hi] = run[np.argsort(keys[run], kind="mergesort")]
            continue
        for a in range(lo + 1, hi):
            item = order[a]
            key = keys[item]
            b = a - 1
            while b >= lo and keys[order[b]] > key:
                order[b + 1] = order[b]
                b -= 1
            order[b + 1] = item
