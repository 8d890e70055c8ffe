"""Write a nuScenes-style layout (the inverse of :mod:`drcpo.datasets.nuscenes`).

What is written is what :class:`~drcpo.datasets.nuscenes.NuScenesDataset` (and the devkit) read:
the JSON tables under ``ROOT/<version>/`` (all thirteen the devkit loads: category,
attribute, visibility, instance, sensor, calibrated_sensor, ego_pose, log, scene, sample,
sample_data, sample_annotation, map) and the LIDAR_TOP point clouds (``samples/LIDAR_TOP/`` for
key sweeps, ``sweeps/LIDAR_TOP/`` for the others), float32 x 5. Tokens are 32 hex digits derived
from the scene name and the record's place, so the same scenes give the same files.

The whole root is written by :func:`drcpo.outputs.write_directory` (a temporary directory moved
into place when complete), with the marker ``ROOT/drcpo_nuscenes.json`` written last, so
``overwrite`` only ever replaces a root drcpo wrote.
"""

from __future__ import annotations

import hashlib
import json
import os
import struct
import zlib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drcpo.datasets.kitti import FRAME_ID
from drcpo.datasets.nuscenes import CATEGORY_TO_CLASS, LIDAR_CHANNEL, POINT_COLUMNS
from drcpo.errors import DataError
from drcpo.outputs import OutputKind, atomic_write_bytes, write_directory

__all__ = [
    "NUSCENES_MANIFEST",
    "NUSCENES_OUTPUT",
    "AnnotationRecord",
    "NuScenesWriter",
    "SceneRecord",
    "SweepRecord",
    "token_of",
    "write_nuscenes",
]

NUSCENES_MANIFEST = "drcpo_nuscenes.json"
NUSCENES_FORMAT = "drcpo-nuscenes"
NUSCENES_FORMAT_VERSION = 1
NUSCENES_OUTPUT = OutputKind(
    "drcpo nuScenes-style data set",
    NUSCENES_MANIFEST,
    NUSCENES_FORMAT,
    ("samples", "sweeps", "maps", "{version}"),
)

#: The devkit's visibility levels (token, level, description).
_VISIBILITY = (
    ("1", "v0-40", "visibility of whole object is between 0 and 40%"),
    ("2", "v40-60", "visibility of whole object is between 40 and 60%"),
    ("3", "v60-80", "visibility of whole object is between 60 and 80%"),
    ("4", "v80-100", "visibility of whole object is between 80 and 100%"),
)


@dataclass(frozen=True, eq=False)
class SweepRecord:
    """One LIDAR_TOP sweep.

    Attributes:
        timestamp: microseconds.
        points: ``float32 (N, 5)`` x, y, z (metres, sensor frame), intensity, ring.
        ego_translation: ``(3,)`` the ego pose (ego -> global), metres.
        ego_rotation: ``(4,)`` its ``w, x, y, z`` quaternion.
        key: whether the sweep is a sample's (annotated) key sweep.
    """

    timestamp: int
    points: np.ndarray
    ego_translation: np.ndarray
    ego_rotation: np.ndarray
    key: bool = False


@dataclass(frozen=True, eq=False)
class AnnotationRecord:
    """One box of a key sweep, global frame (nuScenes' convention).

    Attributes:
        instance: index of the object in its scene's ``instances``.
        translation: ``(3,)`` box centre, metres.
        size: ``(3,)`` width, length, height, metres.
        rotation: ``(4,)`` ``w, x, y, z`` quaternion, box -> global.
        num_lidar_pts: LiDAR points in the box.
        num_radar_pts: radar points in the box.
        visibility: the devkit's visibility level token, ``"1"`` to ``"4"``.
    """

    instance: int
    translation: np.ndarray
    size: np.ndarray
    rotation: np.ndarray
    num_lidar_pts: int
    num_radar_pts: int = 0
    visibility: str = "4"


