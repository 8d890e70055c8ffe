"""Partition grids of object boxes (shared by the candidate index and iterative construction).

An object's box in canonical pose is cut into an even ``nx x ny x nz`` grid (along x, y, z).
Cell rule: a point's cell along an axis is ``floor((c + d/2) / d * n)`` clipped to ``[0, n - 1]``,
so a point on an inner cell boundary belongs to the upper cell and points on or beyond the box's
faces belong to the outermost cell. Cells are numbered ``(ix * ny + iy) * nz + iz``.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from drcpo.errors import ConfigError

__all__ = [
    "DEFAULT_GRIDS",
    "DEFAULT_MIRRORED",
    "FALLBACK_GRID",
    "Grid",
    "grid_for",
    "mirror_points",
    "num_partitions",
    "partition_counts",
    "partition_index",
]

Grid = tuple[int, int, int]

#: The paper's grids per class (along x, y, z).
DEFAULT_GRIDS: dict[str, Grid] = {
    "Car": (10, 4, 3),
    "Cyclist": (4, 2, 3),
    "Pedestrian": (2, 2, 3),
}
#: Grid of any class without its own entry.
FALLBACK_GRID: Grid = (4, 2, 3)
#: Classes mirrored across the x axis (y -> -y) before densities are measured.
DEFAULT_MIRRORED: tuple[str, ...] = ("Car", "Cyclist")


def grid_for(name: str, grids: Mapping[str, Grid] | None = None) -> Grid:
    """The partition grid of class ``name`` (``grids`` overrides the defaults)."""
    table = {**DEFAULT_GRIDS, **(grids or {})}
    grid = tuple(int(n) for n in table.get(name, table.get("default", FALLBACK_GRID)))
    if len(grid) != 3 or min(grid) < 1:
        raise ConfigError(
            f"partition grid for {name!r} must be three positive integers, got {grid}"
        )
    return grid  # type: ignore[return-value]


def num_partitions(grid: Grid) -> int:
    return int(grid[0] * grid[1] * grid[2])


def partition_index(points: np.ndarray, dims: np.ndarray, grid: Grid) -> np.ndarray:
    """Flat cell index ``int64 (N,)`` of canonical ``(N, 3+)`` points in a box of size ``dims``.

    Args:
        points: points in canonical pose, metres.
        dims: ``(3,)`` box size dx, dy, dz, metres (must be positive).
        grid: cells along x, y, z.
    """
    dims = np.asarray(dims, dtype=np.float64)
    counts = np.asarray(grid, dtype=np.int64)
    xyz = np.asarray(points)[:, :3].astype(np.float64)
    cell = np.floor((xyz + dims / 2.0) / dims * counts).astype(np.int64)
    np.clip(cell, 0, counts - 1, out=cell)
    return (cell[:, 0] * counts[1] + cell[:, 1]) * counts[2] + cell[:, 2]


def partition_counts(points: np.ndarray, dims: np.ndarray, grid: Grid) -> np.ndarray:
    """Points per cell ``int64 (P,)`` of canonical points in a box of size ``dims``."""
    return np.bincount(partition_index(points, dims, grid), minlength=num_partitions(grid))


def mirror_points(points: np.ndarray) -> np.ndarray:
    """The points plus their mirror image across the x axis (y -> -y): ``(2N, C)``."""
    points = np.asarray(points)
    mirrored = points.copy()
    mirrored[:, 1] = -mirrored[:, 1]
    return np.concatenate([points, mirrored], axis=0)
