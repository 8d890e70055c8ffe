"""KITTI object detection layout: its files read (calibration, labels, point clouds, splits, road
planes, image sizes) and whole frames.

Layout read here (``ROOT`` as OpenPCDet's ``data/kitti``)::

    ROOT/ImageSets/{train,val,test,...}.txt     one frame id per line
    ROOT/training/velodyne/ID.bin               float32 (N, 4) x, y, z, intensity
    ROOT/training/label_2/ID.txt                camera-frame labels (DontCare ignored)
    ROOT/training/calib/ID.txt                  P2, R0_rect, Tr_velo_to_cam
    ROOT/training/planes/ID.txt                 optional road plane (rectified camera frame)
    ROOT/training/image_2/ID.png                optional; only its size is read (FOV filter)

The ``test`` split lives in ``ROOT/testing`` instead, as in OpenPCDet.

Camera boxes (``label_2``) are converted to LiDAR boxes exactly as OpenPCDet does
(``boxes3d_kitti_camera_to_lidar``), so our boxes agree with OpenPCDet's ``gt_boxes_lidar``; the
calibration and its conversions are :mod:`~drcpo.datasets.kitti_coordinates`'.
Every reader raises :class:`~drcpo.errors.DataError` naming the file (and line) on bad input.
"""

from __future__ import annotations

import math
import os
import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from drcpo.datasets.kitti_coordinates import DEFAULT_IMAGE_SHAPE, Calibration
from drcpo.errors import DataError
from drcpo.frame import Frame, FrameSequence

__all__ = [
    "DONT_CARE",
    "FRAME_ID",
    "KittiDataset",
    "KittiLabels",
    "check_frame_id",
    "kitti_difficulty",
    "read_calib",
    "read_image_shape",
    "read_labels",
    "read_plane",
    "read_points",
    "read_split",
    "split_directory",
]

DONT_CARE = "DontCare"


# Point clouds -------------------------------------------------------------------------------
def read_points(path: str | os.PathLike, num_features: int = 4) -> np.ndarray:
    """Read a KITTI ``velodyne/*.bin`` file: ``float32 (N, num_features)`` (x, y, z, intensity).

    Raises :class:`DataError` naming the file when it is missing, its size is not a multiple of
    ``4 * num_features`` bytes, or a value is NaN or infinite.
    """
    path = Path(path)
    row_bytes = 4 * num_features
    try:
        # Read as bytes: np.fromfile with a float32 dtype drops a partial last value silently,
        # so a file 1-3 bytes past a whole point would pass a check on the value count.
        raw = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise DataError(f"{path}: cannot read point cloud ({exc.strerror or exc})") from exc
    if raw.size % row_bytes:
        raise DataError(
            f"{path}: size {raw.size} bytes is not a multiple of {row_bytes} "
            f"({num_features} float32 values per point); truncated or not a KITTI .bin"
        )
    points = raw.view("<f4").reshape(-1, num_features).astype(np.float32, copy=False)
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        bad = int(np.flatnonzero(~finite)[0])
        raise DataError(
            f"{path}: point {bad} holds a NaN or infinite value "
            f"({int((~finite).sum())} such points)"
        )
    return points


# Calibration --------------------------------------------------------------------------------
_CALIB_FIELDS = {"P2": (3, 4), "R0_rect": (3, 3), "Tr_velo_to_cam": (3, 4)}
#: Fields whose 3 x 3 part is inverted (LiDAR <-> camera). KITTI's are rotations (condition
#: number 1); past this bound the float32 inverse keeps hardly a digit, so the file is wrong.
_INVERTED_FIELDS = ("R0_rect", "Tr_velo_to_cam")
_MAX_CONDITION = 1e6


