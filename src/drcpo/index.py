"""Candidate index (DR.CPO pre-processing): for every object, the K best objects to fill it.

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

On disk (``DB/index/``, written atomically)::

    candidates.npy   int32   (N, K)      database rows, best first; -1 pads
    densities.npy    float32 (N, P_max)  partition densities; 0 pads and non-indexed classes
    manifest.json    format, version, parameters, database checksum, per-class grids/maxima/stats
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numba as nb
import numpy as np

from drcpo.config_fields import Checked, spec, to_dict
from drcpo.database import GroundTruthDatabase, read_manifest
from drcpo.errors import ConfigError, DataError
from drcpo.outputs import OutputKind, save_array, write_directory
from drcpo.partitions import DEFAULT_MIRRORED, Grid, flat_cell, grid_for, num_partitions
from drcpo.similarity import SimilaritySearch

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "INDEX_DIRNAME",
    "INDEX_OUTPUT",
    "MAX_K",
    "CandidateIndex",
    "IndexConfig",
    "MapBlocks",
    "build_index",
    "indexed_mask",
    "load_index",
    "normalise_counts",
    "partition_occupancy",
    "rank_candidates",
]


FORMAT_NAME = "drcpo-candidate-index"
FORMAT_VERSION = 1
INDEX_DIRNAME = "index"
INDEX_OUTPUT = OutputKind(
    "drcpo candidate index", "manifest.json", FORMAT_NAME, ("candidates.npy", "densities.npy")
)

#: ``progress(class_name, objects_done, objects_total)``, called from the calling thread.
Progress = Callable[[str, int, int], None]

#: Largest K: far beyond the paper's 400; above it the N x K candidate table alone is out of
#: reach for any real database (checked against the memory before it is allocated).
MAX_K = 100_000
_CHUNK_POINTS = 1 << 20  # points per chunk when counting partition occupancy


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class IndexConfig(Checked):
    """Parameters of the candidate index (paper defaults): the config section ``index``, whose
    keys are the first seven fields.

    Attributes:
        k: candidates kept per object (the first stage keeps ``2 k``).
        alpha: a partition is low-density below ``alpha`` x the mean non-empty density.
        min_points: objects with fewer points are neither indexed nor candidates.
        exclude_difficulty: difficulty codes never indexed (e.g. ``[-1]`` for unknown).
        classes: classes to index (``None``: every class in the database).
        approximate_above: classes with more indexed objects use the approximate first stage
            (``None``: always exact).
        approx_factor: the approximate mode re-ranks ``approx_factor x 2k`` nearest neighbours.

    Not config keys:
        grids: partition grid overrides ``{class: [nx, ny, nz]}`` (key ``"default"`` for
            classes without their own grid); see :data:`drcpo.partitions.DEFAULT_GRIDS`.
        mirror: classes whose points are mirrored across the x axis before counting.
            In a loaded configuration both are ``drcpo.construction``'s, so the index
            partitions every class as construction does.
        block_size: objects per work item.
    """

    KEY_PATH = "index"

    k: int = field(
        default=400, metadata=spec("int", "candidates kept per object", low=1, high=MAX_K)
    )
    alpha: float = field(
        default=0.8,
        metadata=spec(
            "float", "low-density partitions: below alpha x the mean", low=0.0, low_open=True
        ),
    )
    min_points: int = field(
        default=5, metadata=spec("int", "objects with fewer points are not indexed", low=0)
    )
    exclude_difficulty: list[int] = field(
        default_factory=list,
        metadata=spec("ints", "difficulty codes never indexed", low=-1, high=2),
    )
    classes: list[str] | None = field(
        default=None,
        metadata=spec("names", "classes to index (null: every class)", classes=True, optional=True),
    )
    approximate_above: int | None = field(
        default=None,
        metadata=spec(
            "int",
            "approximate first stage for classes with more indexed objects (null: never)",
            low=0,
            optional=True,
        ),
    )
    approx_factor: float = field(
        default=1.5,
        metadata=spec("float", "the approximate mode re-ranks this x 2k neighbours", low=1.0),
    )
    grids: dict[str, list[int]] = field(
        default_factory=dict,
        metadata=spec("grids", set_by="drcpo.construction.grids (the index partitions as it)"),
    )
    mirror: list[str] = field(
        default_factory=lambda: list(DEFAULT_MIRRORED),
        metadata=spec("names", set_by="drcpo.construction.mirror (the index mirrors as it)"),
    )
    block_size: int = field(
        default=512, metadata=spec("int", low=1, set_by="the caller (objects per work item)")
    )

    def grid(self, name: str) -> Grid:
        return grid_for(name, self.grids)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able parameters that decide the index (what the manifest stores): the config
        keys, the grids and the mirrored classes."""
        grids = {name: list(grid) for name, grid in self.grids.items()}
        return {**to_dict(self), "grids": grids, "mirror": list(self.mirror)}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> IndexConfig:
        """The inverse of :meth:`to_dict`; also reads the names manifests used before
        (``mirrored``, ``exclude_difficulties``) and ignores their ``workers`` and ``block_size``
        (how it was built, not what)."""
        values = {_OLD_NAMES.get(key, key): value for key, value in values.items()}
        for key in _HOW_BUILT:
            values.pop(key, None)
        known = sorted(f.name for f in fields(cls) if f.name not in _HOW_BUILT)
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ConfigError(f"unknown index parameters {unknown}; known: {known}")
        return cls(**values)