@dataclass(frozen=True, eq=False)
class SceneRecord:
    """One scene: its sweeps in time order, the boxes of each key sweep, its objects.

    Attributes:
        name: unique scene name, e.g. ``scene-0001``.
        sweeps: the LIDAR_TOP sweeps, timestamps increasing; the key ones are the samples.
        annotations: per key sweep (in order), its boxes.
        instances: each object's nuScenes category name (e.g. ``vehicle.car``).
        lidar_translation, lidar_rotation: the calibrated sensor (sensor -> ego).
        description: the scene's free text.
    """

    name: str
    sweeps: list[SweepRecord]
    annotations: list[list[AnnotationRecord]]
    instances: list[str]
    lidar_translation: np.ndarray
    lidar_rotation: np.ndarray
    description: str = ""
    location: str = "synthetic"


def token_of(*parts: object) -> str:
    """A 32 hex digit token derived from ``parts`` (the same parts, the same token)."""
    return hashlib.md5("/".join(map(str, parts)).encode()).hexdigest()


def _floats(value: Any, shape: tuple[int, ...], where: str) -> list[float]:
    array = np.asarray(value, dtype=np.float64)
    if array.shape != shape or not np.isfinite(array).all():
        raise DataError(f"{where}: expected {shape} finite numbers, got {value!r}")
    return [float(v) for v in array]


