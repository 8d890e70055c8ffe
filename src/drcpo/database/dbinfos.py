"""Importing OpenPCDet's and MMDetection3D's databases (``*_dbinfos_*.pkl``, ``gt_database/``).

The infos pickle is read through :mod:`~drcpo.database.safe_pickle` (no code in it is run) and
every field of every object is checked (:func:`validate_dbinfos`) before any point is read; each
object's points (stored minus its box centre, or MMDetection3D's bottom centre) are turned into
canonical pose, as are the velocities of 9-value boxes. The result is the database that
:mod:`~drcpo.database.build` cuts out of the same frames.
"""

from __future__ import annotations

import os
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from drcpo.database import safe_pickle
from drcpo.database.build import Progress
from drcpo.database.store import DATABASE_OUTPUT, GroundTruthDatabase, ObjectRecord
from drcpo.datasets.kitti import FRAME_ID, KittiLabels, read_labels, read_points
from drcpo.errors import ConfigError, DataError, shown
from drcpo.frame import MAX_COORDINATE, rotate_velocities
from drcpo.geometry import rotate_points_z
from drcpo.outputs import check_output

__all__ = ["IMPORT_MARGIN", "import_mmdet3d", "import_openpcdet", "validate_dbinfos"]

_DBINFO_KEYS = ("name", "path", "image_idx", "gt_idx", "box3d_lidar", "num_points_in_gt")


def import_openpcdet(
    dbinfos_pkl: str | os.PathLike,
    out: str | os.PathLike,
    root: str | os.PathLike | None = None,
    overwrite: bool = False,
    num_features: int = 4,
    progress: Progress | None = None,
    origin: str = "centre",
) -> GroundTruthDatabase:
    """Convert an OpenPCDet database (``*_dbinfos_*.pkl`` + ``gt_database/*.bin``) to ours.

    Args:
        dbinfos_pkl: OpenPCDet's ``kitti_dbinfos_<split>.pkl``, read through
            :mod:`drcpo.database.safe_pickle` (only numpy arrays/scalars/dtypes and builtins).
        out: database directory to create (atomically).
        root: data root the ``path`` entries are relative to; default: the pickle's directory.
        overwrite: replace an existing ``out``.
        num_features: float32 values per point in the ``.bin`` files.
        progress: optional ``progress(objects_done, objects_total)`` callback.
        origin: where the infos' ``box3d_lidar`` z and the stored points refer to: ``"centre"``
            (OpenPCDet) or ``"bottom"`` (MMDetection3D: z is the bottom centre's and the points
            are relative to it; see :func:`import_mmdet3d`).

    OpenPCDet stores each object's points minus the box centre; they are rotated by the box's
    -heading into canonical pose, as are the velocities of 9-value boxes (nuScenes' dbinfos).
    Objects are ordered by frame id, then index in frame, as a build from the same frames orders
    them. Occlusion and truncation, which the infos lack, are read from
    ``root/training/label_2`` when those label files exist (else left unknown).

    Every field of every object is checked (see :func:`validate_dbinfos`) before any point is
    read; a ``path`` outside ``root`` and a ``gt_idx`` past the frame's labels are refused.
    """
    dbinfos_pkl = Path(dbinfos_pkl)
    out = Path(out)
    root = Path(root) if root is not None else dbinfos_pkl.parent
    if origin not in _ORIGINS:
        raise ConfigError(f"origin must be one of {', '.join(_ORIGINS)}, got {origin!r}")
    if not dbinfos_pkl.is_file():  # the missing input is the news, not where the output goes
        raise DataError(f"{dbinfos_pkl}: cannot read (no such file)")
    check_output(out, DATABASE_OUTPUT, overwrite, inputs=[dbinfos_pkl, root])
    entries = sorted(
        _dbinfo_entries(dbinfos_pkl, origin), key=lambda e: (e["image_idx"], e["gt_idx"])
    )
    if not entries:
        raise DataError(f"{dbinfos_pkl}: holds no objects")
    labels = _LabelLookup(root / "training" / "label_2")
    records = []
    for done, entry in enumerate(entries, start=1):
        records.append(_imported_record(entry, root, num_features, labels, origin))
        if progress is not None:
            progress(done, len(entries))
    parameters = {
        "source": _ORIGINS[origin],
        "dbinfos": str(dbinfos_pkl.resolve()),
        "root": str(root.resolve()),
        "classes": sorted({entry["name"] for entry in entries}),
        "labels_read": labels.used,
    }
    database = GroundTruthDatabase.from_records(records, point_dim=num_features)
    database.save(out, parameters=parameters, overwrite=overwrite)
    return GroundTruthDatabase.open(out)


