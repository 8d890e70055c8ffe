"""Building the candidate index (:mod:`drcpo.index`, DR.CPO pre-processing): for every object,
the K best objects to fill it.

For each class, every *indexed* object i (enough points, difficulty not excluded) gets up to K
candidates among the indexed objects of its class, chosen in two stages:

1. **Similar boxes.** The best ``2K`` objects by 3D IoU of the canonical boxes,
   ``prod(min dims) / (vol_i + vol_j - prod(min dims))`` (never i itself), ranked by IoU
   (descending), then database row (ascending).
2. **Filling.** Of those, the best K by how much density they bring to i's low-density
   partitions: a partition of i is *low* when its density is below ``alpha`` times the mean of
   i's non-empty partition densities (all partitions when i has no points); the score of a
   candidate is the sum of its densities over i's low partitions. Ranked by score (descending),
   then stage-1 rank. A class with fewer objects gives each object all the others.

**Densities.** Partition p of object i has density ``count_i[p] / max_j count_j[p]`` where the
maximum runs over the class's indexed objects and counts use the cell rule of
:mod:`drcpo.partitions` (mirrored classes count each point and its mirror image); 0 where the
maximum is 0. Objects of an indexed class that are not themselves indexed still get densities
(with the same maxima, so they may exceed 1).

**Exact top-2K without an N x N matrix.** With ``u = log(dims)`` and ``p``/``q`` the sums of the
positive/negative parts of ``u_i - u_j``, the IoU is exactly ``1 / (exp(p) + exp(q) - 1)``. The
objects are bucketed in a uniform grid over u-space; each object searches the cells around its
own in rings of growing Chebyshev radius, keeping its best 2K in a bounded heap, skips every cell
whose lower bounds on p and q already make the IoU smaller than the heap's worst, and stops once a
whole ring is out of reach (``IoU <= exp(-L_inf distance)``). The result equals the brute-force
ranking, ties included (tested). Of a group of identical boxes only the 2K + 1 lowest rows can
rank for anyone, so the surplus is left out of the search (a class of identical boxes would
otherwise cost O(N^2)). The cell size adapts to the class's density, so the cost per object
depends on K and hardly on N. Objects are processed in blocks, in cell order; blocks write
disjoint rows, so the result does not depend on who ranks them (a cluster's workers may).

**Approximate mode** (classes with more than ``approximate_above`` indexed objects; off by
default): the ``approx_factor x 2K`` nearest neighbours in u-space by L1 distance
(``scipy.spatial.cKDTree``) are re-ranked by exact IoU and the best 2K kept. Stage 2 is unchanged.
Its recall against the exact top-2K is measured by ``benchmarks/bench_index.py``
(``approx_recall``, :func:`drcpo.similarity.similarity_recall`). On realistic size distributions
the exact grid search is faster than the k-d tree query itself (1,000,000 objects: see the
benchmark), which is why the exact search is the default at every size; the approximate mode
remains for size distributions so spread out that the grid search degrades.

**Arithmetic.** IoUs are computed in float64 as in :func:`drcpo.geometry.canonical_iou3d`.
Scores and means are float64 sums of float32 densities, which are exact (so independent of the
summation order) as long as no partition maximum exceeds about 10^6 points.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numba as nb
import numpy as np

from drcpo.database import GroundTruthDatabase
from drcpo.errors import ConfigError, DataError
from drcpo.index import CandidateIndex, IndexConfig
from drcpo.partitions import Grid, flat_cell, num_partitions
from drcpo.similarity import SimilaritySearch

__all__ = [
    "MapBlocks",
    "build_index",
    "indexed_mask",
    "normalise_counts",
    "partition_occupancy",
    "rank_candidates",
]


#: ``progress(class_name, objects_done, objects_total)``, called from the calling thread.
Progress = Callable[[str, int, int], None]
_CHUNK_POINTS = 1 << 20  # points per chunk when counting partition occupancy


# --------------------------------------------------------------------------------------------
# Building
# --------------------------------------------------------------------------------------------
def indexed_mask(database: GroundTruthDatabase, config: IndexConfig) -> np.ndarray:
    """``bool (N,)``: objects that are indexed and may be candidates."""
    keep = database.num_points >= config.min_points
    if config.exclude_difficulty:
        keep &= ~np.isin(database.difficulty, np.asarray(config.exclude_difficulty))
    if config.classes is not None:
        keep &= np.isin(database.names, np.asarray(config.classes, dtype=str))
    return keep


def build_index(
    database: GroundTruthDatabase,
    config: IndexConfig | None = None,
    progress: Progress | None = None,
    map_blocks: MapBlocks | None = None,
) -> CandidateIndex:
    """Build the candidate index of ``database`` (see the module docstring for the method).

    ``map_blocks``: who ranks the blocks of objects (:data:`MapBlocks`; e.g. the workers of a
    cluster, :mod:`drcpo.distributed`); default: this process, in order.
    The index does not depend on it.

    Raises :class:`DataError` before any work when the database's data does not match its
    manifest checksum (:meth:`GroundTruthDatabase.verified_checksum`; a database opened with
    ``verify=False`` is verified here): the index records that checksum, and must not vouch
    for a modified database.
    """
    config = config or IndexConfig()
    checksum = database.verified_checksum()
    names = database.names
    present = set(names.tolist())
    classes = sorted(present if config.classes is None else present & set(config.classes))
    grids = {name: config.grid(name) for name in classes}
    p_max = max((num_partitions(g) for g in grids.values()), default=1)
    keep = indexed_mask(database, config)

    n = len(database)
    rows_of = {name: np.flatnonzero(names == name) for name in classes}
    indexed_of = {name: rows[keep[rows]] for name, rows in rows_of.items()}
    _check_table_fits(n, config.k, {name: len(rows) for name, rows in indexed_of.items()})
    densities, max_counts = _densities(database, grids, config.mirror, p_max, indexed_of)
    candidates = np.full((n, config.k), -1, np.int32)
    stats: dict[str, dict[str, Any]] = {}
    for name in classes:
        indexed = indexed_of[name]
        mode = _mode_for(len(indexed), config)
        if len(indexed) > 1:
            rank_candidates(
                database.boxes[indexed, 3:6],
                densities[indexed, : num_partitions(grids[name])],
                config,
                mode=mode,
                progress=None if progress is None else _named(progress, name),
                rows=indexed,
                out=candidates,
                map_blocks=map_blocks,
            )
        elif progress is not None:
            progress(name, len(indexed), len(indexed))
        found = sum(int((candidates[chunk] >= 0).sum()) for chunk in _chunks(indexed))
        stats[name] = {
            "objects": len(rows_of[name]),
            "indexed": len(indexed),
            "mean_candidates": found / len(indexed) if len(indexed) else 0.0,
            "mode": mode,
        }
    return CandidateIndex(candidates, densities, grids, max_counts, config, checksum, stats)


def _check_table_fits(n: int, k: int, indexed: Mapping[str, int]) -> None:
    """Refuse, before allocating it, an ``int32 (n, k)`` candidate table larger than memory."""
    need = n * k * np.dtype(np.int32).itemsize
    have = _memory_bytes()
    if have is None or need <= have:
        return
    largest = max(indexed, key=lambda name: indexed[name], default=None)
    most = max(indexed[largest] - 1, 0) if largest is not None else 0
    raise ConfigError(
        f"index K = {k} for {n} objects needs a candidate table of {_fmt_bytes(need)} "
        f"(int32 N x K), more than this machine's {_fmt_bytes(have)} of memory; the largest "
        f"class ({largest}, {most + 1} indexed objects) gives an object at most {most} "
        "candidates: choose a smaller K"
    )


def _memory_bytes() -> int | None:
    """Physical memory of this machine in bytes (``None`` where the OS does not say)."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, OSError, ValueError):
        return None


