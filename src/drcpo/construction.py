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
(:mod:`drcpo.construction_kernels`) that reads the candidates' points straight from the
(memory-mapped) database and draws from the ``Generator`` exactly as the plain numpy
formulation does (``rng.integers(0, K, size)`` per iteration): same points in the same order,
same thresholds (the mean summed in partition order), same rng state afterwards.
``tests/test_construction.py`` keeps that formulation as the reference.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from drcpo.config_fields import Checked, spec
from drcpo.construction_kernels import _construct_partition, _Limits, _Sources, _Stored
from drcpo.errors import DataError
from drcpo.partitions import DEFAULT_MIRRORED, Grid, grid_for

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


def _stored(database) -> _Stored:
    return _Stored(np.asarray(database.points), np.asarray(database.offsets, dtype=np.int64))
