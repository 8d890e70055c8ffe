"""Write frames in the KITTI object detection layout (the inverse of :mod:`drcpo.datasets.kitti`).

Every file is written to a temporary sibling and renamed into place
(:func:`drcpo.outputs.atomic_write_bytes`), so a reader never sees a half-written file. Labels
carry more decimals than KITTI's (2) for the 3D box, so a frame read back gives the boxes written
to well under 1e-4 m.

Layout written (``ROOT`` as OpenPCDet's ``data/kitti``)::

    ROOT/ImageSets/<split>.txt
    ROOT/training/velodyne/ID.bin     float32 (N, 4)
    ROOT/training/label_2/ID.txt      type trunc occ alpha x1 y1 x2 y2 h w l x y z ry
    ROOT/training/calib/ID.txt        P0 P1 P2 P3 R0_rect Tr_velo_to_cam Tr_imu_to_velo
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from drcpo.datasets.kitti import OCCLUSION_LEVELS, check_split_name
from drcpo.datasets.kitti_coordinates import DEFAULT_IMAGE_SHAPE, Calibration, lidar_boxes_to_camera
from drcpo.errors import DataError
from drcpo.geometry import rotation_matrix_z, wrap_angle
from drcpo.outputs import atomic_write_bytes

__all__ = [
    "CALIB_KEYS",
    "REFERENCE_CALIB",
    "calib_text",
    "calibration_matrices",
    "label_lines",
    "project_boxes",
    "reference_calibration",
    "write_calib",
    "write_frame",
    "write_image_sets",
    "write_labels",
    "write_points",
]

#: Calibration of KITTI training frame 000001 (a real HDL-64E + camera rig), all seven matrices.
REFERENCE_CALIB: dict[str, np.ndarray] = {
    "P0": np.array(
        [[721.5377, 0.0, 609.5593, 0.0], [0.0, 721.5377, 172.854, 0.0], [0.0, 0.0, 1.0, 0.0]]
    ),
    "P1": np.array(
        [[721.5377, 0.0, 609.5593, -387.5744], [0.0, 721.5377, 172.854, 0.0], [0.0, 0.0, 1.0, 0.0]]
    ),
    "P2": np.array(
        [
            [721.5377, 0.0, 609.5593, 44.85728],
            [0.0, 721.5377, 172.854, 0.2163791],
            [0.0, 0.0, 1.0, 0.002745884],
        ]
    ),
    "P3": np.array(
        [
            [721.5377, 0.0, 609.5593, -339.5242],
            [0.0, 721.5377, 172.854, 2.199936],
            [0.0, 0.0, 1.0, 0.002729905],
        ]
    ),
    "R0_rect": np.array(
        [
            [0.9999239, 0.00983776, -0.007445048],
            [-0.009869795, 0.9999421, -0.004278459],
            [0.007402527, 0.004351614, 0.9999631],
        ]
    ),
    "Tr_velo_to_cam": np.array(
        [
            [0.007533745, -0.9999714, -0.000616602, -0.004069766],
            [0.01480249, 0.0007280733, -0.9998902, -0.07631618],
            [0.9998621, 0.00752379, 0.01480755, -0.2717806],
        ]
    ),
    "Tr_imu_to_velo": np.array(
        [
            [0.9999976, 0.0007553071, -0.002035826, -0.8086759],
            [-0.0007854027, 0.9998898, -0.01482298, 0.3195559],
            [0.002024406, 0.01482454, 0.9998881, -0.7997231],
        ]
    ),
}
CALIB_KEYS: tuple[str, ...] = tuple(REFERENCE_CALIB)
_CALIB_SHAPES = {k: v.shape for k, v in REFERENCE_CALIB.items()}
_NEAR_PLANE = 0.1  # metres in front of the camera; nearer box samples do not project
_FACE_GRID = 9  # samples per box edge when measuring the projected box


def reference_calibration() -> Calibration:
    """:data:`REFERENCE_CALIB` as a :class:`Calibration`."""
    return Calibration(
        REFERENCE_CALIB["P2"], REFERENCE_CALIB["R0_rect"], REFERENCE_CALIB["Tr_velo_to_cam"]
    )


def calibration_matrices(
    calib: Calibration, others: Mapping[str, np.ndarray] | None = None
) -> dict[str, np.ndarray]:
    """All seven matrices of a calib file: P2, R0_rect and Tr_velo_to_cam from ``calib``, the
    rest (P0, P1, P3, Tr_imu_to_velo) from ``others`` or else :data:`REFERENCE_CALIB`.

    ``calib`` holds float32 matrices; where a float64 matrix in ``others`` (or the reference)
    rounds to the same float32 values, that one is written, so a KITTI file is reproduced
    digit for digit.
    """
    matrices = {**REFERENCE_CALIB, **(others or {})}
    for key in ("P2", "R0_rect", "Tr_velo_to_cam"):
        ours = getattr(calib, key)
        known = np.asarray(matrices[key], dtype=np.float64)
        if known.shape != ours.shape or not np.array_equal(known.astype(np.float32), ours):
            matrices[key] = ours
    return matrices


def write_points(path: str | os.PathLike, points: np.ndarray) -> Path:
    """Write ``float32 (N, C)`` points as a KITTI ``.bin`` (little-endian float32, row-major)."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise DataError(f"{path}: points must have shape (N, 3 + C), got {points.shape}")
    if not np.isfinite(points).all():
        raise DataError(f"{path}: refusing to write NaN or infinite point values")
    return atomic_write_bytes(path, np.ascontiguousarray(points, dtype="<f4").tobytes())


