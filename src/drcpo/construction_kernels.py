"""The compiled (numba) construction of :mod:`drcpo.construction`: every object of a batch built
in one call, reading the candidates' points straight from the (memory-mapped) database.

Per source object: its points within the margin of its box (and, for a mirrored class, their
mirror images) are counted in the box's partition grid; each partition's density (count over the
class's largest count there, the index's normaliser, or the object's own largest count), the
threshold (the mean density of the occupied partitions) and the coverage follow; then each round
draws one candidate per deficient partition from the ``Generator`` (as ``rng.integers(0, K,
size)`` does) and adds the points that candidate has in that partition of the source box. What
travels into the kernels travels as the named tuples below.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

from drcpo.partitions import cell_of

__all__: list[str] = []  # internal to drcpo.construction, which has the API


class _Stored(NamedTuple):
    """The database as the kernels read it: plain ndarray views (no copy)."""

    points: np.ndarray  # (P, 3 + C) float32, every object in its canonical pose
    offsets: np.ndarray  # (n + 1,) int64: object k's points are points[offsets[k]:offsets[k + 1]]


class _Sources(NamedTuple):
    """The source objects of one compiled call, one row each."""

    rows: np.ndarray  # (S,) int64 database rows
    dims: np.ndarray  # (S, 3) float64 box sizes
    grids: np.ndarray  # (S, 3) int64 partition grids
    mirror: np.ndarray  # (S,) bool: the class is mirrored across the x axis
    scales: np.ndarray  # (S, P_max) float64 density normalisers per partition
    own_scale: np.ndarray  # (S,) bool: normalise by the object's own largest count instead


class _Limits(NamedTuple):
    margin: float  # metres outside the source box that points may lie
    max_iterations: int
    coverage: float  # share of fillable partitions above the threshold that ends an object


class _Box(NamedTuple):
    """One source object's box as the kernels cut it."""

    dims: np.ndarray  # (3,) float64
    grid: np.ndarray  # (3,) int64
    margin: float
    copies: int  # 2: each point and its mirror image


# Points are referenced as 2 * (row in ``database.points``) + (1 for the mirror image) while
# objects grow; the rows are copied out once at the end.


@numba.njit(cache=True, nogil=True)
def _construct_partition(stored, sources, candidates, limits, rng):
    """Construction of every object of ``sources`` in turn (see the module docstring).

    Each iteration draws one candidate per deficient partition (ascending partition order, as
    ``rng.integers(0, K, size)`` draws), then adds the points that each drawn candidate (and
    its mirror image) has in that partition of the source box, in stored order, each mirror
    image right after its point. Returns what :func:`drcpo.construction._objects` takes.
    """
    n = sources.rows.shape[0]
    refs = np.empty(_capacity(stored.offsets, sources.rows), dtype=np.int64)
    added = np.empty(64, dtype=np.int64)
    n_refs = n_added = 0
    ref_offsets, added_offsets, iterations, initial, final = _per_object(n)
    slot = np.empty(stored.offsets.shape[0] - 1, dtype=np.int64)  # see _add_once
    pool = np.empty(candidates.shape[1], dtype=np.int64)
    near = np.empty(1024, dtype=np.int64)
    for s in range(n):
        grid = sources.grids[s]
        box = _Box(sources.dims[s], grid, limits.margin, 2 if sources.mirror[s] else 1)
        counts = np.zeros(grid[0] * grid[1] * grid[2], dtype=np.int64)
        refs, n_refs = _add_source(stored, sources.rows[s], box, counts, refs, n_refs)
        scale, fillable = _normalisers(counts, sources.scales[s], sources.own_scale[s])
        threshold = _threshold(counts, scale, fillable)
        current = initial[s] = _coverage(counts, scale, fillable, threshold)
        n_pool = 0
        for j in range(candidates.shape[1]):
            if candidates[s, j] >= 0:
                pool[n_pool] = candidates[s, j]
                n_pool += 1
        rounds = 0
        while n_pool > 0 and rounds < limits.max_iterations and current < limits.coverage:
            deficient = _deficient(counts, scale, fillable, threshold)
            drawn = np.empty(deficient.shape[0], dtype=np.int64)
            for j in range(drawn.shape[0]):
                drawn[j] = pool[rng.integers(0, n_pool)]
            for j in range(drawn.shape[0]):
                cell = deficient[j]
                before = n_refs
                refs, n_refs, near = _gather(stored, drawn[j], cell, box, refs, n_refs, near)
                counts[cell] += n_refs - before
                if n_refs > before:
                    added, n_added = _add_once(added, n_added, added_offsets[s], drawn[j], slot)
            rounds += 1
            current = _coverage(counts, scale, fillable, threshold)
        ref_offsets[s + 1], added_offsets[s + 1] = n_refs, n_added
        iterations[s], final[s] = rounds, current
    out = _copy_rows(stored.points, refs, n_refs)
    dims = sources.dims.copy()
    return out, ref_offsets, dims, iterations, added[:n_added], added_offsets, initial, final