_OLD_NAMES = {"mirrored": "mirror", "exclude_difficulties": "exclude_difficulty"}
_HOW_BUILT = ("workers", "block_size")  # no bearing on the index


# --------------------------------------------------------------------------------------------
# The index
# --------------------------------------------------------------------------------------------
@dataclass
class CandidateIndex:
    """Candidates and partition densities of every object of a database.

    Attributes:
        candidates: ``int32 (N, K)`` database rows, best first, ``-1`` padded.
        densities: ``float32 (N, P_max)`` partition densities, zero padded.
        grids: partition grid of each indexed class.
        max_counts: per indexed class, the largest count of each partition (the normalisers).
        config: the parameters it was built with.
        database_checksum: checksum of the database it was built from.
        classes: per class ``{"objects", "indexed", "mean_candidates", "mode"}``.
    """

    candidates: np.ndarray
    densities: np.ndarray
    grids: dict[str, Grid]
    max_counts: dict[str, np.ndarray]
    config: IndexConfig
    database_checksum: str
    classes: dict[str, dict[str, Any]]

    @property
    def k(self) -> int:
        return int(self.candidates.shape[1])

    def num_partitions(self, name: str) -> int:
        return num_partitions(self.grids[name])

    def candidates_of(self, row: int) -> np.ndarray:
        """Database rows of object ``row``'s candidates, best first (no padding)."""
        line = self.candidates[row]
        return line[line >= 0]

    def densities_of(self, row: int, name: str) -> np.ndarray:
        """Partition densities ``float32 (P,)`` of object ``row`` of class ``name``."""
        return self.densities[row, : self.num_partitions(name)]

    # Persistence --------------------------------------------------------------------------
    def manifest(self) -> dict[str, Any]:
        return {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "database_checksum": self.database_checksum,
            "num_objects": int(self.candidates.shape[0]),
            "k": self.k,
            "p_max": int(self.densities.shape[1]),
            "parameters": self.config.to_dict(),
            "classes": {
                name: {
                    **stats,
                    "grid": list(self.grids[name]),
                    "max_counts": self.max_counts[name].tolist(),
                }
                for name, stats in self.classes.items()
            },
        }

    def checksum(self) -> str:
        """SHA-256 (16 hex digits) of what decides DR.CPO's draws: the manifest (parameters,
        grids, maxima) and both arrays. Saved in the manifest, checked on load, and recorded
        by a resumable augment run, so that a changed index is never mixed in."""
        digest = hashlib.sha256(json.dumps(self.manifest(), sort_keys=True).encode())
        digest.update(np.ascontiguousarray(self.candidates, np.int32).tobytes())
        digest.update(np.ascontiguousarray(self.densities, np.float32).tobytes())
        return digest.hexdigest()[:16]

    def save(self, db_dir: str | os.PathLike, overwrite: bool = False) -> Path:
        """Write ``db_dir/index/`` atomically (temporary directory, then rename).

        ``overwrite`` replaces only a drcpo index (see :mod:`drcpo.outputs`).
        """
        manifest = {**self.manifest(), "checksum": self.checksum()}

        def write(tmp: Path) -> None:
            save_array(tmp / "candidates.npy", np.asarray(self.candidates, np.int32))
            save_array(tmp / "densities.npy", np.asarray(self.densities, np.float32))
            (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")

        return write_directory(Path(db_dir) / INDEX_DIRNAME, write, INDEX_OUTPUT, overwrite)

    @classmethod
    def load(
        cls,
        database: GroundTruthDatabase,
        path: str | os.PathLike | None = None,
        mmap: bool = True,
    ) -> CandidateIndex:
        """Load the index of ``database`` (default ``database.path / "index"``).

        Raises :class:`DataError` when the index is missing, malformed, was built from a
        different database (checksum mismatch), was changed since it was saved (its own
        checksum), or pairs an object with a candidate of another class.
        """
        if path is None:
            if database.path is None:
                raise DataError("an in-memory database has no index directory; pass path=")
            path = Path(database.path) / INDEX_DIRNAME
        path = Path(path)
        manifest = _read_manifest(path)
        expected = database.checksum
        if manifest.get("database_checksum") != expected:
            raise DataError(
                f"{path}: index was built for database checksum "
                f"{manifest.get('database_checksum')!r}, but this database has {expected!r}; "
                "rebuild it with `drcpo index DB --overwrite`"
            )
        candidates = _load_array(path / "candidates.npy", mmap)
        densities = _load_array(path / "densities.npy", mmap)
        n = len(database)
        if candidates.ndim != 2 or candidates.shape[0] != n or candidates.dtype != np.int32:
            raise DataError(
                f"{path / 'candidates.npy'}: expected int32 ({n}, K), "
                f"got {candidates.dtype} {candidates.shape}"
            )
        if densities.ndim != 2 or densities.shape[0] != n or densities.dtype != np.float32:
            raise DataError(
                f"{path / 'densities.npy'}: expected float32 ({n}, P), "
                f"got {densities.dtype} {densities.shape}"
            )
        try:
            config = IndexConfig.from_dict(manifest["parameters"])
            classes = manifest["classes"]
            grids = {name: tuple(int(v) for v in c["grid"]) for name, c in classes.items()}
            max_counts = {
                name: np.asarray(c["max_counts"], np.int64) for name, c in classes.items()
            }
            stats = {
                name: {k: v for k, v in c.items() if k not in ("grid", "max_counts")}
                for name, c in classes.items()
            }
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"{path / 'manifest.json'}: malformed manifest ({exc!r})") from exc
        index = cls(candidates, densities, grids, max_counts, config, expected, stats)
        saved = manifest.get("checksum")  # indexes saved before drcpo recorded one have none
        if saved is not None and index.checksum() != saved:
            raise DataError(
                f"{path}: the index changed since it was saved (checksum {index.checksum()!r}, "
                f"its manifest says {saved!r}); rebuild it with `drcpo index DB --overwrite`"
            )
        _check_candidate_classes(path, database, candidates)
        return index


