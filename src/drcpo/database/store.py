"""The ground-truth database: every labelled object's points in canonical pose, plus metadata.

On-disk layout (a directory; no pickle anywhere)::

    DB/
      manifest.json        format name and version, build parameters, counts, content checksum,
                           point_features (the names of the point columns after x, y, z)
      points.npy           float32 (P, 3 + C)  all objects' points, concatenated, canonical pose
                           (KITTI: C = 1, intensity; nuScenes: intensity, time_lag)
      offsets.npy          int64   (N + 1,) object i owns points[offsets[i]:offsets[i + 1]]
      boxes.npy            float64 (N, 7)  original LiDAR boxes (OpenPCDet convention)
      names.npy            unicode (N,)    class names
      frame_ids.npy        unicode (N,)    frame each object was cut from
      index_in_frame.npy   int32   (N,)    row of the object in its frame's labels
      num_points.npy       int64   (N,)    points per object
      difficulty.npy       int8    (N,)    0 easy, 1 moderate, 2 hard, -1 unknown (KITTI)
      occlusion.npy        int8    (N,)    KITTI occlusion level (-1 when unknown)
      truncation.npy       float32 (N,)    KITTI truncation (NaN when unknown)
      velocity.npy         float64 (N, 2)  optional: vx, vy (m/s) in the object's canonical
                                           frame, i.e. its LiDAR velocity rotated by -heading

Format version 2 adds ``point_features`` and ``velocity.npy``; version 1 (no velocities, the
feature names unrecorded: ``intensity``, then ``feature_<column>``) still opens, and a
database without velocities has the checksum it had as version 1 (the checksum covers
``velocity.npy`` only when it exists).

``points.npy`` and ``offsets.npy`` are memory-mapped, so reading one object's points costs O(1)
and opens no per-object file. Databases are written through :func:`drcpo.outputs.write_directory`
(a temporary sibling directory renamed into place at the end), so an interrupted build never
leaves a database that loads.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drcpo.errors import DataError
from drcpo.frame import rotate_velocities
from drcpo.outputs import OutputKind, save_array, write_directory

__all__ = [
    "DATABASE_OUTPUT",
    "DIFFICULTY_NAMES",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "READ_VERSIONS",
    "GroundTruthDatabase",
    "ObjectRecord",
    "default_point_features",
    "difficulty_name",
    "read_manifest",
]

FORMAT_NAME = "drcpo-gt-database"
FORMAT_VERSION = 2
READ_VERSIONS = (1, 2)  # version 1: no point_features, no velocity.npy
DIFFICULTY_NAMES = ("easy", "moderate", "hard")  # codes 0, 1, 2; -1 is "unknown"
DATABASE_OUTPUT = OutputKind(
    "drcpo database",
    "manifest.json",
    FORMAT_NAME,
    ("*.npy", "index"),  # index: `drcpo index`
)

_COLUMNS: dict[str, Any] = {
    "boxes": np.float64,
    "names": str,
    "frame_ids": str,
    "index_in_frame": np.int32,
    "num_points": np.int64,
    "difficulty": np.int8,
    "occlusion": np.int8,
    "truncation": np.float32,
}
#: Columns a database may lack (version 1 never has them), hashed after the others.
_OPTIONAL: dict[str, Any] = {"velocity": np.float64}
_CHECKSUM_ORDER = ("points", "offsets", *_COLUMNS, *_OPTIONAL)
_FINITE = ("points", "boxes", "velocity")  # all values finite (truncation may be NaN)
_CHUNK_ROWS = 1 << 18  # rows hashed at a time (4 MiB of points): cache-sized, few calls


def default_point_features(point_dim: int) -> tuple[str, ...]:
    """Names of the point columns after x, y, z when a database does not record them (format
    version 1, KITTI): ``intensity``, then ``feature_<column>``."""
    return tuple("intensity" if c == 3 else f"feature_{c}" for c in range(3, point_dim))


def difficulty_name(code: int) -> str:
    """``"easy"``, ``"moderate"``, ``"hard"`` or ``"unknown"`` for a difficulty code."""
    return DIFFICULTY_NAMES[code] if 0 <= code < len(DIFFICULTY_NAMES) else "unknown"


@dataclass(frozen=True)
class ObjectRecord:
    """One object to store: canonical points ``float32 (n, 3 + C)`` and its metadata.

    ``velocity``: ``(2,)`` vx, vy (m/s) in the object's canonical frame (its LiDAR velocity
    rotated by ``-box[6]``), or ``None`` when the source has none.
    """

    points: np.ndarray
    name: str
    box: np.ndarray
    frame_id: str = ""
    index_in_frame: int = -1
    difficulty: int = -1
    occlusion: int = -1
    truncation: float = float("nan")
    velocity: np.ndarray | None = None


class GroundTruthDatabase:
    """Objects' canonical points and metadata, memory-mapped from a directory or held in memory.

    Use :meth:`open` for a database on disk and :meth:`from_records` / :meth:`from_arrays` for
    one in memory (tests, synthetic data); :meth:`save` writes either kind.
    """

    def __init__(
        self,
        points: np.ndarray,
        offsets: np.ndarray,
        columns: dict[str, np.ndarray],
        manifest: dict[str, Any] | None = None,
        path: Path | None = None,
    ) -> None:
        self._points = points
        self._offsets = offsets
        self._columns = columns
        self.path = path
        self.manifest = manifest if manifest is not None else {}
        self._verified = False
        _check_consistent(points, offsets, columns, where=str(path or "<memory>"))

    # Construction -------------------------------------------------------------------------
    @classmethod
    def open(cls, path: str | os.PathLike, verify: bool = True) -> GroundTruthDatabase:
        """Open a database directory; raises :class:`DataError` naming what is wrong.

        Args:
            path: the database directory.
            verify: run :meth:`verify` (every array's bytes against the manifest checksum, no
                NaN/inf in points or boxes): one streaming pass over the files, about as long
                as reading them. ``False`` for huge databases verified once already; building
                an index verifies them all the same (:meth:`verified_checksum`).
        """
        path = Path(path)
        manifest = read_manifest(path, FORMAT_NAME, READ_VERSIONS, "not a drcpo database")
        points = _load(path / "points.npy", mmap=True)
        offsets = _load(path / "offsets.npy", mmap=True)
        columns = {name: _load(path / f"{name}.npy") for name in _COLUMNS}
        if manifest["format_version"] >= 2 and manifest.get("velocity"):
            columns["velocity"] = _load(path / "velocity.npy")
        _check_text_columns(path, columns)
        _check_features(path, manifest, points)
        database = cls(points, offsets, columns, manifest=manifest, path=path)
        if verify:
            database.verify()
        return database

    @classmethod
    def from_records(
        cls,
        records: Iterable[ObjectRecord],
        point_dim: int = 4,
        point_features: Sequence[str] | None = None,
    ) -> GroundTruthDatabase:
        """An in-memory database from :class:`ObjectRecord` objects (in order).

        ``point_features``: names of the ``point_dim - 3`` columns after x, y, z (default:
        :func:`default_point_features`). Velocities are stored when any record has one (the
        others get 0).
        """
        records = list(records)
        chunks = [np.asarray(r.points, dtype=np.float32).reshape(-1, point_dim) for r in records]
        sizes = np.array([len(c) for c in chunks], dtype=np.int64)
        points = np.concatenate(chunks) if chunks else np.zeros((0, point_dim), np.float32)
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        columns = {
            "boxes": np.array([r.box for r in records], dtype=np.float64).reshape(-1, 7),
            "names": np.array([r.name for r in records], dtype=str),
            "frame_ids": np.array([r.frame_id for r in records], dtype=str),
            "index_in_frame": np.array([r.index_in_frame for r in records], dtype=np.int32),
            "num_points": sizes,
            "difficulty": np.array([r.difficulty for r in records], dtype=np.int8),
            "occlusion": np.array([r.occlusion for r in records], dtype=np.int8),
            "truncation": np.array([r.truncation for r in records], dtype=np.float32),
        }
        if any(r.velocity is not None for r in records):
            columns["velocity"] = np.array(
                [np.zeros(2) if r.velocity is None else r.velocity for r in records],
                dtype=np.float64,
            ).reshape(-1, 2)
        return cls(points, offsets, columns, manifest=_features_manifest(point_dim, point_features))

    @classmethod
    def from_arrays(
        cls,
        points: np.ndarray,
        offsets: np.ndarray,
        names: Sequence[str] | np.ndarray,
        boxes: np.ndarray,
        **columns: np.ndarray,
    ) -> GroundTruthDatabase:
        """An in-memory database from concatenated points, offsets and per-object columns.

        Columns not given get "unknown" values (frame id "", index -1, difficulty -1, ...);
        ``velocity`` (``(N, 2)``, canonical frame) is left out unless given.
        """
        offsets = np.asarray(offsets, dtype=np.int64)
        n = len(offsets) - 1
        full = {
            "boxes": np.asarray(boxes, dtype=np.float64).reshape(-1, 7),
            "names": np.asarray(names, dtype=str),
            "frame_ids": np.full(n, "", dtype=str),
            "index_in_frame": np.full(n, -1, dtype=np.int32),
            "num_points": np.diff(offsets),
            "difficulty": np.full(n, -1, dtype=np.int8),
            "occlusion": np.full(n, -1, dtype=np.int8),
            "truncation": np.full(n, np.nan, dtype=np.float32),
        }
        kinds = {**_COLUMNS, **_OPTIONAL}
        unknown = set(columns) - set(kinds)
        if unknown:
            raise ValueError(f"unknown database columns: {sorted(unknown)}")
        for name, values in columns.items():
            full[name] = np.asarray(values).astype(kinds[name], copy=False)
        points = np.asarray(points, dtype=np.float32)
        return cls(
            points,
            offsets,
            full,
            manifest=_features_manifest(points.shape[1] if points.ndim == 2 else 4),
        )

    # Access -------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._offsets) - 1

    def __repr__(self) -> str:
        where = self.path or "memory"
        return f"GroundTruthDatabase({len(self)} objects, {len(self._points)} points, {where})"

    @property
    def points(self) -> np.ndarray:
        """All objects' canonical points, concatenated: ``float32 (P, 3 + C)``
        (memory-mapped)."""
        return self._points

    @property
    def point_features(self) -> tuple[str, ...]:
        """Names of the point columns after x, y, z (e.g. ``("intensity",)``)."""
        names = self.manifest.get("point_features")
        if names is None:
            return default_point_features(self._points.shape[1])
        return tuple(str(n) for n in names)

    @property
    def velocity(self) -> np.ndarray | None:
        """``float64 (N, 2)`` vx, vy (m/s) of the objects in their canonical frames (the LiDAR
        velocity rotated by the box's -heading), or ``None`` when the database has none."""
        return self._columns.get("velocity")

    def velocities(self, rows: np.ndarray, headings: np.ndarray) -> np.ndarray | None:
        """LiDAR velocities ``float64 (S, 2)`` of objects ``rows`` placed at ``headings``
        ``(S,)`` (radians): their canonical velocities turned by the headings; ``None``
        when the database has none."""
        if self.velocity is None:
            return None
        rows = np.asarray(rows, dtype=np.int64)
        return rotate_velocities(self.velocity[rows], np.asarray(headings, dtype=np.float64))

    @property
    def offsets(self) -> np.ndarray:
        """``int64 (N + 1,)``: object i owns ``points[offsets[i]:offsets[i + 1]]``."""
        return self._offsets

    @property
    def names(self) -> np.ndarray:
        return self._columns["names"]

    @property
    def boxes(self) -> np.ndarray:
        """Original LiDAR boxes ``float64 (N, 7)`` of the objects."""
        return self._columns["boxes"]

    @property
    def num_points(self) -> np.ndarray:
        return self._columns["num_points"]

    @property
    def frame_ids(self) -> np.ndarray:
        return self._columns["frame_ids"]

    @property
    def index_in_frame(self) -> np.ndarray:
        return self._columns["index_in_frame"]

    @property
    def difficulty(self) -> np.ndarray:
        return self._columns["difficulty"]

    @property
    def occlusion(self) -> np.ndarray:
        return self._columns["occlusion"]

    @property
    def truncation(self) -> np.ndarray:
        return self._columns["truncation"]

    @property
    def classes(self) -> list[str]:
        """Class names present, sorted."""
        return sorted(set(self.names.tolist()))

    @property
    def checksum(self) -> str:
        """Content checksum (from the manifest when opened from disk, else computed)."""
        return self.manifest.get("checksum") or self.compute_checksum()

    def rows_of_class(self, name: str) -> np.ndarray:
        """Database rows ``int64`` of the objects of class ``name``, ascending."""
        return np.flatnonzero(self.names == name)

    def object_points(self, i: int) -> np.ndarray:
        """Points ``float32 (n, 3 + C)`` of object ``i`` in canonical pose (a read-only
        view)."""
        if not -len(self) <= i < len(self):
            raise IndexError(f"object {i} out of range for a database of {len(self)} objects")
        i = int(i) % len(self)
        return self._points[self._offsets[i] : self._offsets[i + 1]]

    def summary(self) -> dict[str, dict[str, int]]:
        """``{class: {"objects": n, "points": m}}`` sorted by class name."""
        out: dict[str, dict[str, int]] = {}
        for name in self.classes:
            rows = self.rows_of_class(name)
            out[name] = {"objects": len(rows), "points": int(self.num_points[rows].sum())}
        return out

    def compute_checksum(self) -> str:
        """SHA-256 over every array's bytes, in a fixed order (``"sha256:<hex>"``)."""
        return self._scan(check_values=False)

    def _scan(self, check_values: bool) -> str:
        """The content checksum, streamed over the arrays in chunks (memory-mapped ones are
        read once, never copied whole); with ``check_values``, raise :class:`DataError` on
        the first non-finite point or box value, in the same pass."""
        digest = hashlib.sha256()
        arrays = {"points": self._points, "offsets": self._offsets, **self._columns}
        for name in _CHECKSUM_ORDER:
            if name not in arrays:  # an optional column this database lacks
                continue
            array = arrays[name]
            digest.update(f"{name}:{array.dtype.str}:{array.shape}".encode())
            for start in range(0, len(array), _CHUNK_ROWS):
                chunk = np.ascontiguousarray(array[start : start + _CHUNK_ROWS])
                digest.update(chunk.reshape(-1).view(np.uint8))
                if check_values and name in _FINITE and not np.isfinite(chunk).all():
                    self._non_finite(name, chunk, start)
        return "sha256:" + digest.hexdigest()

    def _non_finite(self, name: str, chunk: np.ndarray, start: int) -> None:
        row = start + int(np.flatnonzero(~np.isfinite(chunk.reshape(len(chunk), -1)).all(1))[0])
        per_object = name != "points"
        obj = row if per_object else int(np.searchsorted(self._offsets, row, "right") - 1)
        where = f"{self.path / f'{name}.npy'}" if self.path else f"<memory> {name}"
        raise DataError(
            f"{where}: row {row} (object {obj}, {self.names[obj]!s}) of database "
            f"{self.path or '<memory>'} holds a NaN or infinite value: "
            f"{np.asarray(chunk[row - start]).tolist()}"
        )

    def verify(self) -> None:
        """Check the data: recompute the checksum and compare it with the manifest's, and look
        for NaN/inf in points and boxes (one pass). Raises :class:`DataError` naming the
        database (and, for a bad value, the file and row)."""
        actual = self._scan(check_values=True)
        stored = self.manifest.get("checksum")
        if stored and stored != actual:
            raise DataError(
                f"database {self.path}: its files ({', '.join(self._files())}) do not match the "
                f"checksum in {self.path / 'manifest.json'} ({stored}, data gives {actual}): "
                "the database was modified or is corrupt; rebuild it"
            )
        self._verified = True

    def _files(self) -> list[str]:
        names = ("points", "offsets", *self._columns)
        return [f"{name}.npy" for name in _CHECKSUM_ORDER if name in names]

    @property
    def verified(self) -> bool:
        """Whether :meth:`verify` has passed on this object."""
        return self._verified

    def verified_checksum(self) -> str:
        """The content checksum, known to match the data: the manifest's once :meth:`verify`
        passed (on :meth:`open`, or here first), else (in memory) computed. What an index is
        built against, so that it never vouches for a database whose data changed."""
        if not self.manifest.get("checksum"):
            return self.compute_checksum()
        if not self._verified:
            self.verify()
        return self.manifest["checksum"]

    # Writing ------------------------------------------------------------------------------
    def save(
        self,
        path: str | os.PathLike,
        parameters: dict[str, Any] | None = None,
        overwrite: bool = False,
    ) -> Path:
        """Write the database to ``path`` atomically (temporary directory, then rename).

        ``overwrite`` replaces only a drcpo database (see :mod:`drcpo.outputs`); raises
        :class:`~drcpo.errors.OutputError` when ``path`` cannot be written.
        """
        arrays = {"points": self._points, "offsets": self._offsets, **self._columns}
        manifest = {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "parameters": parameters
            if parameters is not None
            else self.manifest.get("parameters", {}),
            "num_objects": len(self),
            "num_points": len(self._points),
            "point_dim": int(self._points.shape[1]),
            "point_features": list(self.point_features),
            "velocity": self.velocity is not None,
            "classes": self.summary(),
            "checksum": self.compute_checksum(),
        }

        def write(tmp: Path) -> None:
            for name, array in arrays.items():
                save_array(tmp / f"{name}.npy", array)
            (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")

        return write_directory(path, write, DATABASE_OUTPUT, overwrite=overwrite)


def read_manifest(
    path: Path, format_name: str, format_version: int | Sequence[int], missing: str
) -> dict:
    """Read ``path/manifest.json`` and check its format name and version (one, or the
    versions this drcpo reads).

    Raises :class:`DataError` naming the file; ``missing`` says what a directory without a
    manifest is not (e.g. "not a drcpo database").
    """
    manifest_path = path / "manifest.json"
    if not manifest_path.is_file():
        raise DataError(f"{path}: {missing} (no manifest.json)")
    try:
        manifest = json.loads(manifest_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"{manifest_path}: unreadable manifest ({exc})") from exc
    except RecursionError:
        raise DataError(f"{manifest_path}: unreadable manifest (nested too deeply)") from None
    except OSError as exc:
        raise DataError(f"{manifest_path}: cannot read the manifest ({exc.strerror})") from exc
    if not isinstance(manifest, dict) or manifest.get("format") != format_name:
        found = manifest.get("format") if isinstance(manifest, dict) else manifest
        raise DataError(f"{manifest_path}: format is {found!r}, expected {format_name!r}")
    versions = (format_version,) if isinstance(format_version, int) else tuple(format_version)
    found = manifest.get("format_version")
    if isinstance(found, bool) or found not in versions:
        readable = " or ".join(str(v) for v in versions)
        raise DataError(
            f"{manifest_path}: format_version {found} is not supported (this drcpo reads "
            f"{readable})"
        )
    return manifest


def _load(path: Path, mmap: bool = False) -> np.ndarray:
    if not path.is_file():
        raise DataError(f"{path}: missing database file")
    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise DataError(f"{path}: unreadable array ({exc})") from exc
    except MemoryError:  # a header promising more than this machine holds (the file lies)
        raise DataError(
            f"{path}: unreadable array (its header asks for more memory than there is)"
        ) from None


def _check_text_columns(path: Path, columns: dict[str, np.ndarray]) -> None:
    """Class names and frame ids are unicode arrays (another tool may store integer ids)."""
    for name, kind in _COLUMNS.items():
        if kind is str and columns[name].dtype.kind != "U":
            raise DataError(
                f"{path / f'{name}.npy'}: {name} must be strings, got {columns[name].dtype} "
                "(a drcpo database stores names as text, e.g. 'Car')"
            )


def _features_manifest(point_dim: int, names: Sequence[str] | None = None) -> dict[str, Any]:
    """The in-memory manifest that records the feature names of ``point_dim`` columns."""
    if point_dim < 3:
        return {}  # not points at all: the consistency check names the shape
    names = default_point_features(point_dim) if names is None else tuple(map(str, names))
    if len(names) != point_dim - 3:
        raise DataError(
            f"point_features {list(names)} name {len(names)} columns, the points have "
            f"{point_dim - 3} after x, y, z"
        )
    return {"point_features": list(names)}


def _check_features(path: Path, manifest: dict, points: np.ndarray) -> None:
    """A version-2 manifest's ``point_features`` name each point column after x, y, z."""
    names = manifest.get("point_features")
    if names is None and manifest["format_version"] < 2:
        return
    dim = points.shape[1] if points.ndim == 2 else 0
    if (
        not isinstance(names, list)
        or not all(isinstance(n, str) for n in names)
        or len(names) != dim - 3
    ):
        raise DataError(
            f"{path / 'manifest.json'}: point_features = {names!r} must list the names of "
            f"the {dim - 3} point columns after x, y, z of {path / 'points.npy'}"
        )


def _check_consistent(
    points: np.ndarray, offsets: np.ndarray, columns: dict[str, np.ndarray], where: str
) -> None:
    if points.ndim != 2 or points.shape[1] < 3:
        raise DataError(f"{where}: points must be (P, 3 + C), got {points.shape}")
    if offsets.ndim != 1 or len(offsets) < 1 or offsets[0] != 0 or offsets[-1] != len(points):
        raise DataError(f"{where}: offsets do not cover the {len(points)} points")
    if len(offsets) > 1 and (np.diff(offsets) < 0).any():
        raise DataError(f"{where}: offsets are not non-decreasing")
    n = len(offsets) - 1
    for name, array in columns.items():
        if len(array) != n:
            raise DataError(f"{where}: column {name!r} has {len(array)} rows, expected {n}")
    if columns["boxes"].shape != (n, 7):
        raise DataError(f"{where}: boxes must be ({n}, 7), got {columns['boxes'].shape}")
    velocity = columns.get("velocity")
    if velocity is not None and velocity.shape != (n, 2):
        raise DataError(f"{where}: velocity must be ({n}, 2), got {velocity.shape}")
    if not np.array_equal(columns["num_points"], np.diff(offsets)):
        raise DataError(f"{where}: num_points disagrees with offsets")
