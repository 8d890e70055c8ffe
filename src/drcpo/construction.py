"""Iterative construction of a whole-body object from its indexed candidates (DR.CPO, step 1).

Everything happens in the source object's canonical pose (centre at the origin, heading 0).

``partition`` mode (the paper): mirror the object across the x axis when its class is mirrored,
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

``whole`` mode (the reference implementation's variant): each iteration adds all (mirrored)
points of one candidate drawn without replacement, the densities are measured on the source box's
grid (points beyond its faces count in the outermost cells), the same stop rule applies, and the
box grows to contain every point (``dims = max(source dims, 2 max |xyz|)``).

Partitions in which no object of the class has a point (class maximum 0) can never be filled;
they are left out of both the draw and the coverage fraction. Without ``class_max_counts`` the
object's own largest partition count normalises its densities, which leaves the comparison with
the mean, and so every decision, unchanged up to the candidate index's per-partition weighting.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numba
import numpy as np

from drcpo.errors import ConfigError, DataError
from drcpo.partitions import (
    DEFAULT_MIRRORED,
    Grid,
    grid_for,
    mirror_points,
    partition_counts,
)

MODES = ("partition", "whole")


@dataclass(frozen=True)
class ConstructionConfig:
    """Parameters of :func:`construct_object` (paper defaults).

    Attributes:
        mode: ``"partition"`` (the paper) or ``"whole"`` (the reference implementation).
        coverage: fraction of partitions that must be above the threshold to stop, in (0, 1].
        max_iterations: most rounds of additions (0 disables construction).
        margin: metres beyond the source box's faces within which added points are kept
            (``partition`` mode).
        mirrored_classes: classes mirrored across the x axis (y -> -y).
        grids: per-class partition grids overriding :data:`drcpo.partitions.DEFAULT_GRIDS`
            (``{"Car": (10, 4, 3), "default": (4, 2, 3)}``); stored as sorted pairs.
    """

    mode: str = "partition"
    coverage: float = 0.85
    max_iterations: int = 20
    margin: float = 0.05
    mirrored_classes: tuple[str, ...] = DEFAULT_MIRRORED
    grids: Mapping[str, Grid] | tuple[tuple[str, Grid], ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"construction.mode must be one of {MODES}, got {self.mode!r}")
        if not 0 < self.coverage <= 1:
            raise ConfigError(f"construction.coverage must be in (0, 1], got {self.coverage}")
        if int(self.max_iterations) != self.max_iterations or self.max_iterations < 0:
            raise ConfigError(
                f"construction.max_iterations must be an integer >= 0, got {self.max_iterations}"
            )
        if not self.margin >= 0:
            raise ConfigError(f"construction.margin must be >= 0 metres, got {self.margin}")
        if isinstance(self.mirrored_classes, str):
            raise ConfigError("construction.mirrored_classes must be a list of class names")
        object.__setattr__(self, "mirrored_classes", tuple(str(c) for c in self.mirrored_classes))
        pairs = self.grids.items() if isinstance(self.grids, Mapping) else self.grids
        grids = tuple(sorted((str(name), _valid_grid(name, grid)) for name, grid in pairs))
        object.__setattr__(self, "grids", grids)
        object.__setattr__(self, "max_iterations", int(self.max_iterations))

    def grid(self, name: str) -> Grid:
        """The partition grid of class ``name``."""
        return grid_for(name, dict(self.grids))


def _valid_grid(name: str, grid) -> Grid:
    try:
        return grid_for(str(name), {str(name): tuple(grid)})
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"construction.grids.{name}: {exc}") from exc


@dataclass(frozen=True, eq=False)
class ConstructedObject:
    """A constructed object in canonical pose.

    Attributes:
        points: ``float32 (n, 3 + C)`` points (features pass through), canonical pose.
        dims: ``float64 (3,)`` box size dx, dy, dz (metres); the source's in ``partition`` mode.
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
    config = config or ConstructionConfig()
    n_objects = len(database)
    if not -n_objects <= int(row) < n_objects:
        raise DataError(f"object row {row} is out of range for a database of {n_objects}")
    row = int(row) % n_objects
    name = str(database.names[row])
    dims = np.asarray(database.boxes[row, 3:6], dtype=np.float64)
    if not (np.isfinite(dims).all() and (dims > 0).all()):
        raise DataError(f"database object {row} has a degenerate box size {dims.tolist()}")
    candidates = _valid_candidates(candidate_rows, n_objects, row)
    mirror = name in config.mirrored_classes
    source = np.asarray(database.object_points(row))
    source = mirror_points(source) if mirror else source.copy()
    grid = config.grid(name)
    if config.mode == "partition":
        return _construct_partition(
            database, source, dims, grid, candidates, rng, config, mirror, class_max_counts
        )
    return _construct_whole(
        database, source, dims, grid, candidates, rng, config, mirror, class_max_counts
    )