def load_index(
    database: GroundTruthDatabase, path: str | os.PathLike | None = None, mmap: bool = True
) -> CandidateIndex:
    """Shorthand for :meth:`CandidateIndex.load`."""
    return CandidateIndex.load(database, path, mmap=mmap)


def _check_candidate_classes(path: Path, database: GroundTruthDatabase, table: np.ndarray) -> None:
    """Every candidate a row of its object's class (DR.CPO pastes candidates' points)."""
    names = np.asarray(database.names).astype(str)
    rows, slots = np.nonzero(table >= 0)
    found = table[rows, slots]
    wrong = np.flatnonzero(names[np.minimum(found, len(names) - 1)] != names[rows])
    if len(wrong) or (found >= len(names)).any():
        row, other = (int(rows[wrong[0]]), int(found[wrong[0]])) if len(wrong) else (-1, -1)
        raise DataError(
            f"{path / 'candidates.npy'}: object {row} ({names[row]}) has candidate {other} "
            f"({names[other]}) among {len(wrong)} candidates of another class or out of range"
        )


def _read_manifest(path: Path) -> dict[str, Any]:
    return read_manifest(path, FORMAT_NAME, FORMAT_VERSION, "no candidate index; run `drcpo index`")


def _load_array(path: Path, mmap: bool) -> np.ndarray:
    if not path.is_file():
        raise DataError(f"{path}: missing index file")
    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise DataError(f"{path}: unreadable array ({exc})") from exc
    except MemoryError:  # a header promising more than this machine holds (the file lies)
        raise DataError(
            f"{path}: unreadable array (its header asks for more memory than there is)"
        ) from None


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