@dataclass
class NuScenesWriter:
    """Builds a nuScenes layout under ``root``: :meth:`add_scene` writes a scene's point files
    and keeps its table rows, :meth:`finish` writes the tables."""

    root: Path
    version: str = "v1.0-trainval"
    tables: dict[str, list[dict[str, Any]]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        check_version_name(self.version)
        names = ("scene", "sample", "sample_data", "sample_annotation", "instance", "ego_pose")
        self.tables = {name: [] for name in (*names, "calibrated_sensor", "log")}
        self._categories: set[str] = set()
        self._scenes: set[str] = set()

    def add_scene(self, scene: SceneRecord) -> None:
        """Write ``scene``'s point clouds and keep its rows (:class:`DataError` on bad input)."""
        where = f"scene {scene.name!r}"
        if scene.name in self._scenes or not scene.name:
            raise DataError(f"{where}: scene names must be unique and non-empty")
        self._scenes.add(scene.name)
        keys = [i for i, sweep in enumerate(scene.sweeps) if sweep.key]
        if not keys:
            raise DataError(f"{where}: needs at least one key sweep")
        if len(scene.annotations) != len(keys):
            raise DataError(
                f"{where}: {len(scene.annotations)} annotation lists for {len(keys)} key sweeps"
            )
        times = [int(s.timestamp) for s in scene.sweeps]
        if (np.diff(times) <= 0).any():
            raise DataError(f"{where}: sweep timestamps must increase")
        scene_token, log_token = token_of(scene.name, "scene"), token_of(scene.name, "log")
        calib = token_of(scene.name, "calibrated_sensor")
        self.tables["log"].append(
            {
                "token": log_token,
                "logfile": scene.name,
                "vehicle": "drcpo",
                "date_captured": "2000-01-01",
                "location": scene.location,
            }
        )
        self.tables["calibrated_sensor"].append(
            {
                "token": calib,
                "sensor_token": token_of("sensor", LIDAR_CHANNEL),
                "translation": _floats(scene.lidar_translation, (3,), f"{where} lidar translation"),
                "rotation": _floats(scene.lidar_rotation, (4,), f"{where} lidar rotation"),
                "camera_intrinsic": [],
            }
        )
        samples = [token_of(scene.name, "sample", k) for k in range(len(keys))]
        for k, token in enumerate(samples):
            self.tables["sample"].append(
                {
                    "token": token,
                    "timestamp": times[keys[k]],
                    "prev": samples[k - 1] if k else "",
                    "next": samples[k + 1] if k + 1 < len(samples) else "",
                    "scene_token": scene_token,
                }
            )
        self._sample_data(scene, samples, calib)
        self._annotations(scene, samples)
        self.tables["scene"].append(
            {
                "token": scene_token,
                "log_token": log_token,
                "nbr_samples": len(samples),
                "first_sample_token": samples[0],
                "last_sample_token": samples[-1],
                "name": scene.name,
                "description": scene.description,
            }
        )

    def _sample_data(self, scene: SceneRecord, samples: list[str], calib: str) -> None:
        tokens = [token_of(scene.name, "sample_data", i) for i in range(len(scene.sweeps))]
        keys_so_far = 0
        for i, sweep in enumerate(scene.sweeps):
            where = f"scene {scene.name!r} sweep {i}"
            keys_so_far += bool(sweep.key)
            # a sweep belongs to the next key sample (the last one after the last key sweep)
            key_number = keys_so_far - 1 if sweep.key else min(keys_so_far, len(samples) - 1)
            folder = "samples" if sweep.key else "sweeps"
            name = f"{scene.name}__{LIDAR_CHANNEL}__{int(sweep.timestamp)}.pcd.bin"
            filename = f"{folder}/{LIDAR_CHANNEL}/{name}"
            _write_points(self.root / filename, sweep.points, where)
            pose = token_of(scene.name, "ego_pose", i)
            self.tables["ego_pose"].append(
                {
                    "token": pose,
                    "timestamp": int(sweep.timestamp),
                    "rotation": _floats(sweep.ego_rotation, (4,), f"{where} ego rotation"),
                    "translation": _floats(sweep.ego_translation, (3,), f"{where} ego translation"),
                }
            )
            self.tables["sample_data"].append(
                {
                    "token": tokens[i],
                    "sample_token": samples[key_number],
                    "ego_pose_token": pose,
                    "calibrated_sensor_token": calib,
                    "timestamp": int(sweep.timestamp),
                    "fileformat": "pcd",
                    "is_key_frame": bool(sweep.key),
                    "height": 0,
                    "width": 0,
                    "filename": filename,
                    "prev": tokens[i - 1] if i else "",
                    "next": tokens[i + 1] if i + 1 < len(tokens) else "",
                }
            )

    def _annotations(self, scene: SceneRecord, samples: list[str]) -> None:
        tracks: dict[int, list[tuple[str, AnnotationRecord, str]]] = {}
        for k, boxes in enumerate(scene.annotations):
            for box in boxes:
                if not 0 <= box.instance < len(scene.instances):
                    raise DataError(
                        f"scene {scene.name!r} sample {k}: instance {box.instance} out of range"
                    )
                token = token_of(scene.name, "sample_annotation", k, box.instance)
                tracks.setdefault(box.instance, []).append((token, box, samples[k]))
        for instance, track in sorted(tracks.items()):
            instance_token = token_of(scene.name, "instance", instance)
            category = scene.instances[instance]
            self._categories.add(category)
            for n, (token, box, sample) in enumerate(track):
                where = f"scene {scene.name!r} annotation {token}"
                size = _floats(box.size, (3,), f"{where} size")
                if min(size) <= 0:
                    raise DataError(f"{where}: size {size} must be positive")
                self.tables["sample_annotation"].append(
                    {
                        "token": token,
                        "sample_token": sample,
                        "instance_token": instance_token,
                        "visibility_token": box.visibility,
                        "attribute_tokens": [],
                        "translation": _floats(box.translation, (3,), f"{where} translation"),
                        "size": size,
                        "rotation": _floats(box.rotation, (4,), f"{where} rotation"),
                        "prev": track[n - 1][0] if n else "",
                        "next": track[n + 1][0] if n + 1 < len(track) else "",
                        "num_lidar_pts": int(box.num_lidar_pts),
                        "num_radar_pts": int(box.num_radar_pts),
                    }
                )
            self.tables["instance"].append(
                {
                    "token": instance_token,
                    "category_token": token_of("category", category),
                    "nbr_annotations": len(track),
                    "first_annotation_token": track[0][0],
                    "last_annotation_token": track[-1][0],
                }
            )

    def finish(self) -> None:
        """Write the tables of every scene added."""
        categories = sorted(set(CATEGORY_TO_CLASS) | self._categories)
        tables = {
            **self.tables,
            "category": [
                {"token": token_of("category", c), "name": c, "description": c} for c in categories
            ],
            "attribute": [],
            "visibility": [
                {"token": t, "level": level, "description": text} for t, level, text in _VISIBILITY
            ],
            "sensor": [
                {
                    "token": token_of("sensor", LIDAR_CHANNEL),
                    "channel": LIDAR_CHANNEL,
                    "modality": "lidar",
                }
            ],
            # One map for every log, as the devkit's reverse index needs; its image is blank
            # (drcpo's worlds have no map; the devkit draws it under a LiDAR sweep).
            "map": [
                {
                    "token": token_of("map", "drcpo"),
                    "log_tokens": [row["token"] for row in self.tables["log"]],
                    "category": "semantic_prior",
                    "filename": MAP_IMAGE,
                }
            ],
        }
        atomic_write_bytes(self.root / MAP_IMAGE, _blank_png(16))
        for name, rows in tables.items():
            text = json.dumps(rows, indent=0)
            atomic_write_bytes(self.root / self.version / f"{name}.json", text.encode())


MAP_IMAGE = "maps/drcpo_blank.png"


def _blank_png(side: int) -> bytes:
    """A ``side`` x ``side`` black 8-bit greyscale PNG (signature, IHDR, IDAT, IEND chunks)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    header = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)
    rows = b"".join(b"\0" + bytes(side) for _ in range(side))  # filter byte 0, then pixels
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows))
        + chunk(b"IEND", b"")
    )


def _write_points(path: Path, points: np.ndarray, where: str) -> None:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != len(POINT_COLUMNS):
        raise DataError(f"{where}: points must have shape (N, 5), got {points.shape}")
    if not np.isfinite(points).all():
        raise DataError(f"{where}: refusing to write NaN or infinite point values")
    atomic_write_bytes(path, np.ascontiguousarray(points, dtype="<f4").tobytes())


def check_version_name(version: Any) -> str:
    """``version`` if it is a plain directory name (``v1.0-mini``), else :class:`DataError`."""
    if not isinstance(version, str) or not FRAME_ID.fullmatch(version):
        raise DataError(
            f"nuScenes version {version!r} is not a plain name (letters, digits, '_', '-' and '.' "
            "not first; no path separators): it names the tables' directory inside the output"
        )
    return version


def write_nuscenes(
    root: str | os.PathLike,
    scenes: Iterable[SceneRecord],
    version: str = "v1.0-trainval",
    overwrite: bool = False,
    manifest: Mapping[str, Any] | None = None,
    progress: Callable[[SceneRecord], None] | None = None,
) -> Path:
    """Write ``scenes`` (produced one at a time) as a nuScenes layout under ``root``,
    atomically as a whole; ``manifest``: extra entries of the marker file (e.g. the
    parameters a synthetic data set was made with). ``version`` names the tables' directory
    inside ``root``: a plain name, never a path (refused before anything is written)."""
    check_version_name(version)

    def write(tmp: Path) -> None:
        writer = NuScenesWriter(tmp, version)
        for scene in scenes:
            writer.add_scene(scene)
            if progress is not None:
                progress(scene)
        writer.finish()
        marker = {
            **(manifest or {}),
            "format": NUSCENES_FORMAT,
            "format_version": NUSCENES_FORMAT_VERSION,
            "version": version,
        }
        (tmp / NUSCENES_MANIFEST).write_text(json.dumps(marker, indent=2) + "\n")

    return write_directory(root, write, NUSCENES_OUTPUT, overwrite)
