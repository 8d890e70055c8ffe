"""KITTI object detection layout: calibration, coordinate conversions, labels, point clouds.

Camera boxes (``label_2``) are converted to LiDAR boxes exactly as OpenPCDet does
(``boxes3d_kitti_camera_to_lidar``), so our boxes agree with OpenPCDet's ``gt_boxes_lidar``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class Calibration:
    """A KITTI calibration: ``P2`` (3, 4), ``R0_rect`` (3, 3), ``Tr_velo_to_cam`` (3, 4).

    Matrices are kept in float32, as OpenPCDet reads them, so conversions agree with it bit for bit
    as far as numpy allows.
    """

    P2: np.ndarray
    R0_rect: np.ndarray
    Tr_velo_to_cam: np.ndarray

    def __post_init__(self) -> None:
        for name, shape in (("P2", (3, 4)), ("R0_rect", (3, 3)), ("Tr_velo_to_cam", (3, 4))):
            value = np.asarray(getattr(self, name), dtype=np.float32)
            if value.shape != shape:
                raise ValueError(f"Calibration.{name} must have shape {shape}, got {value.shape}")
            object.__setattr__(self, name, value)

    def lidar_to_rect(self, points: np.ndarray) -> np.ndarray:
        """LiDAR ``(N, 3+)`` to rectified camera coordinates ``(N, 3)``."""
        hom = np.hstack([np.asarray(points)[:, :3], np.ones((len(points), 1), np.float32)])
        return hom @ (self.Tr_velo_to_cam.T @ self.R0_rect.T)

    def rect_to_lidar(self, points_rect: np.ndarray) -> np.ndarray:
        """Rectified camera ``(N, 3)`` to LiDAR coordinates ``(N, 3)``."""
        r0 = np.eye(4, dtype=np.float32)
        r0[:3, :3] = self.R0_rect
        v2c = np.eye(4, dtype=np.float32)
        v2c[:3, :] = self.Tr_velo_to_cam
        hom = np.hstack([points_rect, np.ones((len(points_rect), 1), np.float32)])
        return (hom @ np.linalg.inv((r0 @ v2c).T))[:, :3]

    def rect_to_image(self, points_rect: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project rectified points ``(N, 3)`` with P2: pixels ``(N, 2)`` and depth ``(N,)``."""
        hom = np.hstack([points_rect, np.ones((len(points_rect), 1), np.float32)])
        projected = hom @ self.P2.T
        depth = projected[:, 2] - self.P2[2, 3]
        return projected[:, :2] / projected[:, 2:3], depth


def camera_boxes_to_lidar(boxes_camera: np.ndarray, calib: Calibration) -> np.ndarray:
    """KITTI camera boxes ``(M, 7)`` [x, y, z (bottom centre, rect), l, h, w, ry] to LiDAR boxes.

    Same arithmetic as OpenPCDet's ``boxes3d_kitti_camera_to_lidar``: the bottom centre moves to
    LiDAR coordinates and up by h / 2; ``heading = -(pi / 2 + ry)``.
    """
    boxes_camera = np.asarray(boxes_camera)
    xyz = calib.rect_to_lidar(boxes_camera[:, 0:3])
    length, height, width, ry = (boxes_camera[:, i : i + 1] for i in (3, 4, 5, 6))
    xyz[:, 2:3] += height / 2
    return np.concatenate([xyz, length, width, height, -(np.pi / 2 + ry)], axis=-1)


def lidar_boxes_to_camera(boxes_lidar: np.ndarray, calib: Calibration) -> np.ndarray:
    """Inverse of :func:`camera_boxes_to_lidar`: LiDAR boxes to KITTI camera boxes ``(M, 7)``."""
    boxes_lidar = np.asarray(boxes_lidar, dtype=np.float64)
    bottom = boxes_lidar[:, 0:3].copy()
    bottom[:, 2] -= boxes_lidar[:, 5] / 2
    xyz = calib.lidar_to_rect(bottom)
    length, width, height, heading = (boxes_lidar[:, i : i + 1] for i in (3, 4, 5, 6))
    return np.concatenate([xyz, length, height, width, -heading - np.pi / 2], axis=-1)
