"""KITTI's coordinate frames and the calibration linking them: LiDAR, rectified camera, image.

:class:`Calibration` holds a frame's ``P2``, ``R0_rect`` and ``Tr_velo_to_cam`` (read by
:func:`drcpo.datasets.kitti.read_calib`) and converts points between the frames; boxes move
between KITTI's camera labels and LiDAR boxes (:func:`camera_boxes_to_lidar`,
:func:`lidar_boxes_to_camera`) exactly as OpenPCDet's ``boxes3d_kitti_camera_to_lidar`` does, so
our boxes agree with its ``gt_boxes_lidar``; :func:`fov_mask` is the camera's field of view, as
its ``get_fov_flag``. All in float32 as OpenPCDet computes them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "DEFAULT_IMAGE_SHAPE",
    "Calibration",
    "camera_boxes_to_lidar",
    "fov_mask",
    "lidar_boxes_to_camera",
]

DEFAULT_IMAGE_SHAPE = (375, 1242)
"""``(height, width)`` in pixels of most KITTI images; used when a frame's image is absent."""
#: Rows per matrix product: below the size at which OpenBLAS starts its worker threads, which
#: then keep spinning on the other cores after the call (where DR.CPO's second thread works;
#: docs/measurements.md). Each row is computed as in one product over all rows.
_PRODUCT_ROWS = 8192


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
        return _product(hom, self.Tr_velo_to_cam.T @ self.R0_rect.T)

    def rect_to_lidar(self, points_rect: np.ndarray) -> np.ndarray:
        """Rectified camera ``(N, 3)`` to LiDAR coordinates ``(N, 3)``."""
        r0 = np.eye(4, dtype=np.float32)
        r0[:3, :3] = self.R0_rect
        v2c = np.eye(4, dtype=np.float32)
        v2c[:3, :] = self.Tr_velo_to_cam
        hom = np.hstack([points_rect, np.ones((len(points_rect), 1), np.float32)])
        return _product(hom, np.linalg.inv((r0 @ v2c).T))[:, :3]

    def rect_to_image(self, points_rect: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project rectified points ``(N, 3)`` with P2: pixels ``(N, 2)`` and depth ``(N,)``."""
        hom = np.hstack([points_rect, np.ones((len(points_rect), 1), np.float32)])
        projected = _product(hom, self.P2.T)
        depth = projected[:, 2] - self.P2[2, 3]
        return projected[:, :2] / projected[:, 2:3], depth


def _product(rows: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """``rows @ matrix`` in blocks of :data:`_PRODUCT_ROWS` rows (the same values)."""
    if len(rows) <= _PRODUCT_ROWS:
        return rows @ matrix
    out = np.empty((len(rows), matrix.shape[1]), dtype=np.result_type(rows, matrix))
    for start in range(0, len(rows), _PRODUCT_ROWS):
        block = slice(start, start + _PRODUCT_ROWS)
        np.matmul(rows[block], matrix, out=out[block])
    return out


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


def fov_mask(
    points: np.ndarray,
    calib: Calibration,
    image_shape: tuple[int, int] = DEFAULT_IMAGE_SHAPE,
) -> np.ndarray:
    """Which points the camera P2 sees: ``bool (N,)``.

    Args:
        points: ``(N, 3+)`` LiDAR points, metres.
        calib: the frame's calibration.
        image_shape: ``(height, width)`` of the frame's image in pixels; KITTI images vary
            slightly (e.g. 370 x 1224), :data:`DEFAULT_IMAGE_SHAPE` is the common 375 x 1242.

    Same semantics and float32 arithmetic as OpenPCDet's ``get_fov_flag``: a point is kept when
    its projection lies in ``[0, width) x [0, height)`` and its depth is >= 0. Like OpenPCDet,
    the pixel coordinates divide by the rectified depth (not the projected one).
    """
    rect = calib.lidar_to_rect(np.asarray(points, dtype=np.float32))
    hom = np.hstack([rect, np.ones((len(rect), 1), np.float32)])
    projected = _product(hom, calib.P2.T)
    depth = projected[:, 2] - calib.P2[2, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = projected[:, 0] / rect[:, 2]
        v = projected[:, 1] / rect[:, 2]
    height, width = image_shape
    return (u >= 0) & (u < width) & (v >= 0) & (v < height) & (depth >= 0)
