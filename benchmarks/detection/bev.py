"""Bird's-eye-view features of a LiDAR point cloud on a fixed grid (numpy, no torch).

The grid covers KITTI's camera-view range (x 0 to 70.4 m, y -40 to 40 m, z -3 to 1 m in the
LiDAR frame) in 0.4 m cells. Channels per cell: the log point count in each of 8 height slices
of 0.5 m, the highest point's height above the bottom of the range (divided by its 4 m), and the
mean intensity; empty cells are 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Grid:
    """The BEV grid: ranges in metres (LiDAR frame), ``cell`` metres square, ``slices`` in z."""

    x_range: tuple[float, float] = (0.0, 70.4)
    y_range: tuple[float, float] = (-40.0, 40.0)
    z_range: tuple[float, float] = (-3.0, 1.0)
    cell: float = 0.4
    slices: int = 8

    @property
    def shape(self) -> tuple[int, int]:
        """``(ny, nx)``: rows run along y, columns along x."""
        ny = round((self.y_range[1] - self.y_range[0]) / self.cell)
        nx = round((self.x_range[1] - self.x_range[0]) / self.cell)
        return ny, nx

    @property
    def channels(self) -> int:
        return self.slices + 2

    def cells(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Row, column and height slice of points ``(N, 3)``, and which lie inside the grid."""
        ny, nx = self.shape
        col = np.floor((xyz[:, 0] - self.x_range[0]) / self.cell).astype(np.int64)
        row = np.floor((xyz[:, 1] - self.y_range[0]) / self.cell).astype(np.int64)
        depth = (self.z_range[1] - self.z_range[0]) / self.slices
        level = np.floor((xyz[:, 2] - self.z_range[0]) / depth).astype(np.int64)
        inside = (col >= 0) & (col < nx) & (row >= 0) & (row < ny)
        inside &= (level >= 0) & (level < self.slices)
        return row, col, level, inside


def bev_features(points: np.ndarray, grid: Grid | None = None) -> np.ndarray:
    """``float32 (C, ny, nx)`` features (see the module docstring) of points ``(N, 4)``
    (x, y, z in metres, intensity); points outside the grid's x, y and z ranges are ignored."""
    grid = grid or Grid()
    points = np.asarray(points, dtype=np.float32)
    ny, nx = grid.shape
    row, col, level, inside = grid.cells(points[:, :3].astype(np.float64))
    row, col, level = row[inside], col[inside], level[inside]
    z, intensity = points[inside, 2], points[inside, 3]
    cell = row * nx + col
    counts = np.bincount(level * (ny * nx) + cell, minlength=grid.slices * ny * nx)
    per_cell = counts.reshape(grid.slices, -1).sum(axis=0)
    top = np.full(ny * nx, -np.inf, dtype=np.float32)
    np.maximum.at(top, cell, z)
    height = np.where(
        per_cell > 0, (top - grid.z_range[0]) / (grid.z_range[1] - grid.z_range[0]), 0
    )
    total = np.bincount(cell, weights=intensity, minlength=ny * nx)
    mean_intensity = total / np.maximum(per_cell, 1)
    features = np.concatenate(
        [np.log1p(counts).reshape(grid.slices, -1), height[None], mean_intensity[None]]
    )
    return features.reshape(grid.channels, ny, nx).astype(np.float32)