@numba.njit(cache=True, nogil=True)
def _add_source(stored, row, box, counts, refs, n_refs):
    """Adds the points of ``row`` within the margin of its box (then, with 2 copies, their
    mirror images) and counts them in the box's grid cells."""
    points, copies = stored.points, box.copies
    d0, d1, d2 = box.dims[0], box.dims[1], box.dims[2]
    nx, ny, nz = box.grid[0], box.grid[1], box.grid[2]
    hx, hy, hz = d0 / 2.0 + box.margin, d1 / 2.0 + box.margin, d2 / 2.0 + box.margin
    start, stop = stored.offsets[row], stored.offsets[row + 1]
    refs = _reserve(refs, n_refs + copies * (stop - start))
    kept = 0
    for i in range(start, stop):
        x, y, z = _xyz(points, i, 0)
        # A mirror image is inside exactly when its point is, in the same x and z cells.
        if abs(x) <= hx and abs(y) <= hy and abs(z) <= hz:
            refs[n_refs + kept] = 2 * i
            kept += 1
            cx, cz = cell_of(x, d0, nx), cell_of(z, d2, nz)
            counts[(cx * ny + cell_of(y, d1, ny)) * nz + cz] += 1
            if copies == 2:
                counts[(cx * ny + cell_of(-y, d1, ny)) * nz + cz] += 1
    if copies == 2:
        for k in range(n_refs, n_refs + kept):
            refs[k + kept] = refs[k] + 1
    return refs, n_refs + copies * kept


@numba.njit(cache=True, nogil=True)
def _add_once(added, n_added, first, row, slot):
    """Appends ``row`` to ``added`` unless it is among ``added[first:n_added]``. ``slot[row]``
    remembers where ``row`` was put; it is only trusted when ``added`` agrees, so ``slot``
    needs no clearing (nor initialising) between objects."""
    k = slot[row]
    if first <= k < n_added and added[k] == row:
        return added, n_added
    added = _reserve(added, n_added + 1)
    added[n_added] = row
    slot[row] = n_added
    return added, n_added + 1


@numba.njit(cache=True, nogil=True)
def _gather(stored, row, cell, box, refs, n_refs, near):
    """Appends to ``refs`` the points of ``row`` (and, with 2 copies, their mirror images)
    that lie in ``cell`` of ``box`` and within its margin, in stored order. ``near`` is scratch
    space; returns ``(refs, n_refs, near)`` (either may have been replaced by a longer copy)."""
    points, copies = stored.points, box.copies
    d0, d1, d2 = box.dims[0], box.dims[1], box.dims[2]
    nx, ny, nz = box.grid[0], box.grid[1], box.grid[2]
    tx, ty, tz = cell // (ny * nz), (cell // nz) % ny, cell % nz
    hx, hy, hz = d0 / 2.0 + box.margin, d1 / 2.0 + box.margin, d2 / 2.0 + box.margin
    bx, by, bz = _band(tx, d0, nx, hx), _band(ty, d1, ny, hy), _band(tz, d2, nz, hz)
    start, stop = stored.offsets[row], stored.offsets[row + 1]
    refs = _reserve(refs, n_refs + copies * (stop - start))
    near = _reserve(near, stop - start)
    # First the points near the cell in x and z, without a branch (the outcome is a coin
    # toss for a point, and mispredictions cost more than the test); then the exact test.
    n_near = 0
    for i in range(start, stop):
        near[n_near] = i
        n_near += np.int64(abs(np.float64(points[i, 0]) - bx[0]) <= bx[1]) & np.int64(
            abs(np.float64(points[i, 2]) - bz[0]) <= bz[1]
        )
    for k in range(n_near):
        i = near[k]
        if not (
            _in_band(points[i, 0], bx, tx, d0, nx, hx)
            and _in_band(points[i, 2], bz, tz, d2, nz, hz)
        ):
            continue
        y = np.float64(points[i, 1])
        if _in_band(y, by, ty, d1, ny, hy):
            refs[n_refs] = 2 * i
            n_refs += 1
        if copies == 2 and _in_band(-y, by, ty, d1, ny, hy):
            refs[n_refs] = 2 * i + 1
            n_refs += 1
    return refs, n_refs, near


@numba.njit(cache=True, nogil=True)
def _per_object(n):
    return (
        np.zeros(n + 1, dtype=np.int64),
        np.zeros(n + 1, dtype=np.int64),
        np.zeros(n, dtype=np.int64),
        np.zeros(n, dtype=np.float64),
        np.zeros(n, dtype=np.float64),
    )