def _valid_candidates(candidate_rows: np.ndarray, n_objects: int, row: int) -> np.ndarray:
    rows = np.asarray(candidate_rows).reshape(-1)
    if rows.size and not np.issubdtype(rows.dtype, np.integer):
        raise DataError(f"candidate rows of object {row} must be integers, got {rows.dtype}")
    rows = rows[rows >= 0].astype(np.int64)
    if rows.size and rows.max() >= n_objects:
        raise DataError(
            f"candidate row {int(rows.max())} of object {row} is out of range for a database "
            f"of {n_objects} objects (index built for another database?)"
        )
    return rows


class _Densities:
    """Partition counts of the growing object and the fixed threshold of the stop rule."""

    def __init__(self, counts: np.ndarray, class_max_counts: np.ndarray | None) -> None:
        n = len(counts)
        if class_max_counts is None:
            scale = np.full(n, float(max(counts.max(initial=0), 1)))
        else:
            scale = np.asarray(class_max_counts, dtype=np.float64).reshape(-1)
            if len(scale) < n or (len(scale) > n and scale[n:].any()):
                raise DataError(
                    f"class_max_counts has {len(scale)} entries; the grid has {n} partitions"
                )
            scale = scale[:n]
        self.fillable = scale > 0
        self.scale = np.where(self.fillable, scale, 1.0)
        self.counts = counts.astype(np.int64)
        density = self.counts / self.scale
        occupied = self.fillable & (self.counts > 0)
        self.threshold = float(density[occupied].mean()) if occupied.any() else 0.0

    def above(self) -> np.ndarray:
        return self.fillable & (self.counts / self.scale > self.threshold)

    def coverage(self) -> float:
        fillable = int(self.fillable.sum())
        return float(self.above().sum() / fillable) if fillable else 1.0

    def deficient(self) -> np.ndarray:
        return np.flatnonzero(self.fillable & ~self.above())


def _construct_partition(
    database, source, dims, grid, candidates, rng, config, mirror, class_max_counts
) -> ConstructedObject:
    source = source[_inside(source, dims, config.margin)]
    densities = _Densities(partition_counts(source, dims, grid), class_max_counts)
    initial = current = densities.coverage()
    chunks, contributors, iterations = [source], [], 0
    points, offsets = _database_arrays(database)
    while candidates.size and iterations < config.max_iterations and current < config.coverage:
        deficient = densities.deficient()
        drawn = candidates[rng.integers(0, len(candidates), size=len(deficient))]
        gathered, per_pair = _gather_partition_points(
            points,
            offsets,
            drawn,
            deficient,
            dims,
            np.asarray(grid, dtype=np.int64),
            mirror,
            float(config.margin),
        )
        iterations += 1
        densities.counts[deficient] += per_pair
        chunks.append(gathered)
        contributors.append(drawn[per_pair > 0])
        current = densities.coverage()
    return ConstructedObject(
        points=np.concatenate(chunks) if len(chunks) > 1 else chunks[0],
        dims=dims.copy(),
        iterations=iterations,
        added_from=_first_use(contributors),
        coverage_initial=initial,
        coverage=current,
    )