def read_calib(path: str | os.PathLike) -> Calibration:
    """Read a KITTI ``calib/*.txt`` file (fields ``P2``, ``R0_rect``, ``Tr_velo_to_cam``).

    Fields are found by name, so their order does not matter; other fields are ignored.
    Raises :class:`DataError` naming the file (and line or field) when it is missing, a
    required field is absent, a value is not a finite number, or ``R0_rect`` or the rotation
    part of ``Tr_velo_to_cam`` is singular (e.g. all zeros), which makes LiDAR boxes undefined.
    """
    path = Path(path)
    lines = _read_lines(path, "calibration")
    values: dict[str, np.ndarray] = {}
    line_of: dict[str, int] = {}
    for number, line in enumerate(lines, start=1):
        key, sep, rest = line.partition(":")
        key = key.strip()
        if not sep or key not in _CALIB_FIELDS:
            continue
        shape = _CALIB_FIELDS[key]
        numbers = _parse_floats(rest.split(), path, number)
        if numbers.size != shape[0] * shape[1] or not np.isfinite(numbers).all():
            raise DataError(
                f"{path}:{number}: {key} needs {shape[0] * shape[1]} finite numbers, "
                f"got {rest.split()!r}"
            )
        values[key] = numbers.astype(np.float32).reshape(shape)
        line_of[key] = number
    missing = [key for key in _CALIB_FIELDS if key not in values]
    if missing:
        raise DataError(f"{path}: calibration field(s) {', '.join(missing)} missing")
    for key in _INVERTED_FIELDS:
        condition = _condition_number(values[key][:, :3])
        if condition > _MAX_CONDITION:
            raise DataError(
                f"{path}:{line_of[key]}: {key} is singular (condition number {condition:.3g}): "
                "its 3 x 3 part must be a rotation for LiDAR <-> camera conversions"
            )
    return Calibration(values["P2"], values["R0_rect"], values["Tr_velo_to_cam"])


def _condition_number(matrix: np.ndarray) -> float:
    """Ratio of the largest to the smallest singular value of a finite square matrix (inf when
    singular, including all zeros, where numpy's ``cond`` would give NaN)."""
    singular = np.linalg.svd(matrix.astype(np.float64), compute_uv=False)
    return float(singular[0] / singular[-1]) if singular[-1] > 0 else math.inf


# Labels -------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class KittiLabels:
    """The labelled objects of one frame (``DontCare`` rows dropped), in file order.

    Attributes (M objects):
        names: ``(M,)`` class names.
        truncation: ``float64 (M,)`` 0 (inside the image) .. 1 (leaving it).
        occlusion: ``int8 (M,)`` 0 visible, 1 partly, 2 largely occluded, 3 unknown.
        alpha: ``float64 (M,)`` observation angle, radians.
        bbox2d: ``float32 (M, 4)`` image box left, top, right, bottom in pixels.
        dimensions: ``float64 (M, 3)`` length, height, width in metres (OpenPCDet's lhw order).
        location: ``float32 (M, 3)`` bottom centre in rectified camera coordinates, metres.
        rotation_y: ``float64 (M,)`` yaw about the camera's y axis, radians.
        score: ``float64 (M,)`` detection score (-1 for ground truth).
        difficulty: ``int8 (M,)`` 0 easy, 1 moderate, 2 hard, -1 unknown (see
            :func:`kitti_difficulty`).
        lines: ``int64 (M,)`` 1-based line of each object in its file, for error messages.

    The dtypes follow OpenPCDet's reader, so derived LiDAR boxes agree with it bit for bit.
    """

    names: np.ndarray
    truncation: np.ndarray
    occlusion: np.ndarray
    alpha: np.ndarray
    bbox2d: np.ndarray
    dimensions: np.ndarray
    location: np.ndarray
    rotation_y: np.ndarray
    score: np.ndarray
    difficulty: np.ndarray
    lines: np.ndarray

    def __len__(self) -> int:
        return len(self.names)

    @property
    def camera_boxes(self) -> np.ndarray:
        """``float64 (M, 7)`` KITTI camera boxes x, y, z (bottom centre), l, h, w, ry."""
        return np.column_stack([self.location, self.dimensions, self.rotation_y]).reshape(-1, 7)

    def lidar_boxes(self, calib: Calibration) -> np.ndarray:
        """``float64 (M, 7)`` LiDAR boxes (centre, dx, dy, dz, heading) as OpenPCDet makes them.

        Same formula as :func:`camera_boxes_to_lidar`, kept in OpenPCDet's precision: the
        float32 location goes through the float32 calibration and the half height is added in
        float32, which is what its ``gt_boxes_lidar`` holds.
        """
        if len(self) == 0:
            return np.zeros((0, 7))
        xyz = calib.rect_to_lidar(self.location)
        length, height, width = (self.dimensions[:, i : i + 1] for i in range(3))
        xyz[:, 2] += height[:, 0] / 2  # float64 sum rounded into float32, as OpenPCDet
        heading = -(np.pi / 2 + self.rotation_y[:, None])
        return np.concatenate([xyz, length, width, height, heading], axis=1).astype(np.float64)