def import_mmdet3d(
    dbinfos_pkl: str | os.PathLike,
    out: str | os.PathLike,
    root: str | os.PathLike | None = None,
    overwrite: bool = False,
    num_features: int = 4,
    progress: Progress | None = None,
) -> GroundTruthDatabase:
    """Convert an MMDetection3D database (``kitti_dbinfos_train.pkl`` +
    ``kitti_gt_database/*.bin``, from its ``create_data.py``) to ours.

    The same layout as OpenPCDet's (:func:`import_openpcdet`, same arguments and checks) but for
    the origin: MMDetection3D's ``box3d_lidar`` has z at the box's bottom centre and each object's
    points are stored minus that bottom centre; both are moved to the centre. Integer
    ``image_idx`` (its KITTI sample index) become KITTI's six-digit frame ids.
    """
    return import_openpcdet(
        dbinfos_pkl, out, root, overwrite, num_features, progress, origin="bottom"
    )


#: ``origin`` of :func:`import_openpcdet` -> the database's ``source`` parameter.
_ORIGINS = {"centre": "openpcdet", "bottom": "mmdet3d"}


def _dbinfo_entries(path: Path, origin: str = "centre") -> list[dict[str, Any]]:
    """The validated objects, boxes with z at the centre whatever ``origin`` the file uses."""
    infos = safe_pickle.load(path)
    if origin == "bottom":
        _kitti_frame_ids(infos)
    entries = validate_dbinfos(infos, str(path))
    if origin == "bottom":
        for entry in entries:
            entry["box"][2] += entry["box"][5] / 2.0
    return entries


def _kitti_frame_ids(infos: Any) -> None:
    """MMDetection3D's integer ``image_idx`` as KITTI's six-digit frame ids, in place (anything
    else is left for :func:`validate_dbinfos` to judge)."""
    for objects in infos.values() if isinstance(infos, dict) else ():
        for info in objects if isinstance(objects, list) else ():
            if (
                isinstance(info, dict)
                and _integer(info.get("image_idx"), 0, _MAX_INT32) is not None
            ):
                info["image_idx"] = f"{int(info['image_idx']):06d}"


def validate_dbinfos(infos: Any, source: str) -> list[dict[str, Any]]:
    """The objects of an OpenPCDet dbinfos dict, every field checked, as plain values.

    Args:
        infos: what the pickle holds: class name -> list of per-object dicts with ``name``,
            ``path``, ``image_idx``, ``gt_idx``, ``box3d_lidar``, ``num_points_in_gt`` and,
            optionally, ``difficulty``, ``bbox`` and ``score``.
        source: the file, for messages.

    Returns one dict per object with ``name``, ``path``, ``image_idx`` (str), ``gt_idx``,
    ``num_points``, ``difficulty`` (int), ``box`` (``float64 (7,)``: centre, sizes, heading)
    and ``velocity`` (``float64 (2,)``: values 8 and 9 of a nuScenes-style 9-value box, in the
    LiDAR frame; ``None`` for 7 or 8 values). Raises :class:`DataError` naming ``source``, the
    record (``Car[3]``) and the field for a wrong type, shape or value, a ``path`` that leaves
    the data root (absolute or through ``..``) and an object listed twice.
    """
    if not isinstance(infos, dict):
        raise DataError(f"{source}: expected a dict of class name -> list of objects")
    entries: list[dict[str, Any]] = []
    seen: dict[tuple[str, int], str] = {}
    for class_name, objects in infos.items():
        if not isinstance(class_name, str):
            raise DataError(f"{source}: class name {shown(class_name, 200)} is not a str")
        class_name = str(class_name)  # OpenPCDet's keys are numpy str_ scalars
        if not isinstance(objects, list):
            kind = type(objects).__name__
            raise DataError(f"{source}: class {class_name!r} holds a {kind}, not a list")
        for position, info in enumerate(objects):
            where = f"{source}: {class_name}[{position}]"
            entry = _dbinfo_entry(info, where)
            if entry["name"] != class_name:
                raise DataError(f"{where}: name {entry['name']!r} is not its class {class_name!r}")
            key = (entry["image_idx"], entry["gt_idx"])
            if key in seen:
                raise DataError(
                    f"{where}: object {entry['gt_idx']} of frame {entry['image_idx']} is "
                    f"already listed as {seen[key]}"
                )
            seen[key] = f"{class_name}[{position}]"
            entries.append(entry)
    return entries