def _construct_whole(
    database, source, dims, grid, candidates, rng, config, mirror, class_max_counts
) -> ConstructedObject:
    densities = _Densities(partition_counts(source, dims, grid), class_max_counts)
    initial = current = densities.coverage()
    chunks, contributors, iterations = [source], [], 0
    order = rng.permutation(candidates)[: config.max_iterations] if candidates.size else candidates
    for candidate in order:
        if current >= config.coverage:
            break
        added = np.asarray(database.object_points(int(candidate)))
        added = mirror_points(added) if mirror else added.copy()
        iterations += 1
        densities.counts += partition_counts(added, dims, grid)
        chunks.append(added)
        if len(added):
            contributors.append(np.array([candidate], dtype=np.int64))
        current = densities.coverage()
    points = np.concatenate(chunks) if len(chunks) > 1 else chunks[0]
    extent = 2.0 * np.abs(points[:, :3].astype(np.float64)).max(axis=0, initial=0.0)
    return ConstructedObject(
        points=points,
        dims=np.maximum(dims, extent),
        iterations=iterations,
        added_from=_first_use(contributors),
        coverage_initial=initial,
        coverage=current,
    )


def _inside(points: np.ndarray, dims: np.ndarray, margin: float) -> np.ndarray:
    """``bool (N,)``: canonical points within ``margin`` of the box (closed, float64)."""
    half = dims / 2.0 + margin
    xyz = np.abs(points[:, :3].astype(np.float64))
    return (xyz <= half).all(axis=1)


def _first_use(contributors: list[np.ndarray]) -> np.ndarray:
    if not contributors:
        return np.zeros(0, dtype=np.int64)
    rows = np.concatenate(contributors).astype(np.int64)
    _, first = np.unique(rows, return_index=True)
    return rows[np.sort(first)]


def _database_arrays(database) -> tuple[np.ndarray, np.ndarray]:
    """Plain ndarray views (no copy) of the database's points and offsets, for numba."""
    return np.asarray(database.points), np.asarray(database.offsets, dtype=np.int64)


@numba.njit(cache=True, nogil=True)
def _gather_partition_points(points, offsets, rows, cells, dims, grid, mirror, margin):
    """Points of candidate ``rows[j]`` that fall in cell ``cells[j]`` of the source box.

    Same cell rule and float64 arithmetic as :func:`drcpo.partitions.partition_index`, applied
    to each candidate point and (when ``mirror``) its mirror image; points more than ``margin``
    outside the box are skipped. Returns the gathered rows ``(T, C)`` (mirror images have y
    negated) and the number gathered per pair ``(len(rows),)``.
    """
    copies = 2 if mirror else 1
    total = 0
    for j in range(rows.shape[0]):
        total += offsets[rows[j] + 1] - offsets[rows[j]]
    out = np.empty((total * copies, points.shape[1]), dtype=points.dtype)
    per_pair = np.zeros(rows.shape[0], dtype=np.int64)
    nx, ny, nz = grid[0], grid[1], grid[2]
    hx, hy, hz = dims[0] / 2.0 + margin, dims[1] / 2.0 + margin, dims[2] / 2.0 + margin
    k = 0
    for j in range(rows.shape[0]):
        target = cells[j]
        tx = target // (ny * nz)
        ty = (target // nz) % ny
        tz = target % nz
        for i in range(offsets[rows[j]], offsets[rows[j] + 1]):
            x = np.float64(points[i, 0])
            z = np.float64(points[i, 2])
            if abs(x) > hx or abs(z) > hz:
                continue
            if _cell(x, dims[0], nx) != tx or _cell(z, dims[2], nz) != tz:
                continue
            for c in range(copies):
                y = np.float64(points[i, 1]) if c == 0 else -np.float64(points[i, 1])
                if abs(y) > hy or _cell(y, dims[1], ny) != ty:
                    continue
                out[k, :] = points[i, :]
                if c == 1:
                    out[k, 1] = -points[i, 1]
                k += 1
                per_pair[j] += 1
    return out[:k], per_pair


@numba.njit(cache=True, nogil=True, inline="always")
def _cell(value, size, count):
    cell = np.int64(np.floor((value + size / 2.0) / size * count))
    if cell < 0:
        return np.int64(0)
    if cell > count - 1:
        return np.int64(count - 1)
    return cell