def _fmt_bytes(count: float) -> str:
    """``6000000`` -> ``"5.7 MiB"`` (binary units, up to TiB)."""
    units = ("B", "KiB", "MiB", "GiB", "TiB")
    power = min(int(math.log(max(count, 1), 1024)), len(units) - 1)
    return f"{count / 1024**power:.1f} {units[power]}"


def _densities(
    database: GroundTruthDatabase,
    grids: Mapping[str, Grid],
    mirrored: Iterable[str],
    p_max: int,
    indexed_of: Mapping[str, np.ndarray],
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Densities ``float32 (N, P_max)`` and each class's maxima over its indexed objects."""
    counts = partition_occupancy(database, grids, mirrored, p_max)
    densities = np.zeros((len(database), p_max), np.float32)
    max_counts: dict[str, np.ndarray] = {}
    for name, grid in grids.items():
        p = num_partitions(grid)
        top = np.zeros(p, np.int64)
        for chunk in _chunks(indexed_of[name]):
            np.maximum(top, counts[chunk, :p].max(axis=0), out=top)
        max_counts[name] = top
        for chunk in _chunks(np.flatnonzero(database.names == name)):
            densities[chunk, :p] = normalise_counts(counts[chunk, :p], top)
    return densities, max_counts


def _chunks(rows: np.ndarray, size: int = 1 << 16) -> Iterable[np.ndarray]:
    """Consecutive pieces of ``rows``, so that per-row temporaries stay small."""
    for start in range(0, len(rows), size):
        yield rows[start : start + size]


def _named(progress: Progress, name: str) -> Callable[[int, int], None]:
    return lambda done, total: progress(name, done, total)


def _mode_for(num_indexed: int, config: IndexConfig) -> str:
    above = config.approximate_above
    return "approximate" if above is not None and num_indexed > above else "exact"


def normalise_counts(counts: np.ndarray, max_counts: np.ndarray) -> np.ndarray:
    """Densities ``float32 (M, P)``: ``counts / max_counts`` per column, 0 where the max is 0."""
    counts = np.asarray(counts, np.float64)
    scale = np.asarray(max_counts, np.float64)
    out = np.divide(counts, scale, out=np.zeros_like(counts), where=scale > 0)
    return out.astype(np.float32)


# --------------------------------------------------------------------------------------------
# Partition occupancy of many objects at once
# --------------------------------------------------------------------------------------------
def partition_occupancy(
    database: GroundTruthDatabase,
    grids: Mapping[str, Grid],
    mirrored: Iterable[str],
    p_max: int | None = None,
    chunk_points: int = _CHUNK_POINTS,
) -> np.ndarray:
    """Points per partition ``int32 (N, P_max)`` of every object of the classes in ``grids``.

    The cell rule :func:`drcpo.partitions.flat_cell`, for all objects over the concatenated
    points, in chunks of about ``chunk_points`` points. Objects of
    mirrored classes count each point twice (as itself and mirrored, y -> -y). Rows of classes
    not in ``grids`` stay 0.

    Raises :class:`DataError` if a box of an included object has a non-positive or non-finite size.
    """
    n = len(database)
    p_max = p_max or max((num_partitions(g) for g in grids.values()), default=1)
    grid_of = np.zeros((n, 3), np.int64)
    is_mirrored = np.zeros(n, bool)
    mirrored = set(mirrored)
    for name, grid in grids.items():
        rows = database.names == name
        grid_of[rows] = grid
        is_mirrored[rows] = name in mirrored
    included = grid_of[:, 0] > 0
    dims = np.asarray(database.boxes[:, 3:6], np.float64)
    bad = included & ~(np.isfinite(dims).all(axis=1) & (dims > 0).all(axis=1))
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise DataError(
            f"{database.path or '<memory>'}: object {row} ({database.names[row]}) has box size "
            f"{dims[row].tolist()}; sizes must be positive and finite"
        )
    counts = np.zeros((n, p_max), np.int32)
    offsets = np.asarray(database.offsets)
    start = 0
    while start < n:
        stop = int(np.searchsorted(offsets, offsets[start] + chunk_points, side="right")) - 1
        stop = min(max(stop, start + 1), n)
        sel = slice(start, stop)
        counts[sel] = _chunk_occupancy(
            database.points[offsets[start] : offsets[stop], :3],
            np.diff(offsets[start : stop + 1]),
            dims[sel],
            grid_of[sel],
            is_mirrored[sel],
            p_max,
        )
        start = stop
    return counts


def _chunk_occupancy(
    xyz: np.ndarray,
    sizes: np.ndarray,
    dims: np.ndarray,
    grid: np.ndarray,
    mirrored: np.ndarray,
    p_max: int,
) -> np.ndarray:
    """Points per partition ``int32 (m, p_max)`` of ``m`` consecutive objects, whose ``(n, 3)``
    points ``xyz`` are ``sizes`` ``(m,)`` long each."""
    return _occupancy(np.asarray(xyz), np.asarray(sizes, np.int64), dims, grid, mirrored, p_max)


@nb.njit(cache=True, nogil=True)
def _occupancy(xyz, sizes, dims, grid, mirrored, p_max):  # pragma: no cover - numba
    out = np.zeros((sizes.shape[0], p_max), np.int32)
    start = 0
    for m in range(sizes.shape[0]):
        stop = start + sizes[m]
        if grid[m, 0] > 0:
            for i in range(start, stop):
                x, y, z = np.float64(xyz[i, 0]), np.float64(xyz[i, 1]), np.float64(xyz[i, 2])
                out[m, flat_cell(x, y, z, dims[m], grid[m])] += 1
                if mirrored[m]:
                    out[m, flat_cell(x, -y, z, dims[m], grid[m])] += 1
        start = stop
    return out


# --------------------------------------------------------------------------------------------
# Ranking (both stages) for one class
# --------------------------------------------------------------------------------------------
def rank_candidates(
    dims: np.ndarray,
    densities: np.ndarray,
    config: IndexConfig,
    mode: str = "exact",
    progress: Callable[[int, int], None] | None = None,
    rows: np.ndarray | None = None,
    out: np.ndarray | None = None,
    map_blocks: MapBlocks | None = None,
) -> np.ndarray:
    """Candidates of every object of one class, best first.

    Args:
        dims: ``(M, 3)`` box sizes (m) of the class's indexed objects, in database-row order
            (so local id order is row order, which breaks ties).
        densities: ``float32 (M, P)`` their partition densities.
        config: ``k``, ``alpha``, ``approx_factor``, ``block_size``.
        mode: ``"exact"`` or ``"approximate"`` first stage.
        rows: ``(M,)`` database rows of the objects; with ``out``, object i's candidates are
            written as database rows to ``out[rows[i], :min(k, M - 1)]``.
        out: ``int32 (N, >= min(k, M - 1))`` array to write into.
        map_blocks: runs the blocks (:data:`MapBlocks`; default: threads of this process).

    Returns:
        ``out``, or without it local ids ``int32 (M, min(k, M - 1))``, ``-1`` padded.
    """
    m = len(dims)
    s = min(2 * config.k, m - 1)
    k = min(config.k, m - 1)
    if out is None:
        out = np.full((m, max(k, 0)), -1, np.int32)
        rows = np.arange(m)
    elif rows is None or len(rows) != m:
        raise ValueError("rank_candidates: out= needs rows= with one row per object")
    if k <= 0:
        return out
    search = SimilaritySearch(dims, s, mode=mode, approx_factor=config.approx_factor)
    # Densities in query (cell) order: neighbours of neighbouring queries share cache lines.
    position = np.empty(m, np.int64)
    position[search.order] = np.arange(m)
    densities = np.ascontiguousarray(np.asarray(densities, np.float32)[search.order])
    totals = densities.sum(axis=1, dtype=np.float64)
    # Index -1 (padding) picks the appended -1.
    labels = np.append(np.asarray(rows, np.int32), np.int32(-1))
    alpha = float(config.alpha)

    def work(start: int) -> tuple[int, np.ndarray]:
        block = search.order[start : start + config.block_size]
        ids, _ = search.top(block)
        return start, _fill_rank(ids, densities, totals, position, start, alpha, k)

    starts = np.arange(0, m, config.block_size)
    for start, ranked in (map_blocks or _map_blocks)(work, starts, m, config, progress):
        block = search.order[start : start + config.block_size]
        out[labels[block], :k] = labels[ranked]
    return out


#: ``map_blocks(work, items, total, config, progress)``: ``work(item)`` of every item, yielded
#: in item order; ``progress(done, total)`` advances by ``config.block_size`` per item.
#: ``work`` is a closure over one class's arrays (picklable with cloudpickle).
MapBlocks = Callable[..., Iterable[Any]]


def _map_blocks(
    work: Callable[[Any], Any],
    items: Iterable[Any],
    total: int,
    config: IndexConfig,
    progress: Callable[[int, int], None] | None,
) -> Iterable[Any]:
    """``work(item)`` for each item, in order; ``progress(done, total)`` advances by
    ``block_size`` per item."""
    done = 0
    for item in items:
        result = work(item)
        done = min(done + config.block_size, total)
        if progress is not None:
            progress(done, total)
        yield result


# --------------------------------------------------------------------------------------------
# Second stage: the best ``k`` of those by density filled in
# --------------------------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _fill_rank(ids, densities, totals, position, first, alpha, k):  # pragma: no cover - numba
    """Best ``k`` of each row of ``ids`` (ranked list, -1 padded) by fill score, then rank.

    Object j's densities are ``densities[position[j]]`` and their float64 sum
    ``totals[position[j]]``; row b of ``ids`` belongs to the object at position ``first + b``.
    """
    nq, s = ids.shape
    p = densities.shape[1]
    out = np.full((nq, k), -1, np.int32)
    low = np.empty(p, np.bool_)
    terms = np.empty(p, np.int64)
    score = np.empty(s, np.float64)
    for b in range(nq):
        d = densities[first + b]
        total = 0.0
        filled = 0
        for c in range(p):
            if d[c] > 0:
                total += np.float64(d[c])
                filled += 1
        n_low = 0
        for c in range(p):
            low[c] = filled == 0 or np.float64(d[c]) < alpha * (total / filled)
            n_low += low[c]
        # Sum over the low partitions, or subtract the others from the total when they are
        # fewer; both are exact (see the module docstring), so the scores are identical.
        complement = 2 * n_low > p
        n_terms = 0
        for c in range(p):
            if low[c] != complement:
                terms[n_terms] = c
                n_terms += 1
        n = s
        for c in range(s):
            j = ids[b, c]
            if j < 0:
                n = c
                break
            row = position[j]
            acc = 0.0
            for e in range(n_terms):
                acc += np.float64(densities[row, terms[e]])
            score[c] = acc - totals[row] if complement else -acc
        # A stable sort of the negated scores keeps equal scores in first-stage order.
        order = np.argsort(score[:n], kind="mergesort")
        for c in range(min(k, n)):
            out[b, c] = ids[b, order[c]]
    return out
