"""nuScenes layout: the JSON tables, the LIDAR_TOP ``.pcd.bin`` sweeps, frames in our convention.

Layout read here (``ROOT`` as the frameworks' ``data/nuscenes``; no nuscenes-devkit needed)::

    ROOT/<version>/{scene, sample, sample_data, sample_annotation, instance, category,
                    ego_pose, calibrated_sensor, sensor}.json     (log, attribute, visibility,
                                                                   map: not needed here)
    ROOT/samples/LIDAR_TOP/*.pcd.bin     key sweeps, float32 (N, 5) x, y, z, intensity, ring
    ROOT/sweeps/LIDAR_TOP/*.pcd.bin      the sweeps between them (20 Hz), same format

Conventions as the devkit's: quaternions ``w, x, y, z``; timestamps in microseconds; a pose
record maps its child frame into its parent (ego -> global, sensor -> ego); a
``sample_annotation`` is a box in the global frame with ``size = (w, l, h)``. A frame is the
LIDAR_TOP sensor's own frame (x right, y forward, z up, as the frameworks keep it): boxes are
moved global -> ego -> lidar, ``dx = l, dy = w, dz = h``, heading = yaw of the box's x axis in
the lidar frame. Velocities follow the devkit's ``box_velocity`` (the instance's previous and
next annotations' positions over their samples' time, global frame; a one-sided difference at
a track's end; unknown without neighbours or when they lie too far apart in time), rotated into
the lidar frame as the frameworks' converters do; unknown -> 0. Category names map to the 10
detection classes as OpenPCDet's and MMDetection3D's converters map them; boxes of other
categories, and (like their ``valid_flag``) boxes with no LiDAR or radar point, are dropped.

The quaternion, pose and box conversions are :mod:`~drcpo.datasets.nuscenes_geometry`'s. Every
reader raises :class:`~drcpo.errors.DataError` naming the file (and token, field) at fault.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from drcpo.datasets.nuscenes_geometry import _finite, _quaternion, boxes_to_sensor, pose_matrix
from drcpo.errors import DataError
from drcpo.frame import Frame, FrameSequence

__all__ = [
    "CATEGORY_TO_CLASS",
    "LIDAR_CHANNEL",
    "MAX_VELOCITY_GAP",
    "NUSCENES_CLASSES",
    "NUSCENES_VERSIONS",
    "POINT_COLUMNS",
    "REQUIRED_TABLES",
    "NuScenesDataset",
    "NuScenesTables",
    "check_sweep_arguments",
    "drop_close",
    "read_pcd_bin",
    "read_scene_list",
]

#: The 10 detection classes, as both frameworks name them.
NUSCENES_CLASSES: tuple[str, ...] = (
    "car",
    "truck",
    "construction_vehicle",
    "bus",
    "trailer",
    "barrier",
    "motorcycle",
    "bicycle",
    "pedestrian",
    "traffic_cone",
)

#: nuScenes category -> detection class, as OpenPCDet's and MMDetection3D's converters map
#: them (the categories they map to ``ignore`` are absent: their boxes are dropped).
CATEGORY_TO_CLASS: dict[str, str] = {
    "human.pedestrian.adult": "pedestrian",
    "human.pedestrian.child": "pedestrian",
    "human.pedestrian.police_officer": "pedestrian",
    "human.pedestrian.construction_worker": "pedestrian",
    "vehicle.car": "car",
    "vehicle.motorcycle": "motorcycle",
    "vehicle.bicycle": "bicycle",
    "vehicle.bus.bendy": "bus",
    "vehicle.bus.rigid": "bus",
    "vehicle.truck": "truck",
    "vehicle.construction": "construction_vehicle",
    "vehicle.trailer": "trailer",
    "movable_object.barrier": "barrier",
    "movable_object.trafficcone": "traffic_cone",
}

NUSCENES_VERSIONS = ("v1.0-trainval", "v1.0-test", "v1.0-mini")
LIDAR_CHANNEL = "LIDAR_TOP"
#: Columns of a ``.pcd.bin`` file (float32 each).
POINT_COLUMNS = ("x", "y", "z", "intensity", "ring")
#: Seconds between the two annotations a velocity is taken from, at most (the devkit's
#: ``max_time_diff``; twice this for a centred difference).
MAX_VELOCITY_GAP = 1.5
#: The tables a frame needs (their records' fields are checked where they are used).
REQUIRED_TABLES = (
    "scene",
    "sample",
    "sample_data",
    "sample_annotation",
    "instance",
    "category",
    "ego_pose",
    "calibrated_sensor",
    "sensor",
)
_MICROSECONDS = 1e-6


def drop_close(points: np.ndarray, radius: float) -> np.ndarray:
    """``points`` less those within ``radius`` metres of their sensor in x and in y (a square,
    as OpenPCDet's ``remove_ego_points`` and MMDetection3D's ``remove_close`` cut the car's
    own returns out of earlier sweeps); all of them for ``radius`` 0."""
    if radius <= 0.0:
        return points
    close = (np.abs(points[:, 0]) < radius) & (np.abs(points[:, 1]) < radius)
    return points[~close]


def check_sweep_arguments(sweeps: Any, remove_close: Any, classes: Sequence[str]) -> None:
    """:class:`DataError` unless ``sweeps`` is an integer from 0 to 30, ``remove_close`` a
    finite number >= 0 and ``classes`` a non-empty subset of :data:`NUSCENES_CLASSES`."""
    if isinstance(sweeps, bool) or not isinstance(sweeps, int) or not 0 <= sweeps <= 30:
        raise DataError(f"sweeps must be an integer from 0 to 30, got {sweeps!r}")
    number = isinstance(remove_close, (int, float)) and not isinstance(remove_close, bool)
    if not number or not (math.isfinite(remove_close) and remove_close >= 0):
        raise DataError(f"remove_close must be a finite number >= 0 (metres), got {remove_close!r}")
    unknown = sorted(set(classes) - set(NUSCENES_CLASSES))
    if unknown or not classes:
        raise DataError(
            f"classes {unknown or list(classes)} not among the nuScenes detection classes "
            f"({', '.join(NUSCENES_CLASSES)})"
        )


# Files ---------------------------------------------------------------------------------------
def read_pcd_bin(path: str | os.PathLike) -> np.ndarray:
    """A ``.pcd.bin`` point cloud: ``float32 (N, 5)`` x, y, z (metres, sensor frame),
    intensity (0-255), ring index.

    Raises :class:`DataError` naming the file when it is missing, its size is not a multiple
    of 20 bytes (5 float32 per point: truncated) or it holds NaN or infinite values.
    """
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise DataError(f"{path}: cannot read point cloud ({exc.strerror or exc})") from exc
    width = 4 * len(POINT_COLUMNS)
    if len(data) % width:
        raise DataError(
            f"{path}: {len(data)} bytes is not a multiple of {width} (5 float32 per point: "
            "x, y, z, intensity, ring); the file is truncated or not a nuScenes .pcd.bin"
        )
    points = np.frombuffer(data, dtype="<f4").reshape(-1, len(POINT_COLUMNS)).astype(np.float32)
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise DataError(f"{path}: point {int(np.argmax(bad))} holds a NaN or infinite value")
    return points


def read_scene_list(path: str | os.PathLike) -> list[str]:
    """Scene names, one a line (blank lines and ``#`` comments skipped), from a split file."""
    try:
        lines = Path(path).read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read the scene list ({exc})") from exc
    names = [line.strip() for line in lines if line.strip() and not line.startswith("#")]
    if not names:
        raise DataError(f"{path}: the scene list names no scene")
    return names


class NuScenesTables:
    """The JSON tables of one version, indexed by token (only the :data:`REQUIRED_TABLES`).

    Also the reverse index the devkit builds: each sample's annotations (file order) and its
    key sample_data per sensor channel.
    """

    def __init__(self, root: str | os.PathLike, version: str) -> None:
        self.root = Path(root)
        self.version = version
        self.directory = self.root / version
        if not self.directory.is_dir():
            found = sorted(p.name for p in self.root.glob("v1.0-*") if p.is_dir())
            raise DataError(
                f"{self.directory}: nuScenes version directory missing "
                f"(found: {', '.join(found) or 'none'})"
            )
        self.records: dict[str, dict[str, dict[str, Any]]] = {}
        self.order: dict[str, list[str]] = {}
        for table in REQUIRED_TABLES:
            self._load(table)
        self.annotations: dict[str, list[str]] = {}
        for token in self.order["sample_annotation"]:
            sample = self.field("sample_annotation", token, "sample_token", str)
            self.annotations.setdefault(sample, []).append(token)
        self.key_data: dict[tuple[str, str], str] = {}
        for token in self.order["sample_data"]:
            if self.field("sample_data", token, "is_key_frame", bool):
                sample = self.field("sample_data", token, "sample_token", str)
                self.key_data[(sample, self.channel(token))] = token

    def path(self, table: str) -> Path:
        return self.directory / f"{table}.json"

    def _load(self, table: str) -> None:
        path = self.path(table)
        try:
            rows = json.loads(path.read_text())
        except FileNotFoundError:
            raise DataError(f"{path}: table {table!r} missing") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise DataError(f"{path}: cannot read table {table!r} ({exc})") from exc
        except RecursionError:
            raise DataError(f"{path}: cannot read table {table!r} (nested too deeply)") from None
        if not isinstance(rows, list):
            raise DataError(f"{path}: expected a JSON list of records, got {type(rows).__name__}")
        records: dict[str, dict[str, Any]] = {}
        for number, row in enumerate(rows):
            token = row.get("token") if isinstance(row, dict) else None
            if not isinstance(token, str) or not token:
                raise DataError(f"{path}: record {number} has no string 'token'")
            if token in records:
                raise DataError(f"{path}: token {token!r} appears twice")
            records[token] = row
        self.records[table] = records
        self.order[table] = list(records)

    def get(self, table: str, token: Any, referrer: str = "") -> dict[str, Any]:
        """The record ``token`` of ``table``; :class:`DataError` naming the table file and
        ``referrer`` (who pointed at it) when there is none."""
        record = self.records[table].get(token) if isinstance(token, str) else None
        if record is None:
            by = f" (referenced by {referrer})" if referrer else ""
            raise DataError(f"{self.path(table)}: no record with token {token!r}{by}")
        return record

    def field(self, table: str, token: str, name: str, kind: type | tuple[type, ...]) -> Any:
        """Field ``name`` of record ``token``, of type ``kind``, else :class:`DataError`."""
        record = self.get(table, token)
        value = record.get(name)
        if (
            name not in record
            or not isinstance(value, kind)
            or (kind is int and isinstance(value, bool))
        ):
            wanted = kind.__name__ if isinstance(kind, type) else "/".join(k.__name__ for k in kind)
            raise DataError(
                f"{self.path(table)}: record {token!r} field {name!r} must be a {wanted}, "
                f"got {value!r}"
            )
        return value

    def link(self, table: str, token: str, name: str, target: str) -> dict[str, Any]:
        """The ``target`` record that field ``name`` of ``table`` record ``token`` names."""
        value = self.field(table, token, name, str)
        return self.get(target, value, f"{table}.json {token!r} field {name!r}")

    def channel(self, sample_data: str) -> str:
        sensor_calib = self.link(
            "sample_data", sample_data, "calibrated_sensor_token", "calibrated_sensor"
        )
        sensor = self.link("calibrated_sensor", sensor_calib["token"], "sensor_token", "sensor")
        return self.field("sensor", sensor["token"], "channel", str)

    def timestamp(self, table: str, token: str) -> int:
        """Microseconds."""
        return self.field(table, token, "timestamp", int)

    def sensor_to_global(self, sample_data: str) -> np.ndarray:
        """``(4, 4)`` sensor -> global transform of a sample_data record (its ego pose times its
        calibrated sensor)."""
        calib = self.link(
            "sample_data", sample_data, "calibrated_sensor_token", "calibrated_sensor"
        )
        pose = self.link("sample_data", sample_data, "ego_pose_token", "ego_pose")
        return self._pose("ego_pose", pose) @ self._pose("calibrated_sensor", calib)

    def _pose(self, table: str, record: dict[str, Any]) -> np.ndarray:
        where = f"{self.path(table)}: record {record['token']!r}"
        return pose_matrix(record.get("translation"), record.get("rotation"), where)


@dataclass(frozen=True)
class _Boxes:
    """A sample's annotations in the sensor frame (rows = kept annotations)."""

    boxes: np.ndarray
    names: np.ndarray
    velocity: np.ndarray
    num_points: np.ndarray
    tokens: list[str]
    instances: list[str]


class NuScenesDataset(FrameSequence):
    """LIDAR_TOP frames of a nuScenes-layout data set (the datasets protocol: ``frame_ids``,
    ``frame(frame_id)``).

    Args:
        root: the data root (holding ``samples/``, ``sweeps/`` and ``<version>/``).
        version: the table directory, e.g. ``v1.0-trainval`` or ``v1.0-mini``.
        scenes: names (or tokens) of the scenes to read, in the order given, or a split: a text
            file of scene names, one a line (e.g. the devkit's ``splits.val`` written out);
            ``None``: every
            scene in ``scene.json`` order.
        sweeps: how many earlier sweeps (following the sample_data ``prev`` chain) to join to
            each key sweep, 0 to 30; fewer at a scene's start.
        classes: detection classes to keep (of :data:`NUSCENES_CLASSES`).
        keep_empty: keep boxes with no LiDAR and no radar point (the frameworks drop them).
        remove_close: drop the points of earlier sweeps within this many metres of their sensor
            in x and y (:func:`drop_close`; the frameworks' pipelines use 1.0), 0: keep all.

    ``frame_ids`` are sample tokens, scene by scene, in time order. ``frame(token)``: points
    ``float32 (N, 5)``: x, y, z, intensity (0-255), then the ring index (``sweeps=0``) or the
    sweep's time lag in seconds (0 for the key sweep); metadata ``point_features``,
    ``velocity (M, 2)`` (m/s, lidar frame), ``num_points_in_gt (M,)`` (the annotations'
    ``num_lidar_pts``), ``sweep_origins (S, 3)`` (each sweep's sensor origin in the key sweep's
    frame; row 0 the key sweep), ``sweep_time_lags (S,)`` (seconds, float32 values as in the
    points), ``timestamp`` (seconds), ``scene``, ``annotation_tokens``, ``instance_tokens``,
    ``lidar_path``.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        version: str = "v1.0-trainval",
        scenes: Sequence[str] | str | os.PathLike | None = None,
        sweeps: int = 0,
        classes: Sequence[str] = NUSCENES_CLASSES,
        keep_empty: bool = False,
        remove_close: float = 0.0,
    ) -> None:
        check_sweep_arguments(sweeps, remove_close, classes)
        if isinstance(scenes, (str, os.PathLike)):
            scenes = read_scene_list(scenes)
        self.root = Path(root)
        self.tables = NuScenesTables(root, version)
        self.sweeps = sweeps
        self.classes = tuple(classes)
        self.keep_empty = keep_empty
        self.remove_close = float(remove_close)
        self.scene_tokens = self._select_scenes(scenes)
        self.frame_ids: list[str] = []
        self.scene_of: dict[str, str] = {}
        for scene in self.scene_tokens:
            for token in self._samples_of(scene):
                if token in self.scene_of:  # two scenes (or one listed twice) share a sample
                    raise DataError(
                        f"{self.tables.path('sample')}: sample {token!r} is reached from scene "
                        f"{self.scene_of[token]!r} and from scene {scene!r}; each sample "
                        "belongs to one scene (is a scene listed twice?)"
                    )
                self.frame_ids.append(token)
                self.scene_of[token] = scene

    def _select_scenes(self, scenes: Sequence[str] | None) -> list[str]:
        t = self.tables
        if scenes is None:
            return list(t.order["scene"])
        by_name = {t.field("scene", s, "name", str): s for s in t.order["scene"]}
        chosen = []
        for scene in scenes:
            token = by_name.get(scene, scene if scene in t.records["scene"] else None)
            if token is None:
                listing = ", ".join(sorted(by_name)[:10]) + (" ..." if len(by_name) > 10 else "")
                raise DataError(f"{t.path('scene')}: no scene named {scene!r} (have: {listing})")
            chosen.append(token)
        return chosen

    def _samples_of(self, scene: str) -> list[str]:
        """The scene's samples along its ``next`` chain, checked as the devkit's tables promise:
        each sample of this scene, none twice, the chain ending at ``last_sample_token`` (a
        chain running on into the next scene would leak its samples into this one's split)."""
        t = self.tables
        token = t.field("scene", scene, "first_sample_token", str)
        last = t.field("scene", scene, "last_sample_token", str)
        where = f"scene.json {scene!r} field 'first_sample_token'"
        samples: list[str] = []
        seen: set[str] = set()
        while token:
            t.get("sample", token, where)
            if token in seen:
                raise DataError(f"{t.path('sample')}: the 'next' chain of scene {scene!r} loops")
            owner = t.field("sample", token, "scene_token", str)
            if owner != scene:
                raise DataError(
                    f"{t.path('sample')}: sample {token!r}, reached along the 'next' chain of "
                    f"scene {scene!r}, belongs to scene {owner!r}"
                )
            seen.add(token)
            samples.append(token)
            if token == last:
                break
            where = f"sample.json {token!r} field 'next'"
            token = t.field("sample", token, "next", str)
        if not samples or samples[-1] != last:
            raise DataError(
                f"{t.path('sample')}: the 'next' chain of scene {scene!r} ends at "
                f"{(samples or [''])[-1]!r}, not at its last_sample_token {last!r}"
            )
        return samples

    # One frame --------------------------------------------------------------------------------
    def lidar_token(self, sample: str) -> str:
        """The LIDAR_TOP key sample_data of sample ``sample``."""
        self.tables.get("sample", sample, "a frame id")
        token = self.tables.key_data.get((sample, LIDAR_CHANNEL))
        if token is None:
            raise DataError(
                f"{self.tables.path('sample_data')}: sample {sample!r} has no {LIDAR_CHANNEL} "
                "key frame (is_key_frame true)"
            )
        return token

    def points_path(self, sample_data: str) -> Path:
        name = self.tables.field("sample_data", sample_data, "filename", str)
        relative = PurePosixPath(name)
        if relative.is_absolute() or ".." in relative.parts or not relative.parts:
            raise DataError(
                f"{self.tables.path('sample_data')}: record {sample_data!r} field 'filename' "
                f"{name!r} must be a path inside the data root"
            )
        return self.root / relative

    def frame(self, frame_id: str) -> Frame:
        """The LIDAR_TOP frame of sample ``frame_id`` (see the class docstring)."""
        t = self.tables
        key = self.lidar_token(frame_id)
        key_to_global = t.sensor_to_global(key)
        global_to_key = np.linalg.inv(key_to_global)
        path = self.points_path(key)
        points = read_pcd_bin(path)
        origins, lags = [np.zeros(3)], [0.0]
        if self.sweeps:
            parts = [points.copy()]
            parts[0][:, 4] = 0.0
            for token, lag in self._earlier_sweeps(key):
                sweep = drop_close(read_pcd_bin(self.points_path(token)), self.remove_close)
                to_key = global_to_key @ t.sensor_to_global(token)
                xyz = sweep[:, :3].astype(np.float64) @ to_key[:3, :3].T + to_key[:3, 3]
                sweep[:, :3] = xyz.astype(np.float32)
                sweep[:, 4] = lag
                parts.append(sweep)
                origins.append(to_key[:3, 3])
                lags.append(float(lag))
            points = np.concatenate(parts)
        labels = self._boxes(frame_id, global_to_key)
        scene = t.link("sample", frame_id, "scene_token", "scene")
        metadata = {
            "frame_id": frame_id,
            "velocity": labels.velocity,
            "num_points_in_gt": labels.num_points,
            "point_features": ("intensity", "time_lag" if self.sweeps else "ring"),
            "sweep_origins": np.array(origins, dtype=np.float64),
            "sweep_time_lags": np.array(lags, dtype=np.float64),
            "timestamp": t.timestamp("sample_data", key) * _MICROSECONDS,
            "scene": t.field("scene", scene["token"], "name", str),
            "annotation_tokens": labels.tokens,
            "instance_tokens": labels.instances,
            "lidar_path": str(path.relative_to(self.root)),
        }
        return Frame(points=points, boxes=labels.boxes, names=labels.names, metadata=metadata)

    def _earlier_sweeps(self, key: str) -> list[tuple[str, np.float32]]:
        """Up to ``sweeps`` sample_data tokens before ``key`` with their time lags (seconds,
        float32: the value the points carry)."""
        t = self.tables
        now = t.timestamp("sample_data", key)
        found: list[tuple[str, np.float32]] = []
        token = key
        while len(found) < self.sweeps:
            previous = t.field("sample_data", token, "prev", str)
            if not previous:
                break
            t.get("sample_data", previous, f"sample_data.json {token!r} field 'prev'")
            lag = np.float32((now - t.timestamp("sample_data", previous)) * _MICROSECONDS)
            if not lag > (found[-1][1] if found else 0.0):
                raise DataError(
                    f"{t.path('sample_data')}: record {previous!r} ('prev' of {token!r}) is not "
                    f"earlier than it (timestamps must fall along the 'prev' chain)"
                )
            found.append((previous, lag))
            token = previous
        return found

    def _boxes(self, sample: str, global_to_sensor: np.ndarray) -> _Boxes:
        t = self.tables
        rows, names = [], []
        for token in t.annotations.get(sample, []):
            instance = t.link("sample_annotation", token, "instance_token", "instance")
            category = t.link("instance", instance["token"], "category_token", "category")
            name = CATEGORY_TO_CLASS.get(t.field("category", category["token"], "name", str))
            if name is None or name not in self.classes:
                continue
            lidar = t.field("sample_annotation", token, "num_lidar_pts", int)
            radar = t.field("sample_annotation", token, "num_radar_pts", int)
            if lidar + radar == 0 and not self.keep_empty:
                continue
            rows.append(token)
            names.append(name)
        centres, sizes, rotations = (np.zeros((len(rows), n)) for n in (3, 3, 4))
        velocity = np.zeros((len(rows), 3))
        for i, token in enumerate(rows):
            record = t.get("sample_annotation", token)
            where = f"{t.path('sample_annotation')}: record {token!r}"
            centres[i] = _finite(record.get("translation"), (3,), f"{where} field 'translation'")
            sizes[i] = _finite(record.get("size"), (3,), f"{where} field 'size'")
            if (sizes[i] <= 0).any():
                raise DataError(f"{where} field 'size': {sizes[i].tolist()} must be positive")
            rotations[i] = _quaternion(record.get("rotation"), f"{where} field 'rotation'")
            velocity[i] = self.box_velocity(token)
        boxes = boxes_to_sensor(centres, sizes, rotations, global_to_sensor)
        velocity = np.nan_to_num(velocity @ global_to_sensor[:3, :3].T, nan=0.0)[:, :2]
        return _Boxes(
            boxes=boxes,
            names=np.array(names, dtype=str),
            velocity=velocity,
            num_points=np.array(
                [t.get("sample_annotation", r)["num_lidar_pts"] for r in rows], dtype=np.int64
            ),
            tokens=rows,
            instances=[t.get("sample_annotation", r)["instance_token"] for r in rows],
        )

    def box_velocity(self, annotation: str) -> np.ndarray:
        """``(3,)`` velocity of an annotation's instance, global frame, m/s, as the devkit's
        ``box_velocity`` defines it (``nan`` where unknown)."""
        t = self.tables
        here = t.get("sample_annotation", annotation)
        ends = []
        for side in ("prev", "next"):
            other = t.field("sample_annotation", annotation, side, str)
            where = f"sample_annotation.json {annotation!r} field {side!r}"
            ends.append(t.get("sample_annotation", other, where) if other else None)
        if ends[0] is None and ends[1] is None:
            return np.full(3, np.nan)
        first, last = (end if end is not None else here for end in ends)

        def sample_time(record: dict[str, Any]) -> int:
            sample = t.link("sample_annotation", record["token"], "sample_token", "sample")
            return t.timestamp("sample", sample["token"])

        times = [sample_time(first), sample_time(last)]
        # microseconds subtracted before scaling: the devkit scales first, about 1e-7 s worse
        gap = (times[1] - times[0]) * _MICROSECONDS
        limit = MAX_VELOCITY_GAP * (2 if ends[0] is not None and ends[1] is not None else 1)
        if gap > limit:
            return np.full(3, np.nan)
        if gap <= 0:
            raise DataError(
                f"{t.path('sample_annotation')}: record {annotation!r}: its track's samples are "
                f"not in time order ({first['token']!r} at {times[0]}, {last['token']!r} at "
                f"{times[1]} us)"
            )
        where = f"{t.path('sample_annotation')}: record"
        start = _finite(first.get("translation"), (3,), f"{where} {first['token']!r} translation")
        end = _finite(last.get("translation"), (3,), f"{where} {last['token']!r} translation")
        return (end - start) / gap