#: KITTI's occlusion levels: 0 visible, 1 partly, 2 largely occluded, 3 unknown; -1 in results.
OCCLUSION_LEVELS = (-1, 0, 1, 2, 3)
_LABEL_FIELDS = 15  # type, truncation, occlusion, alpha, bbox (4), h, w, l, x, y, z, ry


def read_labels(path: str | os.PathLike) -> KittiLabels:
    """Read a KITTI ``label_2/*.txt`` file; ``DontCare`` rows and blank lines are skipped.

    Raises :class:`DataError` naming the file and line for a line with the wrong number of
    fields, a non-numeric or non-finite value, a non-positive box size, or an occlusion that is
    not one of :data:`OCCLUSION_LEVELS`.
    """
    path = Path(path)
    rows: list[tuple[str, np.ndarray, int]] = []
    for number, line in enumerate(_read_lines(path, "label"), start=1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) not in (_LABEL_FIELDS, _LABEL_FIELDS + 1):
            raise DataError(
                f"{path}:{number}: expected {_LABEL_FIELDS} or {_LABEL_FIELDS + 1} fields "
                f"(type, truncated, occluded, alpha, bbox x4, h w l, x y z, ry[, score]), "
                f"got {len(fields)}: {line.strip()!r}"
            )
        name = fields[0]
        if name == DONT_CARE:
            continue
        numbers = _parse_floats(fields[1:], path, number)
        if not np.isfinite(numbers).all():
            raise DataError(f"{path}:{number}: NaN or infinite value in {line.strip()!r}")
        if (numbers[7:10] <= 0).any():
            raise DataError(
                f"{path}:{number}: {name} has a non-positive size h, w, l = {numbers[7:10]}"
            )
        if numbers[1] not in OCCLUSION_LEVELS:
            raise DataError(
                f"{path}:{number}: {name} has occlusion {fields[2]!r}; KITTI's levels are "
                f"{', '.join(str(v) for v in OCCLUSION_LEVELS)}"
            )
        rows.append((name, numbers, number))
    return _labels_from_rows(rows)


def _labels_from_rows(rows: list[tuple[str, np.ndarray, int]]) -> KittiLabels:
    numbers = _LABEL_FIELDS - 1  # all but the type; an optional score follows
    table = np.array([r[1][:numbers] for r in rows], dtype=np.float64).reshape(-1, numbers)
    truncation, occlusion = table[:, 0], table[:, 1]
    bbox2d = table[:, 3:7].astype(np.float32)
    h, w, length = table[:, 7], table[:, 8], table[:, 9]
    score = np.array([r[1][numbers] if len(r[1]) > numbers else -1.0 for r in rows])
    return KittiLabels(
        names=np.array([r[0] for r in rows], dtype=str),
        truncation=truncation,
        occlusion=occlusion.astype(np.int8),
        alpha=table[:, 2],
        bbox2d=bbox2d,
        dimensions=np.column_stack([length, h, w]),
        location=table[:, 10:13].astype(np.float32),
        rotation_y=table[:, 13],
        score=score.astype(np.float64),
        difficulty=kitti_difficulty(bbox2d, occlusion, truncation),
        lines=np.array([r[2] for r in rows], dtype=np.int64),
    )


# KITTI difficulty thresholds per level: minimum 2D box height (pixels), maximum occlusion level,
# maximum truncation (KITTI devkit, evaluate_object.cpp).
_MIN_HEIGHT = (40.0, 25.0, 25.0)
_MAX_OCCLUSION = (0, 1, 2)
_MAX_TRUNCATION = (0.15, 0.3, 0.5)


def kitti_difficulty(
    bbox2d: np.ndarray,
    occlusion: np.ndarray,
    truncation: np.ndarray,
    convention: Literal["openpcdet", "devkit"] = "openpcdet",
) -> np.ndarray:
    """KITTI difficulty ``int8 (M,)``: 0 easy, 1 moderate, 2 hard, -1 unknown.

    Args:
        bbox2d: ``(M, 4)`` image boxes left, top, right, bottom (pixels).
        occlusion: ``(M,)`` occlusion levels 0..3.
        truncation: ``(M,)`` truncation 0..1.
        convention: ``"openpcdet"`` measures the box height as ``bottom - top + 1`` (OpenPCDet's
            ``get_kitti_obj_level``, whose levels its infos and databases store);
            ``"devkit"`` as ``bottom - top`` (the KITTI devkit's evaluation).

    An object gets the easiest level whose height is at least (40, 25, 25) pixels, occlusion at
    most (0, 1, 2) and truncation at most (0.15, 0.3, 0.5); otherwise -1.
    """
    # float32 boxes widened to float64, as OpenPCDet computes the height
    bbox2d = np.asarray(bbox2d, dtype=np.float32).astype(np.float64).reshape(-1, 4)
    height = bbox2d[:, 3] - bbox2d[:, 1]
    if convention == "openpcdet":
        height = height + 1.0
    elif convention != "devkit":
        raise ValueError(f"convention must be 'openpcdet' or 'devkit', got {convention!r}")
    occlusion = np.asarray(occlusion, dtype=np.float64)
    truncation = np.asarray(truncation, dtype=np.float64)
    out = np.full(len(bbox2d), -1, dtype=np.int8)
    for level in reversed(range(3)):  # easiest level last, so it wins
        fits = (
            (height >= _MIN_HEIGHT[level])
            & (occlusion <= _MAX_OCCLUSION[level])
            & (truncation <= _MAX_TRUNCATION[level])
        )
        out[fits] = level
    return out