def calib_text(matrices: Mapping[str, np.ndarray]) -> str:
    """KITTI calib file text from the seven matrices (:data:`CALIB_KEYS`)."""
    lines = []
    for key in CALIB_KEYS:
        if key not in matrices:
            raise DataError(f"calibration matrix {key} missing (need {', '.join(CALIB_KEYS)})")
        value = np.asarray(matrices[key], dtype=np.float64)
        if value.shape != _CALIB_SHAPES[key] or not np.isfinite(value).all():
            raise DataError(
                f"calibration matrix {key} must be finite with shape {_CALIB_SHAPES[key]}, "
                f"got {value.shape}"
            )
        lines.append(f"{key}: " + " ".join(f"{v:.12e}" for v in value.ravel()))
    return "\n".join(lines) + "\n\n"


def write_calib(path: str | os.PathLike, matrices: Mapping[str, np.ndarray]) -> Path:
    return atomic_write_bytes(path, calib_text(matrices).encode())


def project_boxes(
    boxes: np.ndarray,
    calib: Calibration,
    image_shape: tuple[int, int] = DEFAULT_IMAGE_SHAPE,
) -> tuple[np.ndarray, np.ndarray]:
    """Image boxes and truncation of LiDAR boxes ``(M, 7)`` seen by camera P2.

    Each box's surface is sampled on a 9 x 9 grid per face (corners included); samples less than
    0.1 m in front of the camera do not project.

    Returns:
        bbox2d: ``float64 (M, 4)`` left, top, right, bottom in pixels: the bounds of the projected
            samples clipped to the image (``nan`` rows for boxes with no sample in front).
        truncation: ``float64 (M,)`` fraction of the samples outside the image or behind the
            near plane (0 inside the image, 1 entirely outside).
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    height, width = image_shape
    g = np.linspace(-0.5, 0.5, _FACE_GRID)
    unit = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    unit = unit[(np.abs(unit) == 0.5).any(axis=1)]
    local = unit[None] * boxes[:, None, 3:6]
    world = np.einsum("mij,mkj->mki", rotation_matrix_z(boxes[:, 6]), local) + boxes[:, None, :3]
    rect = calib.lidar_to_rect(world.reshape(-1, 3)).astype(np.float64)
    in_front = rect[:, 2] > _NEAR_PLANE
    safe = rect.copy()
    safe[~in_front, 2] = 1.0
    pixels, _ = calib.rect_to_image(safe)
    pixels = pixels.astype(np.float64)
    inside = in_front & (pixels[:, 0] >= 0) & (pixels[:, 0] < width)
    inside &= (pixels[:, 1] >= 0) & (pixels[:, 1] < height)
    shape = (len(boxes), len(unit))
    in_front, inside = in_front.reshape(shape), inside.reshape(shape)
    pixels = pixels.reshape(*shape, 2)
    low = np.where(in_front[..., None], pixels, np.inf).min(axis=1)
    high = np.where(in_front[..., None], pixels, -np.inf).max(axis=1)
    limit = np.array([width - 1, height - 1], dtype=np.float64)
    bbox = np.column_stack([np.clip(low, 0, limit), np.clip(high, 0, limit)])
    bbox[~in_front.any(axis=1)] = np.nan
    return bbox, 1.0 - inside.mean(axis=1)


def label_lines(
    boxes: np.ndarray,
    names: Sequence[str],
    calib: Calibration,
    occlusion: np.ndarray | None = None,
    truncation: np.ndarray | None = None,
    image_shape: tuple[int, int] = DEFAULT_IMAGE_SHAPE,
) -> list[str]:
    """KITTI ``label_2`` lines for LiDAR boxes ``(M, 7)`` (OpenPCDet convention).

    Camera boxes come from :func:`~drcpo.datasets.kitti_coordinates.lidar_boxes_to_camera`;
    alpha is ``ry - arctan2(x, z)`` of the box in the rectified camera frame; the 2D box and,
    unless given, the truncation come from :func:`project_boxes`. ``occlusion`` defaults to 3
    (unknown); given, each must be a KITTI level (0 to 3, or -1). Boxes entirely behind the
    camera get an empty 2D box at (0, 0). Every positive size is written so that it reads back
    positive (below a millimetre in exponent form), as the reader requires.
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    count = len(boxes)
    if len(names) != count:
        raise DataError(f"label_lines: {len(names)} names for {count} boxes")
    if not np.isfinite(boxes).all() or (boxes[:, 3:6] <= 0).any():
        raise DataError("label_lines: boxes must be finite with positive sizes")
    bbox, projected_truncation = project_boxes(boxes, calib, image_shape)
    bbox = np.nan_to_num(bbox, nan=0.0)
    truncation = projected_truncation if truncation is None else np.asarray(truncation, float)
    occlusion = np.full(count, 3) if occlusion is None else np.asarray(occlusion)
    if len(occlusion) != count or not np.isin(occlusion, OCCLUSION_LEVELS).all():
        raise DataError(
            f"label_lines: occlusion levels must be {count} of {OCCLUSION_LEVELS}, got "
            f"{sorted(set(np.asarray(occlusion).tolist()))}"
        )
    camera = lidar_boxes_to_camera(boxes, calib)
    ry = wrap_angle(camera[:, 6])
    alpha = wrap_angle(ry - np.arctan2(camera[:, 0], camera[:, 2]))
    lines = []
    for i in range(count):
        x, y, z, length, h, w, _ = camera[i]
        lines.append(
            f"{names[i]} {float(truncation[i]):.2f} {int(occlusion[i]):d} {alpha[i]:.2f} "
            f"{bbox[i, 0]:.2f} {bbox[i, 1]:.2f} {bbox[i, 2]:.2f} {bbox[i, 3]:.2f} "
            f"{_size(h)} {_size(w)} {_size(length)} {x:.6f} {y:.6f} {z:.6f} {ry[i]:.6f}"
        )
    return lines