@numba.njit(cache=True, nogil=True)
def _capacity(offsets, rows):
    total = 1024
    for row in rows:
        total += 4 * (offsets[row + 1] - offsets[row])
    return total


@numba.njit(cache=True, nogil=True)
def _reserve(buffer, size):
    """``buffer``, or a copy at least twice as long when shorter than ``size``."""
    if size <= buffer.shape[0]:
        return buffer
    grown = np.empty(max(size, 2 * buffer.shape[0]), dtype=buffer.dtype)
    grown[: buffer.shape[0]] = buffer
    return grown


@numba.njit(cache=True, nogil=True)
def _copy_rows(points, refs, count):
    """The referenced rows ``(count, C)``; mirror images (odd references) have y negated."""
    out = np.empty((count, points.shape[1]), dtype=points.dtype)
    for t in range(count):
        i = refs[t] >> 1
        for c in range(points.shape[1]):
            out[t, c] = points[i, c]
        if refs[t] & 1:
            out[t, 1] = -points[i, 1]
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _xyz(points, i, copy):
    """float64 coordinates of point ``i`` (its mirror image when ``copy`` is 1)."""
    y = np.float64(points[i, 1])
    return np.float64(points[i, 0]), (-y if copy else y), np.float64(points[i, 2])


@numba.njit(cache=True, nogil=True, inline="always")
def _band(cell, size, count, half):
    """Where along one axis a coordinate may be (outer) and surely is (inner) in ``cell`` and
    within ``half`` of the centre, as ``(outer_mid, outer_half, inner_mid, inner_half)``.

    A speed device, not a rule: the cut between cells is ``cell * size / count - size / 2`` up
    to a few float64 roundings of the cell rule (:func:`drcpo.partitions.cell_of`); a guard of
    1e-9 relative dwarfs them, and values between the two intervals get the exact rule
    (:func:`_in_band`), so that most points cost no division.
    """
    lo = -half if cell == 0 else cell * size / count - size / 2.0
    hi = half if cell == count - 1 else (cell + 1) * size / count - size / 2.0
    guard = 1e-9 * (size + half)
    return (lo + hi) / 2.0, (hi - lo) / 2.0 + guard, (lo + hi) / 2.0, (hi - lo) / 2.0 - guard


@numba.njit(cache=True, nogil=True, inline="always")
def _in_band(value, band, cell, size, count, half):
    """``|value| <= half and cell_of(value) == cell``, exactly (NaN is never inside).

    One comparison per interval (``|value - mid| <= half width``): a pair of comparisons
    becomes two branches, the first one a coin toss, which costs more than the whole test.
    """
    value = np.float64(value)
    if not abs(value - band[0]) <= band[1]:
        return False
    if abs(value - band[2]) <= band[3]:
        return True
    return abs(value) <= half and cell_of(value, size, count) == cell


@numba.njit(cache=True, nogil=True)
def _normalisers(counts, class_scale, own):
    """Density normaliser per partition (1 where not fillable) and which are fillable."""
    n = counts.shape[0]
    fillable = np.ones(n, dtype=np.bool_)
    if own:
        largest = 1
        for p in range(n):
            largest = max(largest, counts[p])
        return np.full(n, np.float64(largest)), fillable
    scale = np.empty(n, dtype=np.float64)
    for p in range(n):
        fillable[p] = class_scale[p] > 0
        scale[p] = class_scale[p] if fillable[p] else 1.0
    return scale, fillable


@numba.njit(cache=True, nogil=True)
def _threshold(counts, scale, fillable):
    """Mean density of the occupied fillable partitions (summed in partition order)."""
    densities = np.empty(counts.shape[0], dtype=np.float64)
    n = 0
    for p in range(counts.shape[0]):
        if fillable[p] and counts[p] > 0:
            densities[n] = counts[p] / scale[p]
            n += 1
    return densities[:n].sum() / n if n else 0.0


@numba.njit(cache=True, nogil=True)
def _coverage(counts, scale, fillable, threshold):
    """Fraction of fillable partitions with density above ``threshold`` (1 when none)."""
    above = total = 0
    for p in range(counts.shape[0]):
        if fillable[p]:
            total += 1
            if counts[p] / scale[p] > threshold:
                above += 1
    return above / total if total else 1.0


@numba.njit(cache=True, nogil=True)
def _deficient(counts, scale, fillable, threshold):
    """Fillable partitions not above ``threshold``, ascending."""
    cells = np.empty(counts.shape[0], dtype=np.int64)
    n = 0
    for p in range(counts.shape[0]):
        if fillable[p] and not counts[p] / scale[p] > threshold:
            cells[n] = p
            n += 1
    return cells[:n]