# Splits, planes, images ---------------------------------------------------------------------
def read_split(root: str | os.PathLike, split: str) -> list[str]:
    """Frame ids of ``root/ImageSets/<split>.txt`` in file order.

    Raises :class:`DataError` listing the available splits when ``split`` is unknown, naming
    the split when it is not a plain name (a path would reach outside ``ImageSets``), and naming
    both lines when an id is listed twice (its frame would be augmented or stored twice).
    """
    check_split_name(split)
    image_sets = Path(root) / "ImageSets"
    path = image_sets / f"{split}.txt"
    if not path.is_file():
        available = sorted(p.stem for p in image_sets.glob("*.txt")) if image_sets.is_dir() else []
        listing = ", ".join(available) if available else f"none: no {image_sets}/*.txt"
        raise DataError(f"{path}: unknown split {split!r} (available: {listing})")
    ids: dict[str, int] = {}
    for number, line in enumerate(_read_lines(path, "split"), start=1):
        if line.strip():
            frame_id = check_frame_id(line.strip(), f"{path}:{number}")
            if frame_id in ids:
                raise DataError(
                    f"{path}:{number}: frame id {frame_id!r} listed twice (first on line "
                    f"{ids[frame_id]})"
                )
            ids[frame_id] = number
    return list(ids)


# A frame id names files (velodyne/ID.bin, label_2/ID.txt, ...): letters, digits, "_", "-", "."
# (not first), never a path separator or "..", so no id can reach outside its directory.
FRAME_ID = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]*")


def check_frame_id(frame_id: Any, where: str) -> str:
    """``frame_id`` if it is a safe frame id, else :class:`DataError` naming ``where``."""
    if not isinstance(frame_id, str) or not FRAME_ID.fullmatch(frame_id):
        raise DataError(
            f"{where}: {frame_id!r} is not a frame id (letters, digits, '_', '-' and '.' "
            "not first; no path separators)"
        )
    return frame_id


def check_split_name(split: Any) -> str:
    """``split`` if it is a plain split name (as a frame id: no path separators, no ``..``),
    else :class:`DataError`: a split names ``ImageSets/<split>.txt`` and nothing else."""
    if not isinstance(split, str) or not FRAME_ID.fullmatch(split):
        raise DataError(
            f"split {split!r} is not a split name (letters, digits, '_', '-' and '.' not first; "
            "no path separators): give the name of a file in ImageSets/, not its path"
        )
    return split


def split_directory(root: str | os.PathLike, split: str) -> Path:
    """``root/testing`` for the ``test`` split, else ``root/training`` (OpenPCDet's rule)."""
    return Path(root) / ("testing" if split == "test" else "training")


