"""Making a ground-truth database: from a KITTI split or any data set of frames (the datasets
protocol: ``frame_ids`` and ``frame(frame_id)``, e.g. nuScenes-style data). Importing
OpenPCDet's or MMDetection3D's database instead is :mod:`~drcpo.database.dbinfos`.

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
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from drcpo.database.store import (
    DATABASE_OUTPUT,
    GroundTruthDatabase,
    ObjectRecord,
    default_point_features,
)
from drcpo.datasets.kitti import DONT_CARE, KittiDataset
from drcpo.errors import ConfigError, DataError
from drcpo.frame import VELOCITY, Frame, rotate_velocities
from drcpo.geometry import to_canonical
from drcpo.outputs import check_output

__all__ = [
    "DEFAULT_CLASSES",
    "Dataset",
    "MapFrames",
    "Progress",
    "build_database",
    "build_database_from",
    "frame_records",
    "points_in_boxes_openpcdet",
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
