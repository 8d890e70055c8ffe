"""Candidate index (DR.CPO pre-processing): for every object, the K best objects to fill it.

What the index is: its parameters (:class:`IndexConfig`, the config section ``index``), the index
itself (:class:`CandidateIndex`: each object's candidates, best first, and its partition
densities), its on-disk format and its loading, checked against the database it was built from.
How it is built (the two stages that rank the candidates, the partition densities):
:mod:`drcpo.index_build`.

On disk (``DB/index/``, written atomically)::

    candidates.npy   int32   (N, K)      database rows, best first; -1 pads
    densities.npy    float32 (N, P_max)  partition densities; 0 pads and non-indexed classes
    manifest.json    format, version, parameters, database checksum, per-class grids/maxima/stats
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from drcpo.config_fields import Checked, spec, to_dict
from drcpo.database import GroundTruthDatabase, read_manifest
from drcpo.errors import ConfigError, DataError
from drcpo.outputs import OutputKind, save_array, write_directory
from drcpo.partitions import DEFAULT_MIRRORED, Grid, grid_for, num_partitions

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "INDEX_DIRNAME",
    "INDEX_OUTPUT",
    "MAX_K",
    "CandidateIndex",
    "IndexConfig",
    "load_index",
]


FORMAT_NAME = "drcpo-candidate-index"
FORMAT_VERSION = 1
INDEX_DIRNAME = "index"
INDEX_OUTPUT = OutputKind(
    "drcpo candidate index", "manifest.json", FORMAT_NAME, ("candidates.npy", "densities.npy")
)


#: Largest K: far beyond the paper's 400; above it the N x K candidate table alone is out of
#: reach for any real database (checked against the memory before it is allocated).
MAX_K = 100_000


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

    def check_matches(
        self, database: GroundTruthDatabase, construction: Any, classes: Sequence[str]
    ) -> None:
        """ConfigError unless this index covers ``database`` and partitions and mirrors each of
        ``classes`` as ``construction`` (a :class:`~drcpo.construction.ConstructionConfig`)
        does: it does when built from the same config (``drcpo index DB --config``); this
        catches one built from another."""
        if len(self.candidates) != len(database):
            raise ConfigError(
                f"the candidate index covers {len(self.candidates)} objects but the "
                f"database has {len(database)}; rebuild it with `drcpo index`"
            )
        rebuild = (
            f"rebuild the index from this config: `drcpo index {database.path or 'DB'} "
            "--config <your config.yaml> --overwrite`"
        )
        for name in classes:
            if name not in self.grids:
                continue  # no indexed object of this class: it is never sampled
            grid = construction.grid(name)
            if tuple(self.grids[name]) != tuple(grid):
                raise ConfigError(
                    f"drcpo.construction.grids.{name} = {list(grid)} but the candidate index "
                    f"was built with {list(self.grids[name])}; {rebuild}"
                )
            if (name in construction.mirror) != (name in self.config.mirror):
                raise ConfigError(
                    f"drcpo.construction.mirror and the candidate index disagree on whether "
                    f"{name} is mirrored; {rebuild}"
                )

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
