"""Partition grids of object boxes (shared by the candidate index and iterative construction).

An object's box in canonical pose is cut into an even ``nx x ny x nz`` grid (along x, y, z).
The cell rule is :func:`cell_of` (one axis) and :func:`flat_cell` (the cell number); every
partition count in drcpo (this module, the candidate index, iterative construction) calls them.
"""

from __future__ import annotations

from collections.abc import Mapping

import numba as nb
import numpy as np

from drcpo.errors import ConfigError

__all__ = [
    "DEFAULT_GRIDS",
    "DEFAULT_MIRRORED",
    "FALLBACK_GRID",
    "NUSCENES_MIRRORED",
    "Grid",
    "grid_for",
    "mirror_points",
    "num_partitions",
    "partition_counts",
    "partition_index",
]

Grid = tuple[int, int, int]

#: Grids per class (cells along x = length, y = width, z = height): the paper's for KITTI's
#: classes, and for nuScenes' ten (lower-case names) cells of about the paper's car cell
#: (0.4-0.6 m along a 4-5 m x 1.9 m x 1.7 m car) on the class's typical size: the long
#: vehicles (truck ~7 m, construction_vehicle ~6.5 m, bus and trailer ~11-12 m, all 2.5-3 m
#: wide and about 3 m tall) get more cells along their length and one more in height;
#: two-wheelers and pedestrians the paper's Cyclist and Pedestrian grids; a barrier (about
#: 2.5 m long, 0.5 m thick, 1 m tall) is split along its length only; a traffic cone
#: (0.4 m x 0.4 m x 1 m) into a lower and an upper half.
DEFAULT_GRIDS: dict[str, Grid] = {
    "Car": (10, 4, 3),
    "Cyclist": (4, 2, 3),
    "Pedestrian": (2, 2, 3),
    "car": (10, 4, 3),
    "truck": (14, 4, 4),
    "construction_vehicle": (12, 4, 4),
    "bus": (20, 4, 4),
    "trailer": (20, 4, 4),
    "barrier": (4, 1, 2),
    "motorcycle": (4, 2, 3),
    "bicycle": (4, 2, 3),
    "pedestrian": (2, 2, 3),
    "traffic_cone": (1, 1, 2),
}
#: Grid of any class without its own entry.
FALLBACK_GRID: Grid = (4, 2, 3)
#: Classes mirrored across the x axis (y -> -y) before densities are measured (the paper's;
#: the config's default ``drcpo.construction.mirror``).
DEFAULT_MIRRORED: tuple[str, ...] = ("Car", "Cyclist")
#: The nuScenes classes to mirror (the ``nuscenes`` preset's ``drcpo.construction.mirror``):
#: those whose left and right sides look alike, vehicles and two-wheelers, as the paper's Car
#: and Cyclist. Not pedestrians (as the paper: a walking person is not left-right symmetric),
#: nor barriers and traffic cones (thin or small: the sensor sees one face, and a mirror image
#: would put points inside the object, not on its far side).
NUSCENES_MIRRORED: tuple[str, ...] = (
    "car",
    "truck",
    "construction_vehicle",
    "bus",
    "trailer",
    "motorcycle",
    "bicycle",
)


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


@nb.njit(cache=True, nogil=True, inline="always")
def cell_of(value, size, count):  # pragma: no cover - numba
    """THE cell rule along one axis: the cell ``int64`` of canonical coordinate ``value`` in a
    box of size ``size`` cut into ``count`` cells, ``floor((value + size/2) / size * count)``
    in float64, clipped to ``[0, count - 1]``.

    A point on an inner cell boundary belongs to the upper cell, points on or beyond the box's
    faces to the outermost cell. NaN, and values whose floor lies outside int64 (far beyond
    the box, never in valid data), convert to int64's minimum as numpy's cast does on x86, and
    so land in cell 0. Kernels of other modules inline this rule, and numba's disk cache only
    notices changes to a kernel's own file: after changing it, delete their cached kernels
    (``__pycache__/*.nbi``).
    """
    cell = np.int64(np.floor((value + size / 2.0) / size * count))
    if cell < 0:
        return np.int64(0)
    if cell > count - 1:
        return np.int64(count - 1)
    return cell


@nb.njit(cache=True, nogil=True, inline="always")
def flat_cell(x, y, z, dims, grid):  # pragma: no cover - numba
    """The cell number ``(ix * ny + iy) * nz + iz`` of canonical point ``(x, y, z)`` in a box
    of size ``dims`` cut by ``grid`` ``(nx, ny, nz)`` (:func:`cell_of` along each axis)."""
    ny, nz = grid[1], grid[2]
    ix, iy, iz = cell_of(x, dims[0], grid[0]), cell_of(y, dims[1], ny), cell_of(z, dims[2], nz)
    return (ix * ny + iy) * nz + iz


def partition_index(points: np.ndarray, dims: np.ndarray, grid: Grid) -> np.ndarray:
    """Flat cell index ``int64 (N,)`` (:func:`flat_cell`) of canonical ``(N, 3+)`` points in a
    box of size ``dims``.

    Args:
        points: points in canonical pose, metres.
        dims: ``(3,)`` box size dx, dy, dz, metres (must be positive).
        grid: cells along x, y, z.
    """
    dims = np.asarray(dims, dtype=np.float64).reshape(3)
    counts = np.asarray(grid, dtype=np.int64).reshape(3)
    points = np.asarray(points)
    if points.dtype not in (np.float32, np.float64):  # the kernel's two specialisations
        points = points.astype(np.float64)
    return _partition_index(points, dims, counts)


@nb.njit(cache=True, nogil=True)
def _partition_index(points, dims, grid):  # pragma: no cover - numba
    out = np.empty(points.shape[0], np.int64)
    for i in range(points.shape[0]):
        x, y, z = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        out[i] = flat_cell(x, y, z, dims, grid)
    return out


def partition_counts(points: np.ndarray, dims: np.ndarray, grid: Grid) -> np.ndarray:
    """Points per cell ``int64 (P,)`` of canonical points in a box of size ``dims``."""
    return np.bincount(partition_index(points, dims, grid), minlength=num_partitions(grid))


def mirror_points(points: np.ndarray) -> np.ndarray:
    """The points plus their mirror image across the x axis (y -> -y): ``(2N, C)``."""
    points = np.asarray(points)
    mirrored = points.copy()
    mirrored[:, 1] = -mirrored[:, 1]
    return np.concatenate([points, mirrored], axis=0)