_MAX_INT32 = 2**31 - 1


def _dbinfo_entry(info: Any, where: str) -> dict[str, Any]:
    if not isinstance(info, dict):
        raise DataError(f"{where}: expected a dict of fields, got {type(info).__name__}")
    missing = [key for key in _DBINFO_KEYS if key not in info]
    if missing:
        raise DataError(f"{where}: missing key(s) {', '.join(missing)}")

    def bad(key: str, expected: str) -> DataError:
        return DataError(f"{where}: field {key!r} = {shown(info[key], 200)} is not {expected}")

    name, path, frame_id = (_text(info[key]) for key in ("name", "path", "image_idx"))
    if not name:
        raise bad("name", "a class name (non-empty str)")
    if not path or "\0" in path:
        raise bad("path", "a file path (non-empty str)")
    relative = PurePosixPath(path)
    if relative.is_absolute() or ".." in relative.parts:
        raise bad("path", "a path inside the data root (absolute and '..' paths are refused)")
    if frame_id is None or not FRAME_ID.fullmatch(frame_id):
        raise bad("image_idx", "a frame id (str of letters, digits, '_', '-', '.')")
    gt_idx = _integer(info["gt_idx"], 0, _MAX_INT32)
    if gt_idx is None:
        raise bad("gt_idx", f"an int in [0, {_MAX_INT32}]")
    num_points = _integer(info["num_points_in_gt"], 0, _MAX_INT32)
    if num_points is None:
        raise bad("num_points_in_gt", f"an int in [0, {_MAX_INT32}]")
    difficulty = _integer(info.get("difficulty", -1), -1, 2)
    if difficulty is None:
        raise bad("difficulty", "an int in [-1, 2] (-1: unknown)")
    box = _reals(info["box3d_lidar"])
    if box is None or len(box) < 7 or not np.isfinite(box[:7]).all() or (box[3:6] <= 0).any():
        raise bad("box3d_lidar", "a box of >= 7 finite numbers with positive sizes")
    velocity = box[7:9] if len(box) >= 9 else None  # nuScenes: x, y, z, dx, dy, dz, yaw, vx, vy
    if velocity is not None and not np.isfinite(velocity).all():
        raise bad("box3d_lidar", "a box whose velocities (values 8 and 9) are finite")
    if "bbox" in info and ((bbox := _reals(info["bbox"])) is None or bbox.shape != (4,)):
        raise bad("bbox", "4 numbers")
    if "score" in info and _reals([info["score"]]) is None:
        raise bad("score", "a number")
    return {
        "name": name,
        "path": path,
        "image_idx": frame_id,
        "gt_idx": gt_idx,
        "box": box[:7],
        "velocity": velocity,
        "num_points": num_points,
        "difficulty": difficulty,
    }


def _text(value: Any) -> str | None:
    return str(value) if isinstance(value, str) else None  # np.str_ is a str


