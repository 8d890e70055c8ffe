"""Ground height estimated from a frame's own points (for placing objects on the ground).

Method (all vectorised over a bird's-eye-view grid, a few milliseconds for a KITTI sweep):

1. Lowest point per BEV cell (default 1 m cells) of the points within ``max_range``.
2. Frame-wide plane: RANSAC over the cells' lowest points (explicit ``rng``; normals within
   ``max_tilt_deg`` of vertical), refined by least squares on its inliers. A KITTI road plane,
   when given with its calibration, replaces this fit. Each cell's lowest point is carried to
   the cell centre along the plane's slope.
3. Cells more than ``max_below_plane`` below the plane are noise (reflections); cells more than
   ``max_above_plane`` above it are roofs, walls or canopies with no visible ground near them.
   Both are dropped. Of the rest, a cell is *ground* when its height is at most ``tolerance``
   above every other cell's height plus ``max_slope`` times their distance (a grey erosion with
   a cone-shaped structuring element, radius ``window``). This rejects car roofs, walls and
   canopies whose foot is hidden, since visible ground lies within a few metres of them.
4. Cells without ground take the nearest ground cell's height, corrected by the plane's slope
   between the two, when it lies within ``fill_radius``; otherwise the plane's height.
5. :meth:`GroundModel.height_at` interpolates the cell-centre heights bilinearly; queries
   outside the grid use the nearest edge cell with the same plane correction.

The estimates sit slightly low (a cell's lowest point is about 1.5 noise sigmas below the mean
surface, i.e. 2-4 cm for a Velodyne HDL-64E).

Without any usable point (empty frame) the model is the given road plane, or flat ground at
``fallback_height`` (KITTI's Velodyne is mounted 1.73 m above the road).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from drcpo.errors import ConfigError, DataError

#: Height of the ground below KITTI's Velodyne (metres), used when a frame has no points.
KITTI_SENSOR_HEIGHT = 1.73
_RANSAC_SCORED = 1000


@dataclass(frozen=True)
class GroundConfig:
    """Parameters of :meth:`GroundModel.from_points` (metres unless noted).

    Attributes:
        cell_size: BEV cell side.
        max_range: points with ``|x|`` or ``|y|`` beyond this are ignored.
        max_slope: rise per metre allowed between neighbouring ground cells (0.2 = 11 degrees).
        tolerance: height a ground cell's minimum may exceed the slope cone of its neighbours.
        window: radius of the neighbourhood searched for lower ground.
        fill_radius: cells farther than this from any ground cell use the plane.
        max_below_plane: cell minima this far below the plane are treated as noise.
        max_above_plane: cell minima this far above the plane are never ground.
        ransac_iterations: plane hypotheses tried.
        ransac_threshold: inlier distance of the plane fit.
        max_tilt_deg: largest angle (degrees) between the plane's normal and +z.
        fallback_height: ground z when nothing better is known.
    """

    cell_size: float = 1.0
    max_range: float = 100.0
    max_slope: float = 0.2
    tolerance: float = 0.2
    window: float = 4.0
    fill_radius: float = 10.0
    max_below_plane: float = 1.0
    max_above_plane: float = 1.5
    ransac_iterations: int = 100
    ransac_threshold: float = 0.15
    max_tilt_deg: float = 20.0
    fallback_height: float = -KITTI_SENSOR_HEIGHT

    def __post_init__(self) -> None:
        positive = (
            "cell_size",
            "max_range",
            "window",
            "ransac_threshold",
            "max_below_plane",
            "max_above_plane",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"ground.{name} must be > 0, got {getattr(self, name)}")
        for name in ("max_slope", "tolerance", "fill_radius"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"ground.{name} must be >= 0, got {getattr(self, name)}")
        if self.ransac_iterations < 1:
            raise ConfigError(
                f"ground.ransac_iterations must be >= 1, got {self.ransac_iterations}"
            )
        if not 0 < self.max_tilt_deg < 90:
            raise ConfigError(f"ground.max_tilt_deg must be in (0, 90), got {self.max_tilt_deg}")
        if not np.isfinite(self.fallback_height):
            raise ConfigError(f"ground.fallback_height must be finite, got {self.fallback_height}")


@dataclass(frozen=True, eq=False)
class GroundModel:
    """Ground height ``z(x, y)`` in the LiDAR frame.

    Attributes:
        plane: ``(3,)`` coefficients ``(a, b, c)`` of the frame-wide plane ``z = a x + b y + c``.
        origin: ``(2,)`` x, y of the grid's lower corner (metres).
        cell_size: grid cell side (metres).
        heights: ``(nx, ny)`` ground height at cell centres, or ``None`` (plane only).
        ground_cells: ``bool (nx, ny)`` cells whose height came from their own points.
        source: ``"points"``, ``"plane"`` (RANSAC fit, too few cells for a grid),
            ``"road_plane"`` (given plane, no grid) or ``"default"`` (flat fallback).
    """

    plane: np.ndarray
    origin: np.ndarray
    cell_size: float
    heights: np.ndarray | None
    ground_cells: np.ndarray | None
    source: str

    # Construction -------------------------------------------------------------------------
    @classmethod
    def flat(cls, height: float = -KITTI_SENSOR_HEIGHT) -> GroundModel:
        """Flat ground at ``z = height`` everywhere."""
        return cls.from_plane(np.array([0.0, 0.0, float(height)]), source="default")

    @classmethod
    def from_plane(cls, plane: np.ndarray, source: str = "plane") -> GroundModel:
        """Ground ``z = a x + b y + c`` from ``plane = (a, b, c)``."""
        plane = np.asarray(plane, dtype=np.float64).reshape(3)
        if not np.isfinite(plane).all():
            raise DataError(f"ground plane coefficients must be finite, got {plane}")
        return cls(plane, np.zeros(2), 1.0, None, None, source)

    @classmethod
    def from_points(
        cls,
        points: np.ndarray,
        rng: np.random.Generator | None = None,
        plane: np.ndarray | None = None,
        calib=None,
        config: GroundConfig | None = None,
    ) -> GroundModel:
        """Estimate the ground of one frame.

        Args:
            points: ``(N, 3+)`` LiDAR points, metres (non-finite rows are ignored).
            rng: generator for the RANSAC plane fit; ``None`` uses a fixed seed (0), so the
                same frame always gives the same ground.
            plane: optional KITTI road plane ``(a, b, c, d)`` in rectified camera coordinates
                (``a x + b y + c z + d = 0``); needs ``calib``. Replaces the RANSAC fit.
            calib: :class:`drcpo.datasets.kitti.Calibration` of the frame (for ``plane``).
            config: :class:`GroundConfig` (defaults when ``None``).
        """
        config = config or GroundConfig()
        given = None if plane is None else road_plane_to_lidar(plane, calib)
        x, y, z = _usable_points(points, config.max_range)
        if len(z) == 0:
            if given is not None:
                return cls.from_plane(given, source="road_plane")
            return cls.flat(config.fallback_height)
        cs = config.cell_size
        origin = np.floor(np.array([x.min(), y.min()], dtype=np.float64) / cs) * cs
        flat, shape = _cell_index(x, y, origin, cs)
        lowest = _lowest_points(flat, x, y, z, shape[0] * shape[1])
        occupied = np.isfinite(lowest[:, 2])
        if given is None:
            rng = np.random.default_rng(0) if rng is None else rng
            fitted = _ransac_plane(lowest[occupied], rng, config)
            if fitted is None:
                return cls.flat(config.fallback_height)
            frame_plane = fitted
        else:
            frame_plane = given
        centres = _cell_centres(origin, cs, shape).reshape(-1, 2)
        plane_z = (centres @ frame_plane[:2] + frame_plane[2]).reshape(shape)
        # A cell's lowest point sits anywhere in it; carry it to the centre along the plane.
        shift = np.where(occupied[:, None], centres - lowest[:, :2], 0.0) @ frame_plane[:2]
        minima = (lowest[:, 2] + shift).reshape(shape)
        outlier = (minima < plane_z - config.max_below_plane) | (
            minima > plane_z + config.max_above_plane
        )
        minima[outlier] = np.inf
        ground = _ground_cells(minima, config)
        if ground.sum() < 3:
            return cls.from_plane(frame_plane, source="plane" if given is None else "road_plane")
        heights = _fill_heights(minima, ground, plane_z, config)
        return cls(frame_plane, origin, float(cs), heights, ground, "points")

    # Queries ------------------------------------------------------------------------------
    def plane_height_at(self, xy: np.ndarray) -> np.ndarray:
        """Height ``(K,)`` of the frame-wide plane at ``(K, 2)`` positions."""
        xy = _check_xy(xy)
        return xy @ self.plane[:2] + self.plane[2]

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """Ground height ``float64 (K,)`` (metres) at BEV positions ``(K, 2+)`` (x, y, metres)."""
        xy = _check_xy(xy)
        if self.heights is None:
            return xy @ self.plane[:2] + self.plane[2]
        nx, ny = self.heights.shape
        flat = self.heights.reshape(-1)
        x, y = xy[:, 0], xy[:, 1]
        # Continuous cell coordinates of the query, measured from the first cell's centre.
        gx = (x - self.origin[0]) / self.cell_size - 0.5
        gy = (y - self.origin[1]) / self.cell_size - 0.5
        cx = np.clip(gx, 0.0, nx - 1)
        cy = np.clip(gy, 0.0, ny - 1)
        lx = np.minimum(cx.astype(np.int64), max(nx - 2, 0))
        ly = np.minimum(cy.astype(np.int64), max(ny - 2, 0))
        fx, fy = cx - lx, cy - ly
        hx = np.minimum(lx + 1, nx - 1) * ny
        hy = np.minimum(ly + 1, ny - 1)
        lx = lx * ny
        bottom = flat[lx + ly] * (1 - fy) + flat[lx + hy] * fy
        top = flat[hx + ly] * (1 - fy) + flat[hx + hy] * fy
        inside = bottom * (1 - fx) + top * fx
        # Beyond the grid, continue from the edge along the plane's slope.
        a, b = self.plane[0] * self.cell_size, self.plane[1] * self.cell_size
        return inside + (gx - cx) * a + (gy - cy) * b

    def is_ground(self, points: np.ndarray, tolerance: float = 0.2) -> np.ndarray:
        """``bool (N,)``: points at most ``tolerance`` metres above the ground estimate.

        Points above ``height_at(x, y) + tolerance`` are non-ground (walls, trees, objects).
        """
        points = np.asarray(points)
        if points.ndim != 2 or points.shape[1] < 3:
            raise DataError(f"points must have shape (N, 3+), got {points.shape}")
        return points[:, 2] <= self.height_at(points[:, :2]) + tolerance


def road_plane_to_lidar(plane: np.ndarray, calib) -> np.ndarray:
    """KITTI road plane ``(a, b, c, d)`` (rectified camera frame) as LiDAR ``z = a x + b y + c``.

    The rectified frame is ``p_rect = R0 (T[:, :3] p + T[:, 3])``, so the plane's LiDAR normal is
    ``(R0 T[:, :3])^T n`` and its offset ``n . (R0 T[:, 3]) + d``. OpenPCDet instead fixes the
    rectified x, z of a box centre, solves the plane for y and converts back
    (``put_boxes_on_road_planes``); both give the same surface.
    """
    plane = np.asarray(plane, dtype=np.float64).reshape(-1)
    if plane.shape != (4,) or not np.isfinite(plane).all():
        raise DataError(f"road plane must be four finite numbers (a, b, c, d), got {plane}")
    if calib is None:
        raise DataError("a KITTI road plane needs the frame's calibration (calib)")
    r0 = np.asarray(calib.R0_rect, dtype=np.float64)
    tr = np.asarray(calib.Tr_velo_to_cam, dtype=np.float64)
    normal = (r0 @ tr[:, :3]).T @ plane[:3]
    offset = plane[:3] @ (r0 @ tr[:, 3]) + plane[3]
    if abs(normal[2]) < 1e-6 * max(np.linalg.norm(normal), 1e-12):
        raise DataError(f"road plane {plane} is vertical in the LiDAR frame")
    return np.array([-normal[0], -normal[1], -offset]) / normal[2]


# Helpers ----------------------------------------------------------------------------------
def _check_xy(xy: np.ndarray) -> np.ndarray:
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] < 2:
        raise DataError(f"positions must have shape (K, 2), got {xy.shape}")
    return xy[:, :2]


def _usable_points(
    points: np.ndarray, max_range: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x, y, z columns of the finite points within ``max_range`` in x and y."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise DataError(f"points must have shape (N, 3+), got {points.shape}")
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    # NaN fails every comparison, so the range test also drops non-finite x and y.
    keep = (np.abs(x) <= max_range) & (np.abs(y) <= max_range) & np.isfinite(z)
    if keep.all():
        return x, y, z
    return x[keep], y[keep], z[keep]


def _cell_index(
    x: np.ndarray, y: np.ndarray, origin: np.ndarray, cell_size: float
) -> tuple[np.ndarray, tuple[int, int]]:
    """Flat BEV cell ``int32 (N,)`` of each point and the grid's shape.

    Works in the points' own dtype and in place: each temporary the size of a KITTI sweep costs
    about a millisecond of page faults on small VMs.
    """
    scaled = np.subtract(x, float(origin[0]))
    scaled *= 1.0 / cell_size
    ix = scaled.astype(np.int32)
    np.subtract(y, float(origin[1]), out=scaled)
    scaled *= 1.0 / cell_size
    iy = scaled.astype(np.int32)
    shape = (int(ix.max()) + 1, int(iy.max()) + 1)
    ix *= shape[1]
    ix += iy
    return ix, shape


def _cell_centres(origin: np.ndarray, cell_size: float, shape: tuple[int, int]) -> np.ndarray:
    ix, iy = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    return np.stack([ix, iy], axis=-1) * cell_size + origin + cell_size / 2.0


def _ransac_plane(
    seeds: np.ndarray, rng: np.random.Generator, config: GroundConfig
) -> np.ndarray | None:
    """``(a, b, c)`` of ``z = a x + b y + c`` through most ``(S, 3)`` seeds; ``None`` if S < 3."""
    if len(seeds) < 3:
        return None
    z = seeds[:, 2]
    picks = rng.integers(0, len(z), size=(config.ransac_iterations, 3))
    # Hypotheses are scored on a random subset: enough to rank planes, much cheaper.
    scored = (
        seeds[rng.choice(len(z), _RANSAC_SCORED, replace=False)]
        if len(z) > _RANSAC_SCORED
        else seeds
    )
    p0, p1, p2 = seeds[picks[:, 0]], seeds[picks[:, 1]], seeds[picks[:, 2]]
    normals = np.cross(p1 - p0, p2 - p0)
    length = np.linalg.norm(normals, axis=1)
    upright = np.abs(normals[:, 2]) >= np.cos(np.deg2rad(config.max_tilt_deg)) * length
    usable = upright & (length > 1e-9)
    if not usable.any():
        return _least_squares_plane(seeds)
    normals, p0, length = normals[usable], p0[usable], length[usable]
    offsets = (normals * p0).sum(axis=1)
    distance = scored @ normals.T
    distance -= offsets
    np.abs(distance, out=distance)
    best = int(np.argmax((distance <= config.ransac_threshold * length).sum(axis=0)))
    inliers = (
        np.abs(seeds @ normals[best] - offsets[best]) <= config.ransac_threshold * length[best]
    )
    chosen = seeds[inliers]
    return _least_squares_plane(chosen) if len(chosen) >= 3 else _least_squares_plane(seeds)


def _lowest_points(
    cells: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray, count: int
) -> np.ndarray:
    """``(count, 3)`` x, y, z of the lowest point of each cell (inf z for empty cells)."""
    low_z = np.full(count, np.inf, dtype=z.dtype)
    np.minimum.at(low_z, cells, z)
    at_min = np.flatnonzero(z == low_z[cells])
    # Ties keep one of the tied points (the last written); any lowest point will do.
    low_x, low_y = np.full(count, np.inf), np.full(count, np.inf)
    low_x[cells[at_min]] = x[at_min]
    low_y[cells[at_min]] = y[at_min]
    return np.column_stack([low_x, low_y, low_z.astype(np.float64)])


def _least_squares_plane(xyz: np.ndarray) -> np.ndarray:
    design = np.column_stack([xyz[:, 0], xyz[:, 1], np.ones(len(xyz))])
    coef, *_ = np.linalg.lstsq(design, xyz[:, 2], rcond=None)
    return coef


def _ground_cells(minima: np.ndarray, config: GroundConfig) -> np.ndarray:
    """Cells whose minimum is not above a lower neighbour's slope cone (plus tolerance)."""
    radius = max(int(np.ceil(config.window / config.cell_size)), 1)
    offsets = np.arange(-radius, radius + 1) * config.cell_size
    distance = np.hypot(offsets[:, None], offsets[None, :])
    footprint = distance <= radius * config.cell_size + 1e-9
    # Grey erosion computes min over the footprint of (f(x + y) - s(y)), so s = -slope * |y|
    # yields the lowest neighbouring minimum raised along the allowed slope.
    finite = np.where(np.isfinite(minima), minima, 1e9)
    cone = ndimage.grey_erosion(
        finite, footprint=footprint, structure=np.where(footprint, -config.max_slope * distance, 0)
    )
    return np.isfinite(minima) & (minima <= cone + config.tolerance)


def _fill_heights(
    minima: np.ndarray, ground: np.ndarray, plane_z: np.ndarray, config: GroundConfig
) -> np.ndarray:
    """Cell heights: ground cells keep their minimum; others borrow from the nearest one."""
    distance, (ix, iy) = ndimage.distance_transform_edt(~ground, return_indices=True)
    borrowed = minima[ix, iy] - plane_z[ix, iy] + plane_z
    near = distance * config.cell_size <= config.fill_radius
    return np.where(ground, minima, np.where(near, borrowed, plane_z))