def _size(value: float) -> str:
    """Six decimals (KITTI's files), or the shortest exact form where those would round a
    positive size to zero."""
    return f"{value:.6f}" if value >= 1e-3 else repr(float(value))


def write_labels(path: str | os.PathLike, lines: Sequence[str]) -> Path:
    return atomic_write_bytes(path, "".join(f"{line}\n" for line in lines).encode())


def write_image_sets(root: str | os.PathLike, splits: Mapping[str, Sequence[str]]) -> None:
    """Write ``ROOT/ImageSets/<split>.txt`` (one frame id per line) for each split; a split that
    is not a plain name is refused before anything is written."""
    for split in splits:
        check_split_name(split)
    for split, ids in splits.items():
        text = "".join(f"{frame_id}\n" for frame_id in ids)
        atomic_write_bytes(Path(root) / "ImageSets" / f"{split}.txt", text.encode())


def write_frame(
    root: str | os.PathLike,
    frame_id: str,
    points: np.ndarray,
    boxes: np.ndarray,
    names: Sequence[str],
    calib: Calibration,
    occlusion: np.ndarray | None = None,
    truncation: np.ndarray | None = None,
    image_shape: tuple[int, int] = DEFAULT_IMAGE_SHAPE,
    other_matrices: Mapping[str, np.ndarray] | None = None,
    directory: str = "training",
) -> None:
    """Write one frame's velodyne ``.bin``, ``label_2`` and ``calib`` files under ``ROOT``."""
    base = Path(root) / directory
    write_points(base / "velodyne" / f"{frame_id}.bin", points)
    lines = label_lines(boxes, names, calib, occlusion, truncation, image_shape)
    write_labels(base / "label_2" / f"{frame_id}.txt", lines)
    write_calib(base / "calib" / f"{frame_id}.txt", calibration_matrices(calib, other_matrices))
