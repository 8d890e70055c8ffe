"""nuScenes frames from the frameworks' infos pickles: OpenPCDet's ``nuscenes_infos_*sweeps_*.pkl``
and MMDetection3D 1.x's ``nuscenes_infos_{train,val}.pkl`` (its v2 format), read through
:mod:`drcpo.database.safe_pickle` (no code in the file is run), points read relative to the data
root. Both give the datasets protocol (``frame_ids``, ``frame(frame_id)``) with the frames
:class:`~drcpo.datasets.nuscenes.NuScenesDataset` gives: LiDAR frame, boxes ``(M, 7)`` in our
(= OpenPCDet's) convention with z at the centre, ``velocity (M, 2)``, 5 point columns, sweeps
joined with ``sweep_origins`` / ``sweep_time_lags``.

OpenPCDet's infos (``pcdet/datasets/nuscenes/nuscenes_utils.py``), one dict per sample:
``lidar_path`` (relative to the root), ``token``, ``timestamp`` (s), ``sweeps`` (the earlier
sweeps, nearest first: ``lidar_path``, ``sample_data_token``, ``transform_matrix`` (4, 4) sweep
-> key LiDAR, or ``None`` for the key sweep itself at a scene's start; ``time_lag`` s),
``gt_boxes (N, 9)`` (x, y, z, dx, dy, dz, heading, vx, vy; velocity ``nan`` where unknown),
``gt_names`` (``ignore`` for dropped categories), ``num_lidar_pts``, ``num_radar_pts``. A scene's
first samples repeat sweeps to fill the list; repeats are joined once.

MMDetection3D's v2 infos: ``{"metainfo": {"categories": {name: label}, ...}, "data_list":
[...]}``, each sample: ``token``, ``timestamp`` (s), ``ego2global`` (4, 4), ``lidar_points``
(``lidar_path``: a file name under ``samples/LIDAR_TOP``, ``lidar2ego``, ``num_pts_feats``),
``lidar_sweeps`` (nearest first: ``timestamp``, ``ego2global``, ``lidar_points`` with
``lidar_path`` and ``lidar2ego``), ``instances`` (``bbox_3d``: 7 values, our convention, z at
the centre; ``bbox_label_3d``; ``velocity``: 2 values, maybe ``nan``; ``num_lidar_pts``,
``num_radar_pts``). A sweep's file is found as MMDetection3D finds it: its name under
``samples/LIDAR_TOP`` when its path holds ``samples``, else under ``sweeps/LIDAR_TOP``; a sweep's
pose comes from its float64 ``ego2global`` and ``lidar2ego`` (not the float32 ``lidar2sensor``).

Boxes of classes outside ``classes`` and (as the frameworks' valid flag) boxes with no LiDAR and
no radar point are dropped; ``nan`` velocities become 0.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from drcpo.database import safe_pickle
from drcpo.datasets.nuscenes import (
    NUSCENES_CLASSES,
    check_sweep_arguments,
    drop_close,
    read_pcd_bin,
)
from drcpo.errors import DataError
from drcpo.frame import Frame, FrameSequence

__all__ = ["MMDet3DNuScenesInfos", "NuScenesInfos", "OpenPCDetNuScenesInfos"]


class NuScenesInfos(FrameSequence):
    """Frames from a list of per-sample infos; the two subclasses read the two formats.

    Args:
        infos_pkl: the infos pickle.
        root: the data root the point paths are relative to (default: the pickle's directory).
        sweeps: earlier sweeps to join to each key sweep, 0 to 30 (fewer where the infos list
            fewer).
        classes: detection classes to keep.
        keep_empty: keep boxes with no LiDAR and no radar point.
        remove_close: drop the points of earlier sweeps within this many metres of their sensor
            in x and y (:func:`~drcpo.datasets.nuscenes.drop_close`), 0: keep all.
    """

    def __init__(
        self,
        infos_pkl: str | os.PathLike,
        root: str | os.PathLike | None = None,
        sweeps: int = 0,
        classes: Sequence[str] = NUSCENES_CLASSES,
        keep_empty: bool = False,
        remove_close: float = 0.0,
    ) -> None:
        check_sweep_arguments(sweeps, remove_close, classes)
        self.path = Path(infos_pkl)
        self.root = Path(root) if root is not None else self.path.parent
        self.sweeps = sweeps
        self.classes = tuple(classes)
        self.keep_empty = keep_empty
        self.remove_close = float(remove_close)
        self.infos = self._samples(safe_pickle.load(self.path))
        self.frame_ids: list[str] = []
        self._index: dict[str, int] = {}
        for number, info in enumerate(self.infos):
            token = _get(info, "token", str, self._where(number))
            if token in self._index:
                raise DataError(f"{self._where(number)}: token {token!r} appears twice")
            self._index[token] = number
            self.frame_ids.append(token)

    def _samples(self, data: Any) -> list[dict[str, Any]]:
        raise NotImplementedError

    def _where(self, number: int) -> str:
        return f"{self.path}: sample {number}"

    def info(self, frame_id: str) -> dict[str, Any]:
        if frame_id not in self._index:
            raise DataError(f"{self.path}: no sample with token {frame_id!r}")
        return self.infos[self._index[frame_id]]

    def frame(self, frame_id: str) -> Frame:
        """The key sweep of sample ``frame_id`` with its boxes and earlier sweeps joined."""
        number = self._index.get(frame_id, -1)
        info = self.info(frame_id)
        where = self._where(number)
        key_path = self._key_path(info, where)
        points = read_pcd_bin(key_path)
        origins, lags = [np.zeros(3)], [0.0]
        if self.sweeps:
            parts = [points.copy()]
            parts[0][:, 4] = 0.0
            for path, to_key, lag in self._sweep_list(info, where):
                sweep = drop_close(read_pcd_bin(path), self.remove_close)
                xyz = sweep[:, :3].astype(np.float64) @ to_key[:3, :3].T + to_key[:3, 3]
                sweep[:, :3] = xyz.astype(np.float32)
                sweep[:, 4] = lag
                parts.append(sweep)
                origins.append(to_key[:3, 3].copy())
                lags.append(float(lag))
            points = np.concatenate(parts)
        boxes, names, velocity, lidar, radar = self._labels(info, where)
        keep = np.isin(names, self.classes)
        if not self.keep_empty:
            keep &= (lidar + radar) > 0
        metadata = {
            "frame_id": frame_id,
            "velocity": np.nan_to_num(velocity[keep], nan=0.0),
            "num_points_in_gt": lidar[keep],
            "point_features": ("intensity", "time_lag" if self.sweeps else "ring"),
            "sweep_origins": np.array(origins, dtype=np.float64),
            "sweep_time_lags": np.array(lags, dtype=np.float64),
            "lidar_path": str(key_path.relative_to(self.root)),
        }
        return Frame(points=points, boxes=boxes[keep], names=names[keep], metadata=metadata)

    def _key_path(self, info: dict[str, Any], where: str) -> Path:
        raise NotImplementedError

    def _sweep_list(
        self, info: dict[str, Any], where: str
    ) -> list[tuple[Path, np.ndarray, np.float32]]:
        raise NotImplementedError

    def _labels(self, info: dict[str, Any], where: str) -> tuple[np.ndarray, ...]:
        raise NotImplementedError

    def _inside(self, relative: str, where: str) -> Path:
        """``root / relative``; :class:`DataError` unless a relative path inside the root."""
        path = PurePosixPath(relative)
        if path.is_absolute() or ".." in path.parts or not path.parts:
            raise DataError(f"{where}: {relative!r} must be a path inside the data root")
        return self.root / path

    def _checked_lags(
        self, found: list[tuple[Path, np.ndarray, np.float32]], where: str
    ) -> list[tuple[Path, np.ndarray, np.float32]]:
        previous = np.float32(0.0)
        for number, (_, _, lag) in enumerate(found):
            if not lag > previous:
                raise DataError(
                    f"{where}: sweep {number} has time lag {float(lag)!r} s, not more than the "
                    f"one before ({float(previous)!r}); sweeps must go back in time"
                )
            previous = lag
        return found


class OpenPCDetNuScenesInfos(NuScenesInfos):
    """Frames of OpenPCDet's nuScenes infos (see the module docstring)."""

    def _samples(self, data: Any) -> list[dict[str, Any]]:
        if not isinstance(data, list) or not all(isinstance(info, dict) for info in data):
            raise DataError(f"{self.path}: expected a list of per-sample dicts (OpenPCDet infos)")
        return data

    def _key_path(self, info: dict[str, Any], where: str) -> Path:
        return self._inside(_get(info, "lidar_path", str, where), f"{where} 'lidar_path'")

    def _sweep_list(self, info, where):
        sweeps = _get(info, "sweeps", list, where)
        found, seen = [], set()
        for number, sweep in enumerate(sweeps):
            if len(found) == self.sweeps:
                break
            at = f"{where} sweeps[{number}]"
            if not isinstance(sweep, dict):
                raise DataError(f"{at}: expected a dict, got {type(sweep).__name__}")
            token = _get(sweep, "sample_data_token", str, at)
            matrix = sweep.get("transform_matrix")
            if matrix is None or token in seen:  # the key sweep, or a repeat filling the list
                continue
            seen.add(token)
            to_key = _matrix(matrix, f"{at} 'transform_matrix'")
            lag = np.float32(_number(sweep.get("time_lag"), f"{at} 'time_lag'"))
            found.append((self._inside(_get(sweep, "lidar_path", str, at), at), to_key, lag))
        return self._checked_lags(found, where)

    def _labels(self, info, where):
        boxes = _array(info.get("gt_boxes", np.zeros((0, 9))), f"{where} 'gt_boxes'", 2, nan=True)
        if boxes.size == 0:
            boxes = boxes.reshape(0, 9)
        if boxes.shape[1] not in (7, 9):
            raise DataError(f"{where} 'gt_boxes': expected (N, 9) (or (N, 7)), got {boxes.shape}")
        if not np.isfinite(boxes[:, :7]).all():
            raise DataError(f"{where} 'gt_boxes': NaN or infinite box values")
        count = len(boxes)
        names = _names(info.get("gt_names", []), count, f"{where} 'gt_names'")
        velocity = boxes[:, 7:9] if boxes.shape[1] == 9 else np.zeros((count, 2))
        lidar = _counts(info.get("num_lidar_pts"), count, f"{where} 'num_lidar_pts'")
        radar = _counts(
            info.get("num_radar_pts", np.zeros(count)), count, f"{where} 'num_radar_pts'"
        )
        return _checked_boxes(boxes[:, :7], where), names, velocity.copy(), lidar, radar


class MMDet3DNuScenesInfos(NuScenesInfos):
    """Frames of MMDetection3D 1.x's nuScenes infos (v2 format; see the module docstring).

    ``points_prefix`` / ``sweeps_prefix``: where key and other sweep files lie under the root
    (MMDetection3D's ``data_prefix`` ``pts`` and ``sweeps``).
    """

    def __init__(
        self,
        infos_pkl: str | os.PathLike,
        root: str | os.PathLike | None = None,
        sweeps: int = 0,
        classes: Sequence[str] = NUSCENES_CLASSES,
        keep_empty: bool = False,
        remove_close: float = 0.0,
        points_prefix: str = "samples/LIDAR_TOP",
        sweeps_prefix: str = "sweeps/LIDAR_TOP",
    ) -> None:
        self.points_prefix, self.sweeps_prefix = points_prefix, sweeps_prefix
        super().__init__(infos_pkl, root, sweeps, classes, keep_empty, remove_close)

    def _samples(self, data: Any) -> list[dict[str, Any]]:
        where = str(self.path)
        if not isinstance(data, dict) or "data_list" not in data or "metainfo" not in data:
            raise DataError(
                f"{where}: expected MMDetection3D's v2 infos, a dict with 'metainfo' and "
                "'data_list' (older infos: convert them with its update_infos_to_v2.py)"
            )
        categories = _get(data["metainfo"], "categories", dict, f"{where} 'metainfo'")
        self.label_names = {}
        for name, label in categories.items():
            if not isinstance(name, str) or _integer(label) is None:
                raise DataError(
                    f"{where} metainfo 'categories': {name!r}: {label!r} is not a label"
                )
            if int(label) >= 0:
                self.label_names[int(label)] = name
        samples = data["data_list"]
        if not isinstance(samples, list) or not all(isinstance(s, dict) for s in samples):
            raise DataError(f"{where} 'data_list': expected a list of per-sample dicts")
        return samples

    def _key_path(self, info, where):
        points = _get(info, "lidar_points", dict, where)
        name = _get(points, "lidar_path", str, f"{where} 'lidar_points'")
        return self._inside(f"{self.points_prefix}/{name}", f"{where} 'lidar_points' 'lidar_path'")

    def _sweep_list(self, info, where):
        key_to_global = _pose(info, where)
        global_to_key = np.linalg.inv(key_to_global)
        now = _number(info.get("timestamp"), f"{where} 'timestamp'")
        found = []
        for number, sweep in enumerate(_get(info, "lidar_sweeps", list, where)[: self.sweeps]):
            at = f"{where} lidar_sweeps[{number}]"
            if not isinstance(sweep, dict):
                raise DataError(f"{at}: expected a dict, got {type(sweep).__name__}")
            name = _get(
                _get(sweep, "lidar_points", dict, at), "lidar_path", str, f"{at} 'lidar_points'"
            )
            prefix = self.points_prefix if "samples" in name else self.sweeps_prefix
            path = self._inside(f"{prefix}/{PurePosixPath(name).name}", f"{at} 'lidar_path'")
            lag = np.float32(now - _number(sweep.get("timestamp"), f"{at} 'timestamp'"))
            found.append((path, global_to_key @ _pose(sweep, at), lag))
        return self._checked_lags(found, where)

    def _labels(self, info, where):
        instances = _get(info, "instances", list, where) if "instances" in info else []
        count = len(instances)
        boxes, names = np.zeros((count, 7)), []
        velocity, lidar, radar = (
            np.zeros((count, 2)),
            np.zeros(count, np.int64),
            np.zeros(count, np.int64),
        )
        for i, instance in enumerate(instances):
            at = f"{where} instances[{i}]"
            if not isinstance(instance, dict):
                raise DataError(f"{at}: expected a dict, got {type(instance).__name__}")
            bbox = _array(instance.get("bbox_3d"), f"{at} 'bbox_3d'", 1)
            if bbox.shape[0] not in (7, 9):  # 9: with the velocity appended
                _bad(f"{at} 'bbox_3d'", "7 numbers", instance.get("bbox_3d"))
            boxes[i] = bbox[:7]
            label = _integer(instance.get("bbox_label_3d", instance.get("bbox_label")))
            if label is None:
                raise DataError(f"{at} 'bbox_label_3d': expected an integer label")
            names.append(self.label_names.get(label, "ignore"))
            if "velocity" in instance:
                value = _array(instance["velocity"], f"{at} 'velocity'", 1, nan=True)
                if value.shape != (2,):
                    raise DataError(f"{at} 'velocity': expected 2 numbers, got {value.shape}")
                velocity[i] = value
            lidar[i] = _counts([instance.get("num_lidar_pts")], 1, f"{at} 'num_lidar_pts'")[0]
            radar[i] = _counts([instance.get("num_radar_pts", 0)], 1, f"{at} 'num_radar_pts'")[0]
        return _checked_boxes(boxes, where), np.array(names, dtype=str), velocity, lidar, radar


# Checked reads of plain values -----------------------------------------------------------------
def _get(mapping: Any, key: str, kind: type, where: str) -> Any:
    if not isinstance(mapping, dict):
        raise DataError(f"{where}: expected a dict, got {type(mapping).__name__}")
    if key not in mapping:
        raise DataError(f"{where}: key {key!r} missing")
    value = mapping[key]
    if isinstance(value, np.str_):
        value = str(value)
    if not isinstance(value, kind):
        raise DataError(f"{where} {key!r}: expected a {kind.__name__}, got {type(value).__name__}")
    return value


def _bad(where: str, expected: str, value: Any) -> Any:
    raise DataError(f"{where}: expected {expected}, got {value!r}")


def _array(value: Any, where: str, ndim: int, nan: bool = False) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return _bad(where, "numbers", value)
    if array.ndim != ndim and array.size:
        return _bad(where, f"a {ndim}-D array of numbers", value)
    finite = np.isfinite(array) | (np.isnan(array) if nan else False)
    if not finite.all():
        raise DataError(f"{where}: NaN or infinite values")
    return array


def _matrix(value: Any, where: str) -> np.ndarray:
    matrix = _array(value, where, 2)
    if matrix.shape != (4, 4) or not np.allclose(matrix[3], [0, 0, 0, 1]):
        return _bad(where, "a (4, 4) homogeneous transform", value)
    return matrix


def _pose(record: dict[str, Any], where: str) -> np.ndarray:
    """LiDAR -> global of an MMDetection3D sample or sweep: ``ego2global @ lidar2ego``."""
    points = _get(record, "lidar_points", dict, where)
    lidar2ego = _matrix(points.get("lidar2ego"), f"{where} 'lidar_points' 'lidar2ego'")
    return _matrix(record.get("ego2global"), f"{where} 'ego2global'") @ lidar2ego


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        return _bad(where, "a number", value)
    if not math.isfinite(float(value)):
        return _bad(where, "a finite number", value)
    return float(value)


def _integer(value: Any) -> int | None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        return None
    return int(value)


def _counts(value: Any, count: int, where: str) -> np.ndarray:
    if value is None:
        return _bad(where, f"{count} point counts", value)
    array = np.asarray(value)
    if array.shape != (count,) or (count and array.dtype.kind not in "iu"):
        return _bad(where, f"{count} integer point counts", value)
    if (array < 0).any():
        return _bad(where, "counts >= 0", value)
    return array.astype(np.int64)


def _names(value: Any, count: int, where: str) -> np.ndarray:
    names = np.asarray(value)
    if names.shape != (count,) or (count and names.dtype.kind not in "US"):
        return _bad(where, f"{count} class names", value)
    return names.astype(str)


def _checked_boxes(boxes: np.ndarray, where: str) -> np.ndarray:
    if (boxes[:, 3:6] <= 0).any():
        row = int(np.flatnonzero((boxes[:, 3:6] <= 0).any(axis=1))[0])
        raise DataError(f"{where}: box {row} has a size <= 0 ({boxes[row, 3:6].tolist()})")
    return boxes