def read_plane(path: str | os.PathLike) -> np.ndarray:
    """Read a KITTI road plane ``planes/*.txt``: ``float64 (4,)`` a, b, c, d in rect. camera frame.

    As OpenPCDet: the coefficients on the fourth line, flipped so the normal points up (negative
    camera y) and scaled to a unit normal. The plane is ``a x + b y + c z + d = 0``.
    """
    path = Path(path)
    lines = _read_lines(path, "road plane")
    if len(lines) < 4:
        raise DataError(f"{path}: expected the plane coefficients on line 4, file has {len(lines)}")
    plane = _parse_floats(lines[3].split(), path, 4)
    norm = np.linalg.norm(plane[:3]) if plane.size == 4 else 0.0
    if plane.size != 4 or not np.isfinite(plane).all() or norm == 0:
        raise DataError(f"{path}:4: expected 4 finite coefficients a b c d, got {lines[3]!r}")
    if abs(plane[1]) < 1e-9 * norm:  # b = 0: no height anywhere on it (y points down)
        raise DataError(
            f"{path}:4: the road plane {lines[3].strip()!r} is vertical (b = 0): boxes cannot "
            "be put on it"
        )
    if plane[1] > 0:
        plane = -plane
    return plane / norm


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def read_image_shape(path: str | os.PathLike) -> tuple[int, int]:
    """``(height, width)`` of a PNG image, read from its header (the pixels are not decoded)."""
    path = Path(path)
    try:
        with path.open("rb") as file:
            head = file.read(24)
    except OSError as exc:
        raise DataError(f"{path}: cannot read image ({exc.strerror or exc})") from exc
    if len(head) < 24 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise DataError(f"{path}: not a PNG image")
    width, height = struct.unpack(">II", head[16:24])
    return int(height), int(width)


# Whole frames -------------------------------------------------------------------------------
class KittiDataset(FrameSequence):
    """Frames of one KITTI split: ``len(ds)``, ``ds[i]``, ``ds.frame(frame_id)``, iteration.

    Each :class:`Frame` holds the full point cloud (not field-of-view filtered), the LiDAR boxes
    and names of the non-``DontCare`` labels in file order, and metadata: ``frame_id``,
    ``calib``, ``plane`` (or ``None``), ``image_shape``, ``labels`` (:class:`KittiLabels`),
    ``difficulty``, ``occlusion``, ``truncation``. Frames without a label file (the ``test``
    split) have no boxes.
    """

    def __init__(self, root: str | os.PathLike, split: str = "train", num_features: int = 4):
        self.root = Path(root)
        self.split = split
        self.num_features = num_features
        self.directory = split_directory(self.root, split)
        if not self.directory.is_dir():
            raise DataError(f"{self.directory}: KITTI directory missing (split {split!r})")
        self.frame_ids = read_split(self.root, split)

    def path(self, kind: str, frame_id: str) -> Path:
        """Path of one file: ``kind`` is velodyne, label_2, calib, planes or image_2."""
        suffix = {"velodyne": ".bin", "image_2": ".png"}.get(kind, ".txt")
        return self.directory / kind / f"{frame_id}{suffix}"

    def calib(self, frame_id: str) -> Calibration:
        return read_calib(self.path("calib", frame_id))

    def labels(self, frame_id: str) -> KittiLabels | None:
        """The frame's labels, or ``None`` for a split without ``label_2`` (``test``)."""
        path = self.path("label_2", frame_id)
        if not path.parent.is_dir() and self.split == "test":
            return None
        return read_labels(path)

    def points(self, frame_id: str) -> np.ndarray:
        return read_points(self.path("velodyne", frame_id), self.num_features)

    def image_shape(self, frame_id: str) -> tuple[int, int]:
        """``(height, width)`` from ``image_2`` when present, else :data:`DEFAULT_IMAGE_SHAPE`."""
        path = self.path("image_2", frame_id)
        return read_image_shape(path) if path.is_file() else DEFAULT_IMAGE_SHAPE

    def plane(self, frame_id: str) -> np.ndarray | None:
        path = self.path("planes", frame_id)
        return read_plane(path) if path.is_file() else None

    def frame(self, frame_id: str) -> Frame:
        calib = self.calib(frame_id)
        labels = self.labels(frame_id)
        metadata = {
            "frame_id": frame_id,
            "calib": calib,
            "plane": self.plane(frame_id),
            "image_shape": self.image_shape(frame_id),
            "labels": labels,
        }
        if labels is None:
            return Frame(self.points(frame_id), metadata=metadata)
        metadata.update(
            difficulty=labels.difficulty, occlusion=labels.occlusion, truncation=labels.truncation
        )
        return Frame(self.points(frame_id), labels.lidar_boxes(calib), labels.names, metadata)


# Helpers ------------------------------------------------------------------------------------
def _read_lines(path: Path, what: str) -> list[str]:
    try:
        return path.read_text().splitlines()
    except FileNotFoundError:
        raise DataError(f"{path}: {what} file missing") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read {what} file ({exc})") from exc


def _parse_floats(tokens: Sequence[str], path: Path, line: int) -> np.ndarray:
    try:
        return np.array([float(token) for token in tokens], dtype=np.float64)
    except ValueError as exc:
        raise DataError(f"{path}:{line}: not a number ({exc})") from None