def _integer(value: Any, low: int, high: int) -> int | None:
    """``value`` as an int when it is a Python or numpy integer (not a bool) in [low, high]."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        return None
    return int(value) if low <= value <= high else None


def _reals(value: Any) -> np.ndarray | None:
    """``value`` as ``float64 (n,)`` when it is a 1-D list, tuple or array of real numbers."""
    if isinstance(value, np.ndarray):
        return value.astype(np.float64) if value.ndim == 1 and value.dtype.kind in "iuf" else None
    if not isinstance(value, (list, tuple)):
        return None
    numbers = (int, float, np.integer, np.floating)
    if not all(isinstance(v, numbers) and not isinstance(v, (bool, np.bool_)) for v in value):
        return None
    try:
        return np.array([float(v) for v in value], dtype=np.float64)
    except OverflowError:  # an int beyond float range
        return None


class _LabelLookup:
    """KITTI labels by frame id, read once each, when the label directory exists."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.used = directory.is_dir()
        self._cache: dict[str, KittiLabels] = {}

    def get(self, frame_id: str) -> KittiLabels | None:
        path = self.directory / f"{frame_id}.txt"
        if not self.used or not path.is_file():
            return None
        if frame_id not in self._cache:
            self._cache[frame_id] = read_labels(path)
        return self._cache[frame_id]


#: Metres an imported object's points may lie outside its box (both frameworks store the points
#: inside it; a point further out is a corrupt or foreign file, and would be pasted as the object).
IMPORT_MARGIN = 1.0


def _check_points_in_box(path: Path, canonical: np.ndarray, box: np.ndarray) -> None:
    """Refuse an object whose points (relative, canonical pose) leave its box by more than
    :data:`IMPORT_MARGIN`, or would leave the coordinate limit once placed."""
    if not len(canonical):
        return
    xyz = np.asarray(canonical[:, :3], dtype=np.float64)
    reach = np.abs(xyz) - (np.asarray(box[3:6], dtype=np.float64) / 2 + IMPORT_MARGIN)
    far = np.flatnonzero((reach > 0).any(axis=1) | ~np.isfinite(xyz).all(axis=1))
    if len(far):
        raise DataError(
            f"{path}: {len(far)} of its {len(xyz)} points lie more than {IMPORT_MARGIN} m outside "
            f"the object's box (first: {xyz[far[0]].round(3).tolist()} from the centre, box size "
            f"{np.round(box[3:6], 3).tolist()}); the file does not hold this object's points"
        )
    if (np.abs(np.asarray(box[:3]))[None] + np.abs(xyz) > MAX_COORDINATE).any():
        raise DataError(f"{path}: points beyond the coordinate limit of {MAX_COORDINATE:g} m")


def _imported_record(
    entry: dict[str, Any],
    root: Path,
    num_features: int,
    labels: _LabelLookup,
    origin: str = "centre",
) -> ObjectRecord:
    path = root / entry["path"]
    relative = read_points(path, num_features)
    if origin == "bottom":  # relative to the bottom centre: the centre is dz / 2 above it
        relative = relative.astype(np.float64)
        relative[:, 2] -= entry["box"][5] / 2.0
    if len(relative) != entry["num_points"]:
        raise DataError(
            f"{path}: holds {len(relative)} points, the infos say num_points_in_gt = "
            f"{entry['num_points']}"
        )
    box = entry["box"]
    occlusion, truncation = -1, float("nan")
    frame_labels = labels.get(entry["image_idx"])
    if frame_labels is not None:
        i = entry["gt_idx"]
        if i >= len(frame_labels) or frame_labels.names[i] != entry["name"]:
            raise DataError(
                f"{labels.directory / (entry['image_idx'] + '.txt')}: object {i} is not a "
                f"{entry['name']} as {entry['path']} says; labels and database disagree"
            )
        occlusion, truncation = int(frame_labels.occlusion[i]), float(frame_labels.truncation[i])
    velocity = entry.get("velocity")
    canonical = rotate_points_z(relative, -box[6])
    _check_points_in_box(path, canonical, box)
    return ObjectRecord(
        velocity=None if velocity is None else rotate_velocities(velocity, -box[6])[0],
        points=canonical,
        name=entry["name"],
        box=box,
        frame_id=entry["image_idx"],
        index_in_frame=entry["gt_idx"],
        difficulty=entry["difficulty"],
        occlusion=occlusion,
        truncation=truncation,
    )
