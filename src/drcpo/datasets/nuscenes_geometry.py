"""nuScenes' geometric conventions turned into ours: ``w, x, y, z`` quaternions, pose records
(child -> parent frame, e.g. sensor -> ego -> global) and global ``sample_annotation`` boxes
(``size = (w, l, h)``) as ``(M, 7)`` boxes in the sensor frame (``dx = l, dy = w, dz = h``,
heading = yaw of the box's x axis there), as the devkit and the frameworks' converters compute
them. Every check raises :class:`~drcpo.errors.DataError` naming the record at fault.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from drcpo.errors import DataError

__all__ = ["boxes_to_sensor", "pose_matrix", "rotation_matrix", "yaw_quaternion"]


def rotation_matrix(quaternion: Sequence[float], where: str = "rotation") -> np.ndarray:
    """``float64 (3, 3)`` rotation of a ``w, x, y, z`` quaternion (normalised first, as the
    devkit's pyquaternion does). :class:`DataError` naming ``where`` unless 4 finite numbers
    of non-zero norm."""
    q = _finite(quaternion, (4,), where)
    if np.linalg.norm(q) < 1e-9:
        raise DataError(f"{where}: quaternion {q.tolist()} has zero norm")
    return Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix()


def yaw_quaternion(yaw: np.ndarray) -> np.ndarray:
    """``float64 (..., 4)`` ``w, x, y, z`` quaternions of rotations by ``yaw`` (radians) about
    +z."""
    half = np.asarray(yaw, dtype=np.float64) / 2.0
    zero = np.zeros_like(half)
    return np.stack([np.cos(half), zero, zero, np.sin(half)], axis=-1)


def pose_matrix(translation: Sequence[float], rotation: Sequence[float], where: str) -> np.ndarray:
    """``float64 (4, 4)`` homogeneous transform of a pose record (child -> parent frame)."""
    matrix = np.eye(4)
    matrix[:3, :3] = rotation_matrix(rotation, f"{where}.rotation")
    matrix[:3, 3] = _finite(translation, (3,), f"{where}.translation")
    return matrix


def boxes_to_sensor(
    centres: np.ndarray, sizes_wlh: np.ndarray, rotations: np.ndarray, global_to_sensor: np.ndarray
) -> np.ndarray:
    """Global nuScenes boxes as ``(M, 7)`` boxes of our convention in the sensor frame.

    Args:
        centres: ``(M, 3)`` box centres, global frame, metres.
        sizes_wlh: ``(M, 3)`` width, length, height, metres.
        rotations: ``(M, 4)`` ``w, x, y, z`` quaternions, box -> global.
        global_to_sensor: ``(4, 4)`` transform global -> sensor.
    """
    count = len(centres)
    if count == 0:
        return np.zeros((0, 7))
    rotate = global_to_sensor[:3, :3]
    centre = centres @ rotate.T + global_to_sensor[:3, 3]
    box_to_global = Rotation.from_quat(np.asarray(rotations)[:, [1, 2, 3, 0]]).as_matrix()
    axis = np.einsum("ij,mj->mi", rotate, box_to_global[:, :, 0])  # the box's x axis
    heading = np.arctan2(axis[:, 1], axis[:, 0])
    return np.column_stack([centre, sizes_wlh[:, 1], sizes_wlh[:, 0], sizes_wlh[:, 2], heading])


def _finite(value: Any, shape: tuple[int, ...], where: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        array = None
    if array is None or array.shape != shape or not np.isfinite(array).all():
        raise DataError(f"{where}: expected {math.prod(shape)} finite numbers, got {value!r}")
    return array


def _quaternion(value: Any, where: str) -> np.ndarray:
    """A ``w, x, y, z`` quaternion normalised (:func:`rotation_matrix`'s checks)."""
    rotation_matrix(value, where)
    q = np.asarray(value, dtype=np.float64)
    return q / np.linalg.norm(q)
