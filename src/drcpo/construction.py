"""Iterative construction of a whole-body object from its indexed candidates (DR.CPO, step 1).

Everything happens in the source object's canonical pose (centre at the origin, heading 0).

Mirror the object across the x axis when its class is mirrored,
cut its box into the class's partition grid and measure each partition's density (points in the
partition / the class's largest count in that partition, the candidate index's normalisation).
The threshold is the mean density of the object's non-empty partitions, measured once before the
first iteration (as the reference implementation does), so the process converges. Then repeat:
every partition whose density is not above the threshold receives the points that one candidate,
drawn uniformly at random from the object's candidates, has in that partition (the candidate's
points as stored, in its own canonical pose, mirrored like the source, assigned to the *source*
box's cells). Stop when at least ``coverage`` of the partitions are above the threshold, or after
``max_iterations``. Points more than ``margin`` outside the source box are dropped, so the label
still fits the object.

Partitions in which no object of the class has a point (class maximum 0) can never be filled;
they are left out of both the draw and the coverage fraction. Without ``class_max_counts`` the
object's own largest partition count normalises its densities, which leaves the comparison with
the mean, and so every decision, unchanged up to the candidate index's per-partition weighting.

Implementation: :func:`construct_objects` builds a batch of objects in one compiled (numba) call
that reads the candidates' points straight from the (memory-mapped) database and draws from the
``Generator`` exactly as the plain numpy formulation does (``rng.integers(0, K, size)`` per
iteration), so results
are bit-identical to it: same points in the same order, same thresholds (summed in numpy's
pairwise order), same rng state afterwards. ``tests/test_construction.py`` keeps that
formulation as the reference.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numba
import numpy as np

from drcpo.config_fields import Checked, spec
from drcpo.errors import DataError
from drcpo.partitions import DEFAULT_MIRRORED, Grid, cell_of, grid_for

__all__ = [
    "ConstructedObject",
    "ConstructionConfig",
    "construct_object",
    "construct_objects",
]


@dataclass(frozen=True, eq=False)
class ConstructionConfig(Checked):
    """Parameters of :func:`construct_object` (paper defaults): the config section
    ``drcpo.construction``, whose keys are these fields.

    Attributes:
        coverage: fraction of partitions that must be above the threshold to stop, in (0, 1].
        max_iterations: most rounds of additions (0 disables construction).
        margin: metres beyond the source box's faces within which added points are kept.
        mirror: classes mirrored across the x axis (y -> -y).
        grids: per-class partition grids overriding :data:`drcpo.partitions.DEFAULT_GRIDS`
            (``{"Car": [10, 4, 3], "default": [4, 2, 3]}``).

    The candidate index partitions and mirrors each class with the same ``grids`` and
    ``mirror`` (:class:`drcpo.index.IndexConfig` takes them from here).
    """

    KEY_PATH = "drcpo.construction"

    coverage: float = field(
        default=0.85,
        metadata=spec(
            "float", "stop when this share of partitions is dense", low=0.0, high=1.0, low_open=True
        ),
    )
    max_iterations: int = field(
        default=20, metadata=spec("int", "most construction rounds", low=0, high=1000)
    )
    margin: float = field(
        default=0.05,
        metadata=spec(
            "float", "metres beyond the box where added points are kept", low=0.0, high=1.0
        ),
    )
    mirror: list[str] = field(
        default_factory=lambda: list(DEFAULT_MIRRORED),
        metadata=spec("names", "classes mirrored across the x axis", classes=True),
    )
    grids: dict[str, list[int]] = field(
        default_factory=dict,
        metadata=spec("grids", "partition grid overrides per class", classes=True),
    )

    def grid(self, name: str) -> Grid:
        """The partition grid of class ``name``."""
        return grid_for(name, self.grids)


@dataclass(frozen=True, eq=False)
class ConstructedObject:
    """A constructed object in canonical pose.

    Attributes:
        points: ``float32 (n, 3 + C)`` points (features pass through), canonical pose.
        dims: ``float64 (3,)`` box size dx, dy, dz (metres), the source's.
        iterations: rounds of additions performed.
        added_from: ``int64`` database rows that contributed points, in order of first use.
        coverage_initial: fraction of fillable partitions above the threshold before
            construction (after mirroring).
        coverage: the same fraction after construction.
    """

    points: np.ndarray
    dims: np.ndarray
    iterations: int
    added_from: np.ndarray
    coverage_initial: float
    coverage: float


def construct_object(
    database,
    row: int,
    candidate_rows: np.ndarray,
    rng: np.random.Generator,
    config: ConstructionConfig | None = None,
    class_max_counts: np.ndarray | None = None,
) -> ConstructedObject:
    """Build a denser, whole-body version of database object ``row`` from its candidates.

    Args:
        database: a :class:`drcpo.database.GroundTruthDatabase` (points in canonical pose).
        row: database row of the source object.
        candidate_rows: ``(K,)`` database rows of its candidates (``-1`` entries are skipped), as
            listed by the candidate index; drawn uniformly at random.
        rng: the only source of randomness.
        config: :class:`ConstructionConfig` (paper defaults when ``None``).
        class_max_counts: ``(P,)`` (or zero-padded ``(P_max,)``) largest number of points any
            object of the class has in each partition, the index's density normalisation.
            ``None``: the object's own largest partition count (see the module docstring).

    Returns:
        :class:`ConstructedObject`. An object without candidates (or with
        ``max_iterations = 0``) comes back with its (mirrored) points and 0 iterations.
    """
    return construct_objects(database, [row], [candidate_rows], rng, config, [class_max_counts])[0]


def construct_objects(
    database,
    rows: Sequence[int] | np.ndarray,
    candidate_rows: Sequence[np.ndarray] | np.ndarray,
    rng: np.random.Generator,
    config: ConstructionConfig | None = None,
    class_max_counts: Mapping[str, np.ndarray] | Sequence[np.ndarray | None] | None = None,
) -> list[ConstructedObject]:
    """:func:`construct_object` for several objects in one compiled call.

    The objects draw from ``rng`` one after the other, so the result (and ``rng``'s state
    afterwards) is that of calling :func:`construct_object` on each in turn. Every input is
    checked before anything is drawn.

    Args:
        database: a :class:`drcpo.database.GroundTruthDatabase`.
        rows: ``(S,)`` database rows of the source objects.
        candidate_rows: ``(S, K)`` candidate rows per object, ``-1`` padded (the candidate
            index's ``candidates[rows]``), or ``S`` sequences of rows.
        rng: the only source of randomness.
        config: :class:`ConstructionConfig` (paper defaults when ``None``).
        class_max_counts: per class name (the index's ``max_counts``; a class left out uses its
            objects' own maxima), or per object (``None`` entries likewise), or ``None``.

    Returns:
        The :class:`ConstructedObject` of each row, in order. Their arrays are views into
        arrays shared by the call.
    """
    config = config or ConstructionConfig()
    n_objects = len(database)
    rows = _valid_rows(rows, n_objects)
    dims = np.asarray(database.boxes, dtype=np.float64)[rows, 3:6]
    degenerate = ~(np.isfinite(dims) & (dims > 0)).all(axis=1)
    if degenerate.any():
        k = int(np.argmax(degenerate))
        raise DataError(f"database object {rows[k]} has a degenerate box size {dims[k].tolist()}")
    candidates = _candidate_matrix(candidate_rows, rows, n_objects)
    sources = _Sources(rows, dims, *_class_settings(database, rows, config, class_max_counts))
    if len(rows) == 0:
        return []
    limits = _Limits(float(config.margin), int(config.max_iterations), float(config.coverage))
    return _objects(*_construct_partition(_stored(database), sources, candidates, limits, rng))


def _valid_rows(rows, n_objects: int) -> np.ndarray:
    rows = np.asarray(rows).reshape(-1)
    if rows.dtype.kind not in "iu":
        rows = np.array([int(r) for r in rows.tolist()], dtype=np.int64)
    outside = (rows < -n_objects) | (rows >= n_objects)
    if outside.any():
        row = rows[int(np.argmax(outside))]
        raise DataError(f"object row {row} is out of range for a database of {n_objects}")
    return rows.astype(np.int64) % max(n_objects, 1)


def _candidate_matrix(candidate_rows, rows: np.ndarray, n_objects: int) -> np.ndarray:
    """``int64 (S, K)`` candidate rows per object, ``-1`` padded (any negative is a pad)."""
    if isinstance(candidate_rows, np.ndarray) and candidate_rows.ndim == 2:
        if len(candidate_rows):
            _check_integers(candidate_rows, rows[0] if len(rows) else -1)
        matrix = candidate_rows.astype(np.int64, copy=False)
    else:
        lines = [np.asarray(line).reshape(-1) for line in candidate_rows]
        if len(lines) == len(rows):
            for row, line in zip(rows, lines, strict=True):
                _check_integers(line, row)
        matrix = np.full((len(lines), max(map(len, lines), default=0)), -1, dtype=np.int64)
        for k, line in enumerate(lines):
            matrix[k, : len(line)] = line
    if len(matrix) != len(rows):
        raise DataError(f"{len(matrix)} candidate lists for {len(rows)} objects")
    if matrix.size and matrix.max() >= n_objects:
        k = int(np.argmax((matrix >= n_objects).any(axis=1)))
        raise DataError(
            f"candidate row {int(matrix[k].max())} of object {rows[k]} is out of range for a "
            f"database of {n_objects} objects (index built for another database?)"
        )
    return matrix


def _check_integers(candidates: np.ndarray, row: int) -> None:
    if candidates.size and not np.issubdtype(candidates.dtype, np.integer):
        raise DataError(f"candidate rows of object {row} must be integers, got {candidates.dtype}")


def _class_settings(database, rows, config, class_max_counts):
    """Per object: grid ``(S, 3)``, mirrored ``(S,)``, density normalisers ``(S, P_max)`` and
    whether to use the object's own maximum instead ``(S,)``."""
    classes: dict[str, int] = {}
    of_class = np.array(
        [classes.setdefault(name, len(classes)) for name in database.names[rows].tolist()],
        dtype=np.int64,
    )
    grids = np.array([config.grid(name) for name in classes], dtype=np.int64).reshape(-1, 3)
    mirror = np.array([name in config.mirror for name in classes], dtype=np.bool_)
    n_cells = grids.prod(axis=1)
    if class_max_counts is None or isinstance(class_max_counts, Mapping):
        given = class_max_counts or {}
        values = [given.get(name) for name in classes]
        owner, cells = of_class, n_cells
    else:
        values = list(class_max_counts)
        if len(values) != len(rows):
            raise DataError(f"{len(values)} class_max_counts for {len(rows)} objects")
        owner, cells = np.arange(len(rows)), n_cells[of_class]
    scales = np.zeros((len(values), int(n_cells.max(initial=1))), dtype=np.float64)
    own_scale = np.array([value is None for value in values], dtype=np.bool_)
    for k in np.flatnonzero(~own_scale):
        scales[k, : cells[k]] = _normaliser(values[k], int(cells[k]))
    return grids[of_class], mirror[of_class], scales[owner], own_scale[owner]


def _normaliser(values, n_cells: int) -> np.ndarray:
    scale = np.asarray(values, dtype=np.float64).reshape(-1)
    if len(scale) < n_cells or (len(scale) > n_cells and scale[n_cells:].any()):
        raise DataError(
            f"class_max_counts has {len(scale)} entries; the grid has {n_cells} partitions"
        )
    return scale[:n_cells]


def _objects(points, point_offsets, dims, iterations, added, added_offsets, initial, final):
    ends, added_ends = point_offsets.tolist(), added_offsets.tolist()
    return [
        ConstructedObject(
            points=points[ends[k] : ends[k + 1]],
            dims=dims[k],
            iterations=rounds,
            added_from=added[added_ends[k] : added_ends[k + 1]],
            coverage_initial=before,
            coverage=after,
        )
        for k, (rounds, before, after) in enumerate(
            zip(iterations.tolist(), initial.tolist(), final.tolist(), strict=True)
        )
    ]


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


def _stored(database) -> _Stored:
    return _Stored(np.asarray(database.points), np.asarray(database.offsets, dtype=np.int64))


# Compiled kernels -------------------------------------------------------------------------
# Points are referenced as 2 * (row in ``database.points``) + (1 for the mirror image) while
# objects grow; the rows are copied out once at the end.


@numba.njit(cache=True, nogil=True)
def _construct_partition(stored, sources, candidates, limits, rng):
    """Construction of every object of ``sources`` in turn (see the module docstring).

    Each iteration draws one candidate per deficient partition (ascending partition order, as
    ``rng.integers(0, K, size)`` draws), then adds the points that each drawn candidate (and
    its mirror image) has in that partition of the source box, in stored order, each mirror
    image right after its point. Returns what :func:`_objects` takes.
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
    """Mean density of the occupied fillable partitions, summed as ``numpy.mean`` sums."""
    densities = np.empty(counts.shape[0], dtype=np.float64)
    n = 0
    for p in range(counts.shape[0]):
        if fillable[p] and counts[p] > 0:
            densities[n] = counts[p] / scale[p]
            n += 1
    return _numpy_sum(densities, n) / n if n else 0.0


@numba.njit(cache=True, nogil=True)
def _numpy_sum(values, n):
    """``values[:n].sum()`` in numpy's pairwise order, so that thresholds equal
    ``numpy.mean``'s bit for bit: blocks of up to 128 values are summed by :func:`_block_sum`,
    longer runs split in two (the first half a multiple of 8) and the halves' sums added.
    Iterative, because numba's cache cannot load recursive functions."""
    if n <= 128:
        return _block_sum(values, 0, n)
    # Post-order walk of the split tree: a task is a run (start, length) or, with length -1,
    # "add the last two sums".
    starts = np.empty(256, dtype=np.int64)
    lengths = np.empty(256, dtype=np.int64)
    sums = np.empty(128, dtype=np.float64)
    starts[0], lengths[0] = 0, n
    n_tasks, n_sums = 1, 0
    while n_tasks:
        n_tasks -= 1
        start, length = starts[n_tasks], lengths[n_tasks]
        if length < 0:
            n_sums -= 1
            sums[n_sums - 1] += sums[n_sums]
        elif length <= 128:
            sums[n_sums] = _block_sum(values, start, length)
            n_sums += 1
        else:
            first = length // 2
            first -= first % 8
            starts[n_tasks], lengths[n_tasks] = 0, -1
            starts[n_tasks + 1], lengths[n_tasks + 1] = start + first, length - first
            starts[n_tasks + 2], lengths[n_tasks + 2] = start, first
            n_tasks += 3
    return sums[0]


@numba.njit(cache=True, nogil=True)
def _block_sum(values, start, n):
    """numpy's pairwise_sum for ``n <= 128`` values: 8 running sums, then the rest in turn."""
    if n < 8:
        total = 0.0
        for i in range(start, start + n):
            total += values[i]
        return total
    r0, r1, r2, r3 = values[start], values[start + 1], values[start + 2], values[start + 3]
    r4, r5, r6, r7 = values[start + 4], values[start + 5], values[start + 6], values[start + 7]
    i = start + 8
    stop = start + n - n % 8
    while i < stop:
        r0, r1, r2, r3 = r0 + values[i], r1 + values[i + 1], r2 + values[i + 2], r3 + values[i + 3]
        r4, r5, r6, r7 = (
            r4 + values[i + 4],
            r5 + values[i + 5],
            r6 + values[i + 6],
            r7 + values[i + 7],
        )
        i += 8
    total = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    for j in range(i, start + n):
        total += values[j]
    return total


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
