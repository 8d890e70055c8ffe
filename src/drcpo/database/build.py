"""Making a ground-truth database: from a KITTI split or any data set of frames (the datasets
protocol: ``frame_ids`` and ``frame(frame_id)``, e.g. nuScenes-style data), or by importing
OpenPCDet's.

Both paths give the same database for the same frames: objects cut out of the *full* point
cloud (not field-of-view filtered) with OpenPCDet's own inside rule, so the per-object point
counts equal OpenPCDet's ``num_points_in_gt``, then stored in canonical pose with their metadata
(see :mod:`drcpo.database`). Filters such as minimum points or difficulty are applied later,
when indexing or sampling, as OpenPCDet does. Every point column is kept (x, y, z and the
frame's features, e.g. intensity and the sweep time lag), and a frame's per-box velocities
(``metadata["velocity"]``) are stored in each object's canonical frame.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path, PurePosixPath
from typing import Any, Protocol

import numpy as np

from drcpo.database import safe_pickle
from drcpo.database.store import (
    DATABASE_OUTPUT,
    GroundTruthDatabase,
    ObjectRecord,
    default_point_features,
)
from drcpo.datasets.kitti import (
    DONT_CARE,
    FRAME_ID,
    KittiDataset,
    KittiLabels,
    read_labels,
    read_points,
)
from drcpo.errors import ConfigError, DataError, shown
from drcpo.frame import MAX_COORDINATE, VELOCITY, Frame, rotate_velocities
from drcpo.geometry import rotate_points_z, to_canonical
from drcpo.outputs import check_output

__all__ = [
    "DEFAULT_CLASSES",
    "Dataset",
    "MapFrames",
    "Progress",
    "build_database",
    "build_database_from",
    "frame_records",
    "import_mmdet3d",
    "import_openpcdet",
    "points_in_boxes_openpcdet",
    "validate_dbinfos",
]

DEFAULT_CLASSES = ("Car", "Pedestrian", "Cyclist")

Progress = Callable[[int, int], None]
"""Called as ``progress(done, total)`` after each frame (build) or object (import)."""


class Dataset(Protocol):
    """What a database is built from: frames by id (e.g.
    :class:`~drcpo.datasets.kitti.KittiDataset`). A frame's metadata may carry per-box
    ``difficulty``, ``occlusion``, ``truncation``, ``velocity`` (``(M, 2)``) and the names of
    its point features, ``point_features``. It is sent to worker processes, so it must pickle."""

    frame_ids: list[str]

    def frame(self, frame_id: str) -> Frame: ...


# OpenPCDet's points_in_boxes_cpu (roiaware_pool3d.cpp, check_pt_in_box3d_cpu) widens the box
# by this float32 margin in x and y only.
_OPENPCDET_MARGIN = float(np.float32(1e-2))


def points_in_boxes_openpcdet(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """OpenPCDet's ``points_in_boxes_cpu`` rule, bit for bit: ``bool (N, M)``.

    Args:
        points: ``(N, 3+)`` LiDAR points, metres.
        boxes: ``(M, 7)`` boxes (centre, dx, dy, dz, heading).

    Points and boxes are cast to float32. A point is inside when ``|z - cz| <= dz / 2`` and, in
    the box frame, ``|local_x| < dx / 2 + 0.01`` and ``|local_y| < dy / 2 + 0.01``; the offsets
    and the rotation are float32 sums and products, the comparisons are in float64 (the C++
    source compares a float against ``dz / 2.0``). This differs from
    :func:`drcpo.geometry.points_in_boxes` (closed, no margin) on purpose: it reproduces the
    point sets of OpenPCDet's ``gt_database``.
    """
    xyz = np.asarray(points)[:, :3].astype(np.float32)
    boxes = np.asarray(boxes, dtype=np.float32).reshape(-1, 7)
    out = np.zeros((len(xyz), len(boxes)), dtype=bool)
    for m, (cx, cy, cz, dx, dy, dz, heading) in enumerate(boxes):
        near_z = np.abs(xyz[:, 2] - cz).astype(np.float64) <= float(dz) / 2.0
        rows = np.flatnonzero(near_z)
        # cos/sin of the float angle rounded to float32, as the C++ code stores them
        cos = np.float32(np.cos(-float(heading)))
        sin = np.float32(np.sin(-float(heading)))
        shift_x = xyz[rows, 0] - cx
        shift_y = xyz[rows, 1] - cy
        local_x = shift_x * cos + shift_y * -sin
        local_y = shift_x * sin + shift_y * cos
        inside = (np.abs(local_x).astype(np.float64) < float(dx) / 2.0 + _OPENPCDET_MARGIN) & (
            np.abs(local_y).astype(np.float64) < float(dy) / 2.0 + _OPENPCDET_MARGIN
        )
        out[rows[inside], m] = True
    return out


def frame_records(frame: Frame, classes: Sequence[str] | None = None) -> list[ObjectRecord]:
    """Cut the labelled objects of the chosen ``classes`` (``None``: all) out of a frame.

    Per-box ``difficulty``, ``occlusion`` and ``truncation`` come from the frame's metadata
    (as :class:`~drcpo.datasets.kitti.KittiDataset` fills it) and are unknown when absent; a
    velocity (``metadata["velocity"]``, ``(M, 2)`` in the LiDAR frame) is stored rotated by the
    box's -heading, in the object's canonical frame. Points keep all their columns.
    Each record's ``index_in_frame`` is the object's row in ``frame.boxes``: for KITTI frames
    its row among the non-``DontCare`` labels, OpenPCDet's ``gt_idx``.
    """
    keep = [i for i, name in enumerate(frame.names) if classes is None or name in classes]
    if not keep:
        return []
    difficulty = _per_box(frame, "difficulty", -1)
    occlusion = _per_box(frame, "occlusion", -1)
    truncation = _per_box(frame, "truncation", np.nan)
    velocity = _velocities(frame)
    inside = points_in_boxes_openpcdet(frame.points, frame.boxes[keep])
    return [
        ObjectRecord(
            points=to_canonical(frame.points[inside[:, column]], frame.boxes[i]),
            name=str(frame.names[i]),
            box=frame.boxes[i],
            frame_id=str(frame.frame_id),
            index_in_frame=i,
            difficulty=int(difficulty[i]),
            occlusion=int(occlusion[i]),
            truncation=float(truncation[i]),
            velocity=None if velocity is None else velocity[i],
        )
        for column, i in enumerate(keep)
    ]


def _velocities(frame: Frame) -> np.ndarray | None:
    """The frame's box velocities in each box's canonical frame, ``(M, 2)``, or ``None``."""
    values = frame.metadata.get(VELOCITY)
    if values is None:
        return None
    values = np.asarray(values, dtype=np.float64)
    if values.shape != (len(frame.boxes), 2) or not np.isfinite(values).all():
        raise DataError(
            f"frame {frame.frame_id}: metadata {VELOCITY!r} must be ({len(frame.boxes)}, 2) "
            f"finite numbers, got shape {values.shape}"
        )
    return rotate_velocities(values, -frame.boxes[:, 6])


def _per_box(frame: Frame, key: str, unknown: float) -> np.ndarray:
    values = frame.metadata.get(key)
    if values is None:
        return np.full(len(frame.boxes), unknown)
    values = np.asarray(values)
    if values.shape != (len(frame.boxes),):
        raise DataError(
            f"frame {frame.frame_id}: metadata {key!r} has shape {values.shape}, "
            f"expected ({len(frame.boxes)},)"
        )
    return values


def build_database(
    root: str | os.PathLike,
    split: str,
    out: str | os.PathLike,
    classes: Sequence[str] | str = DEFAULT_CLASSES,
    workers: int = 1,
    overwrite: bool = False,
    progress: Progress | None = None,
    map_frames: MapFrames | None = None,
) -> GroundTruthDatabase:
    """Build a ground-truth database from a KITTI split and write it to ``out`` atomically.

    Args:
        root: KITTI root (holding ``ImageSets`` and ``training``).
        split: split name, a file ``ImageSets/<split>.txt``.
        out: database directory to create.
        classes: class names to keep, or ``"all"`` for every non-``DontCare`` class.
        workers: processes reading frames in parallel; the result does not depend on it.
        overwrite: replace an existing ``out`` (only a drcpo database; only once the new
            database is complete).
        progress: optional ``progress(frames_done, frames_total)`` callback.
        map_frames: who reads the frames (:data:`MapFrames`; e.g. a cluster's workers,
            :mod:`drcpo.distributed`); default: ``workers`` processes. The result is the same.

    Returns the database opened from ``out``. Raises :class:`DataError` on bad input (naming the
    file) or when the split holds no object of the chosen classes, :class:`ConfigError` on bad
    arguments, :class:`~drcpo.errors.OutputError` when ``out`` cannot be written (it exists
    and ``overwrite`` is false, it is not a drcpo database, it overlaps ``root``).
    """
    _check_classes(classes)
    if workers < 1:
        raise ConfigError(f"workers must be >= 1, got {workers}")
    out = Path(out)
    check_output(out, DATABASE_OUTPUT, overwrite, inputs=[root])  # before reading any frame
    dataset = KittiDataset(root, split)
    parameters = {
        "source": "kitti",
        "root": str(Path(root).resolve()),
        "split": split,
    }
    return build_database_from(
        dataset,
        out,
        classes,
        workers,
        overwrite,
        progress,
        parameters=parameters,
        point_dim=dataset.num_features,
        describe=f"{dataset.root}: split {split!r}",
        map_frames=map_frames,
    )


def build_database_from(
    dataset: Dataset,
    out: str | os.PathLike,
    classes: Sequence[str] | str = DEFAULT_CLASSES,
    workers: int = 1,
    overwrite: bool = False,
    progress: Progress | None = None,
    parameters: dict[str, Any] | None = None,
    point_dim: int | None = None,
    describe: str | None = None,
    map_frames: MapFrames | None = None,
) -> GroundTruthDatabase:
    """Build a ground-truth database from any data set of frames and write it to ``out``.

    Args:
        dataset: ``frame_ids`` and ``frame(frame_id) -> Frame`` (:class:`Dataset`), e.g.
            :class:`~drcpo.datasets.kitti.KittiDataset` or a nuScenes-style reader.
        out, classes, workers, overwrite, progress: as in :func:`build_database`.
        parameters: what the manifest records of the source (default: the data set's class
            name and, when it has one, its ``root``).
        point_dim: columns per point (default: the first frame's); every frame must have them.
        describe: the data set in messages (default: its class name).
        map_frames: who reads the frames (:data:`MapFrames`), as in :func:`build_database`.

    The point features' names come from the data set's ``point_features`` attribute, else the
    first frame's ``metadata["point_features"]``, else :func:`default_point_features`.
    Velocities are stored when any frame has ``metadata["velocity"]`` (objects of frames
    without get 0).
    """
    chosen = _check_classes(classes)
    if workers < 1:
        raise ConfigError(f"workers must be >= 1, got {workers}")
    out = Path(out)
    root = getattr(dataset, "root", None)
    check_output(out, DATABASE_OUTPUT, overwrite, inputs=[] if root is None else [root])
    describe = describe or type(dataset).__name__
    frame_ids = list(dataset.frame_ids)
    names = getattr(dataset, "point_features", None)
    if frame_ids and (point_dim is None or names is None) and not isinstance(dataset, KittiDataset):
        first = dataset.frame(frame_ids[0])
        point_dim = first.points.shape[1] if point_dim is None else point_dim
        names = names if names is not None else first.metadata.get("point_features")
    point_dim = 4 if point_dim is None else int(point_dim)
    records = []
    for frame_objects in (map_frames or _map_frames)(dataset, chosen, workers, progress):
        for record in frame_objects:
            if record.points.shape[1] != point_dim:
                raise DataError(
                    f"{describe}: frame {record.frame_id} has {record.points.shape[1]} point "
                    f"columns, the first frame {point_dim}; every frame needs the same features"
                )
            records.append(record)
    if not records:
        raise DataError(
            f"{describe} ({len(frame_ids)} frames) holds no object of "
            f"classes {classes if chosen is None else list(chosen)}"
        )
    if parameters is None:
        parameters = {"source": type(dataset).__name__}
        if root is not None:
            parameters["root"] = str(Path(root).resolve())
    parameters = {
        **parameters,
        "classes": "all" if chosen is None else list(chosen),
        "frames": len(frame_ids),
        "inside_rule": "openpcdet points_in_boxes_cpu (full point cloud, not FOV-filtered)",
    }
    features = default_point_features(point_dim) if names is None else tuple(names)
    database = GroundTruthDatabase.from_records(
        records, point_dim=point_dim, point_features=features
    )
    database.save(out, parameters=parameters, overwrite=overwrite)
    return GroundTruthDatabase.open(out)


def _check_classes(classes: Sequence[str] | str) -> tuple[str, ...] | None:
    if isinstance(classes, str):
        if classes == "all":
            return None
        classes = [classes]
    chosen = tuple(dict.fromkeys(str(c) for c in classes))
    if not chosen:
        raise ConfigError("classes: give at least one class name, or 'all'")
    if "all" in chosen:
        raise ConfigError(f"classes: 'all' cannot be combined with class names {list(chosen)}")
    if DONT_CARE in chosen:
        raise ConfigError("classes: DontCare regions are not objects and cannot be stored")
    return chosen


# Worker processes read their frames from this dataset (set once per process, not per task).
_WORKER_STATE: dict[str, Any] = {}


def _init_worker(dataset: Dataset, classes: tuple[str, ...] | None) -> None:
    _WORKER_STATE.update(dataset=dataset, classes=classes)


def _records_of(frame_id: str) -> list[ObjectRecord]:
    return frame_records(_WORKER_STATE["dataset"].frame(frame_id), _WORKER_STATE["classes"])


#: ``map_frames(dataset, classes, workers, progress)``: :func:`frame_records` of every frame of
#: ``dataset``, yielded in its frame order, calling ``progress(done, total)`` as frames finish.
MapFrames = Callable[..., Iterable[list[ObjectRecord]]]


def _map_frames(
    dataset: Dataset,
    classes: tuple[str, ...] | None,
    workers: int,
    progress: Progress | None,
) -> Iterator[list[ObjectRecord]]:
    """Records of every frame, in split order, computed by ``workers`` processes."""
    total = len(dataset.frame_ids)
    if workers == 1 or total <= 1:
        results: Iterable[list[ObjectRecord]] = (
            frame_records(dataset.frame(frame_id), classes) for frame_id in dataset.frame_ids
        )
        yield from _report(results, total, progress)
        return
    chunk = max(1, total // (workers * 8))
    with ProcessPoolExecutor(
        max_workers=workers, initializer=_init_worker, initargs=(dataset, classes)
    ) as pool:
        # map() yields in submission order, so the database does not depend on scheduling.
        results = pool.map(_records_of, dataset.frame_ids, chunksize=chunk)
        yield from _report(results, total, progress)


def _report(items: Iterable, total: int, progress: Progress | None) -> Iterator:
    for done, item in enumerate(items, start=1):
        if progress is not None:
            progress(done, total)
        yield item


# OpenPCDet import -----------------------------------------------------------------------------
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
