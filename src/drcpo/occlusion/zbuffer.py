"""The two z-buffers: :func:`range_image_occlusion` (e-HPR's ``range_image`` mode, *not* the
paper's method) and :class:`OcclusionMap` (placement's pre-build "occluded" test: is a box hidden
behind the frame?). Their cell arithmetic differs (float64 angles against float32 pseudo-angle
tables) and each reproduces its own reference bit for bit, so they are kept apart.
Imports :mod:`drcpo.errors`, :mod:`drcpo.geometry` and :mod:`drcpo.occlusion.checks` only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba
import numpy as np

from drcpo.errors import ConfigError, DataError
from drcpo.geometry import heading_terms, in_box
from drcpo.occlusion.checks import _check_points, _check_viewpoint

__all__ = ["OcclusionMap", "range_image_occlusion", "surface_samples"]


def range_image_occlusion(
    points: np.ndarray,
    viewpoint: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    *,
    azimuth_resolution: float = float(np.deg2rad(0.2)),
    elevation_resolution: float = float(np.deg2rad(0.4)),
    beam_elevations: np.ndarray | None = None,
    depth_tolerance: float = 0.2,
) -> np.ndarray:
    """Z-buffer occlusion: keep the nearest surface in each (azimuth, elevation) cell.

    This is *not* the paper's method (HPR); it is a lighter alternative that mimics a spinning
    LiDAR: points are binned by azimuth (``azimuth_resolution`` radians) and elevation (either
    regular cells of ``elevation_resolution`` radians or the nearest of the sensor's
    ``beam_elevations``), and a point is kept when its range is within ``depth_tolerance``
    metres of the nearest range in its cell.

    Args:
        points: ``(N, 3 + C)`` points, metres.
        viewpoint: ``(3,)`` sensor position, metres.
        azimuth_resolution: radians per azimuth cell.
        elevation_resolution: radians per elevation cell (ignored with ``beam_elevations``).
        beam_elevations: optional ``(B,)`` beam elevation angles in radians (any order).
        depth_tolerance: metres behind the nearest return that still count as the same surface.

    Returns:
        ``bool (N,)``: visible points. Points at the viewpoint are visible.
    """
    xyz = _check_points(points)
    center = _check_viewpoint(viewpoint)
    for name, value in (
        ("azimuth_resolution", azimuth_resolution),
        ("elevation_resolution", elevation_resolution),
    ):
        if not (math.isfinite(value) and 0 < value <= math.pi):
            raise ConfigError(f"{name} must be in (0, pi] radians, got {value}")
    if not (math.isfinite(depth_tolerance) and depth_tolerance >= 0):
        raise ConfigError(f"depth_tolerance must be >= 0 metres, got {depth_tolerance}")
    visible = np.ones(len(xyz), dtype=bool)
    if len(xyz) == 0:
        return visible
    rel = xyz - center
    rng = np.sqrt(np.einsum("ij,ij->i", rel, rel))
    valid = rng > 0
    if not valid.any():
        return visible
    rel, rng = rel[valid], rng[valid]
    azimuth = np.arctan2(rel[:, 1], rel[:, 0])
    elevation = np.arcsin(np.clip(rel[:, 2] / rng, -1.0, 1.0))
    n_azimuth = max(1, math.ceil(2 * math.pi / azimuth_resolution))
    column = np.floor((azimuth + np.pi) / azimuth_resolution).astype(np.int64) % n_azimuth
    row = _elevation_rows(elevation, elevation_resolution, beam_elevations)
    cell = row * n_azimuth + column
    _, inverse = np.unique(cell, return_inverse=True)
    nearest = np.full(int(inverse.max()) + 1, np.inf)
    np.minimum.at(nearest, inverse, rng)
    visible[valid] = rng <= nearest[inverse] + depth_tolerance
    return visible


def _elevation_rows(
    elevation: np.ndarray, resolution: float, beams: np.ndarray | None
) -> np.ndarray:
    if beams is None:
        return np.floor((elevation + np.pi / 2) / resolution).astype(np.int64)
    beams = np.sort(np.asarray(beams, dtype=np.float64).ravel())
    if beams.size == 0 or not np.isfinite(beams).all():
        raise ConfigError("beam_elevations must be a non-empty list of finite angles (radians)")
    middles = (beams[1:] + beams[:-1]) / 2
    return np.searchsorted(middles, elevation).astype(np.int64)


class OcclusionMap:
    """Nearest range per (azimuth, elevation) cell of a point cloud seen from a viewpoint: a
    z-buffer used to reject placements hidden behind the frame before anything is built.

    Cells are ``0.2 x 0.4`` degrees (about a KITTI HDL-64E's resolution). A box sample counts
    as occluded when its cell holds a point at least ``depth_tolerance`` metres nearer; cells
    without points occlude nothing, so gaps in the frame keep boxes visible. Non-finite points
    occlude nothing either.

    The buffer is filled lazily, only in the cells the queried boxes' samples fall in, and only
    with the points that may hide a sample there: one pass over the points per query, most of
    them set aside by their direction (a pseudo-angle bin and a slope, no trigonometry) before
    their cell is computed. :meth:`prepare` computes those directions once (say, on a thread
    that would otherwise wait); :meth:`occluded` does when they are missing.

    Args:
        points: ``(N, 3+)`` points, metres (not copied; do not modify them while querying).
        viewpoint: ``(3,)`` sensor position, metres.
        depth_tolerance: metres a point must lie in front of a sample to hide it.
    """

    AZIMUTH_STEP = math.radians(0.2)
    ELEVATION_STEP = math.radians(0.4)

    COLUMNS = math.ceil(2 * math.pi / AZIMUTH_STEP)
    ROWS = math.ceil(math.pi / ELEVATION_STEP) + 1

    def __init__(
        self, points: np.ndarray, viewpoint: np.ndarray, depth_tolerance: float = 0.5
    ) -> None:
        self.points = np.asarray(points)
        if self.points.ndim != 2 or self.points.shape[1] < 3:
            raise DataError(f"points must have shape (N, 3+), got {self.points.shape}")
        self.viewpoint = np.asarray(viewpoint, dtype=np.float64).reshape(3)
        self.tolerance = depth_tolerance
        # The cell arithmetic is float32, as the azimuth and elevation always were.
        self._constants = np.array(
            [
                math.pi,
                math.pi / 2,
                self.AZIMUTH_STEP,
                self.ELEVATION_STEP,
                depth_tolerance,
                *self.viewpoint,
            ],
            dtype=np.float32,
        )
        self._directions: tuple[np.ndarray, np.ndarray] | None = None

    def prepare(self) -> OcclusionMap:
        """Compute each point's direction bin and slope (see :meth:`occluded`); returns self."""
        if self._directions is None:
            bins = np.empty(len(self.points), np.int16)
            slopes = np.empty(len(self.points), np.float32)
            _point_directions(self.points, self._constants, bins, slopes)
            self._directions = bins, slopes
        return self

    def occluded(self, boxes: np.ndarray, cleared: np.ndarray | None = None) -> np.ndarray:
        """``float64 (M,)``: share of each ``(M, 7)`` box's sensor-facing surface samples
        occluded, leaving out the points inside the ``cleared`` boxes ``(C, 7)`` (the frame's
        points inside placed boxes are removed to make room for the objects)."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        cleared = np.asarray(np.zeros((0, 7)) if cleared is None else cleared, np.float64)
        cleared = cleared.reshape(-1, 7)
        share = np.zeros(len(boxes))
        if len(boxes) == 0:
            return share
        bins, slopes = self.prepare()._directions
        _occluded_share(
            self.points,
            bins,
            slopes,
            cleared,
            *heading_terms(cleared),
            boxes,
            *heading_terms(boxes),
            self.viewpoint,
            _FACE_GRIDS,
            _FACE_AXES,
            _FACE_SIGNS,
            self._constants,
            _DIRECTIONS,
            _AZIMUTH_FIRST,
            _AZIMUTH_SECOND,
            share,
        )
        return share


@numba.njit(cache=True, nogil=True)
def _point_directions(points, constants, bins, slopes):  # pragma: no cover - numba
    # Per point: its azimuth's pseudo-angle bin (-1: not finite, occludes nothing; -2: straight
    # above or below the viewpoint, always tested in full) and its slope z / horizontal, as
    # slope * |slope|.
    vx, vy, vz = constants[5], constants[6], constants[7]
    for i in range(points.shape[0]):
        x = np.float64(np.float32(points[i, 0]) - vx)
        y = np.float64(np.float32(points[i, 1]) - vy)
        z = np.float64(np.float32(points[i, 2]) - vz)
        if not np.isfinite(x + y + z):
            bins[i] = -1
        elif x == 0.0 and y == 0.0:
            bins[i] = -2
        else:
            bins[i] = min(int(_pseudo_angle(x, y) * (_BINS / 4.0)), _BINS - 1)
            slopes[i] = z * abs(z) / (x * x + y * y)  # slope * |slope|: monotone, no sqrt


def _face_templates(steps: tuple[int, int] = (12, 8)) -> tuple[np.ndarray, np.ndarray]:
    """Unit-box grids on the four sides and the top: ``(5, K, 3)`` and the faces' outward
    ``(axis, sign)`` pairs ``(5, 2)`` (the bottom rests on the ground, no one sees it)."""
    u, v = np.meshgrid(np.linspace(-0.5, 0.5, steps[0]), np.linspace(-0.5, 0.5, steps[1]))
    faces = ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0), (2, 1.0))
    grids = np.zeros((len(faces), u.size, 3))
    for f, (axis, sign) in enumerate(faces):
        u_axis, v_axis = (a for a in range(3) if a != axis)
        grids[f, :, u_axis], grids[f, :, v_axis], grids[f, :, axis] = (
            u.ravel(),
            v.ravel(),
            0.5 * sign,
        )
    return grids, np.array(faces)


_FACE_GRIDS, _FACES = _face_templates()
# 5 x 4 from edge to edge: an object e-HPR keeps often shows only a rim above an occluder.
_SURFACE_GRIDS = _face_templates((5, 4))[0]
_FACE_AXES, _FACE_SIGNS = _FACES[:, 0].astype(np.int64), _FACES[:, 1].copy()


def surface_samples(boxes: np.ndarray, viewpoint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points on the faces of each ``(M, 7)`` box that look towards ``viewpoint`` ``(3,)``:
    a 5 x 4 grid from edge to edge on each such side or top, ``(S, 3)`` metres, box ``m``'s
    being rows ``offsets[m]:offsets[m + 1]`` of ``offsets`` ``int64 (M + 1,)``."""
    world, facing = _facing_samples(boxes, viewpoint, _SURFACE_GRIDS)
    counts = facing.sum(axis=1) * _SURFACE_GRIDS.shape[1]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return world[facing].reshape(-1, 3), offsets


def _facing_samples(
    boxes: np.ndarray, viewpoint: np.ndarray, grids: np.ndarray = _FACE_GRIDS
) -> tuple[np.ndarray, np.ndarray]:
    """Samples ``(M, 5, K, 3)`` on the sides and top of each box in the LiDAR frame (the unit
    ``grids``, ``(5, K, 3)``), and which of those faces look towards ``viewpoint``:
    ``bool (M, 5)``.

    :meth:`OcclusionMap.occluded` computes the same samples (the facing ones only) in numba.
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    cos, sin = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    rel = viewpoint - boxes[:, :3]
    view = np.column_stack(
        [rel[:, 0] * cos + rel[:, 1] * sin, -rel[:, 0] * sin + rel[:, 1] * cos, rel[:, 2]]
    )
    axes, signs = _FACES[:, 0].astype(int), _FACES[:, 1]
    facing = signs * view[:, axes] > boxes[:, 3:6][:, axes] / 2.0
    local = grids[None] * boxes[:, None, None, 3:6]
    world = np.empty_like(local)
    c, s_ = cos[:, None, None], sin[:, None, None]
    world[..., 0] = c * local[..., 0] - s_ * local[..., 1] + boxes[:, None, None, 0]
    world[..., 1] = s_ * local[..., 0] + c * local[..., 1] + boxes[:, None, None, 1]
    world[..., 2] = local[..., 2] + boxes[:, None, None, 2]
    return world, facing


_ANGLE_SLACK = 1e-5  # radians; far above the float32 cell arithmetic's error (~1e-6)
_BINS = 8192  # pseudo-angle bins of each direction table; narrower than a cell (< 1e-3 rad)


def _direction_table(
    edges: np.ndarray, step: float, offset: float, count: int
) -> tuple[np.ndarray, ...]:
    """Per pseudo-angle bin (between consecutive angles of ``edges``, radians): the first cell
    ``floor((angle + offset) / step)`` (float32 constants) its directions may fall in, give or
    take the slack, and whether a cell boundary lies in it (0 or 1; -1: undecided, a seam).
    Also the unit vectors (cos, sin) of the ``count + 1`` cell boundaries."""
    step64, offset64 = float(np.float32(step)), float(np.float32(offset))
    low = np.floor((edges[:-1] - _ANGLE_SLACK + offset64) / step64).astype(np.int64)
    high = np.floor((edges[1:] + _ANGLE_SLACK + offset64) / step64).astype(np.int64)
    crosses = high - low
    crosses[(crosses < 0) | (crosses > 1)] = -1
    bound = np.arange(count + 1) * step64 - offset64
    return low, crosses, np.cos(bound), np.sin(bound)


def _azimuth_table() -> tuple[np.ndarray, ...]:
    p = np.arange(_BINS + 1) * (4.0 / _BINS)  # the inverse of _pseudo_angle at the bin edges
    x = np.select([p < 1, p < 2, p < 3], [1 - p, 1 - p, p - 3], p - 3)
    y = np.select([p < 1, p < 2, p < 3], [p, 2 - p, 2 - p], p - 4)
    edges = np.arctan2(y, x)
    edges[-1] = 0.0  # a full turn: the last bin ends just below azimuth 0
    return _direction_table(edges, OcclusionMap.AZIMUTH_STEP, math.pi, OcclusionMap.COLUMNS)


def _elevation_table() -> tuple[np.ndarray, ...]:
    q = np.arange(_BINS + 1) * (2.0 / _BINS) - 1.0  # the inverse of z / (h + |z|)
    edges = np.arctan2(q, np.where(q < 0, 1 + q, 1 - q))
    return _direction_table(edges, OcclusionMap.ELEVATION_STEP, math.pi / 2, OcclusionMap.ROWS)


@numba.njit(cache=True, nogil=True, inline="always")
def _pseudo_angle(x, y):  # pragma: no cover - numba
    # Monotone in the angle of (x, y) from +x counter-clockwise, in [0, 4); no trigonometry,
    # and selects rather than branches (the quadrants of a sweep's points are unpredictable).
    share = abs(y) / (abs(x) + abs(y))
    base = 0.0 if x >= 0.0 and y >= 0.0 else (4.0 if x >= 0.0 else 2.0)
    return base + share if (x >= 0.0) == (y >= 0.0) else base - share


@numba.njit(cache=True, nogil=True)
def _cell_of(x, y, z, constants, columns, rows):  # pragma: no cover - numba
    # Row and column of one float32 offset from the viewpoint by float32 trigonometry (libm's
    # atan2 and hypot, then the float32 cell arithmetic), as numpy computes them on float32
    # arrays up to its vectorised arctan2's last bit on some CPUs.
    azimuth = np.float32(math.atan2(y, x))
    elevation = np.float32(math.atan2(z, np.float32(np.hypot(x, y))))
    column = math.floor(np.float32(np.float32(azimuth + constants[0]) / constants[2]))
    row = math.floor(np.float32(np.float32(elevation + constants[1]) / constants[3]))
    return min(max(row, 0), rows - 1), column % columns


@numba.njit(cache=True, nogil=True, inline="always")
def _side(first, crosses, bound_cos, bound_sin, a, b, length):  # pragma: no cover - numba
    # The cell of direction (a, b) (angle atan2(b, a)) among first and first + 1, given the
    # unit vector of the boundary between them when one may lie in the direction's bin
    # (crosses); -1 when the direction lies within the slack of that boundary.
    if crosses == 0:
        return first
    if crosses < 0:
        return -1
    turn = bound_cos * b - bound_sin * a  # > 0: past the boundary
    margin = _ANGLE_SLACK * length
    if turn > margin:
        return first + 1
    if turn < -margin:
        return first
    return -1


@numba.njit(cache=True, nogil=True)
def _cells(
    offsets, az_low, az_cross, az_cos, az_sin, el_low, el_cross, el_cos, el_sin, constants, rows
):  # pragma: no cover - numba
    # Row and column ``int64 (n, 2)`` of float32 offsets ``(n, 3)`` from the viewpoint, as
    # _cell_of computes them, through the pseudo-angle tables and at most one boundary test
    # per angle; _cell_of decides the directions within the slack of a boundary.
    columns = az_cos.shape[0] - 1
    out = np.empty((offsets.shape[0], 2), np.int64)
    for i in range(offsets.shape[0]):
        x, y, z = offsets[i, 0], offsets[i, 1], offsets[i, 2]
        fx, fy, fz = np.float64(x), np.float64(y), np.float64(z)
        horizontal = math.sqrt(fx * fx + fy * fy)
        row = column = -1
        if horizontal > 0.0:
            b = min(int(_pseudo_angle(fx, fy) * (_BINS / 4.0)), _BINS - 1)
            first = az_low[b]
            column = _side(
                first, az_cross[b], az_cos[first + 1], az_sin[first + 1], fx, fy, horizontal
            )
            e = min(int((fz / (horizontal + abs(fz)) + 1.0) * (_BINS / 2.0)), _BINS - 1)
            first = el_low[e]
            length = math.sqrt(fx * fx + fy * fy + fz * fz)
            row = _side(
                first, el_cross[e], el_cos[first + 1], el_sin[first + 1], horizontal, fz, length
            )
        if column >= 0 and 0 < row < rows - 1:
            out[i, 0], out[i, 1] = row, column % columns
        else:
            out[i, 0], out[i, 1] = _cell_of(x, y, z, constants, columns, rows)
    return out


@numba.njit(cache=True, nogil=True)
def _occluded_share(
    points,
    bins,
    slopes,
    cleared,
    cleared_cos,
    cleared_sin,
    boxes,
    cos,
    sin,
    viewpoint,
    grids,
    axes,
    signs,
    constants,
    tables,
    az_first,
    az_second,
    share,
):  # pragma: no cover - numba
    columns, rows = tables[2].shape[0] - 1, tables[6].shape[0] - 1
    # 1. The samples of the faces that look at the viewpoint: offset and range of each.
    count, per_face = boxes.shape[0], grids.shape[1]
    sample_box = np.empty(count * grids.shape[0] * per_face, np.int64)
    offsets = np.empty((sample_box.shape[0], 3), np.float32)
    total = 0
    vx, vy, vz = constants[5], constants[6], constants[7]
    for m in range(count):
        rel_x, rel_y = viewpoint[0] - boxes[m, 0], viewpoint[1] - boxes[m, 1]
        view = (
            rel_x * cos[m] + rel_y * sin[m],
            -rel_x * sin[m] + rel_y * cos[m],
            viewpoint[2] - boxes[m, 2],
        )
        for f in range(grids.shape[0]):
            if not signs[f] * view[axes[f]] > boxes[m, 3 + axes[f]] / 2.0:
                continue
            for k in range(per_face):
                local_x = grids[f, k, 0] * boxes[m, 3]
                local_y = grids[f, k, 1] * boxes[m, 4]
                local_z = grids[f, k, 2] * boxes[m, 5]
                x = cos[m] * local_x - sin[m] * local_y + boxes[m, 0]
                y = sin[m] * local_x + cos[m] * local_y + boxes[m, 1]
                offsets[total, 0] = np.float32(x) - vx
                offsets[total, 1] = np.float32(y) - vy
                offsets[total, 2] = np.float32(local_z + boxes[m, 2]) - vz
                sample_box[total] = m
                total += 1
    if total == 0:
        return
    offsets = offsets[:total]
    sample_cell = _cells(offsets, *tables, constants, rows)
    # 2. Per column, the rows wanted and the range within which a point may hide a sample;
    #    the wanted cells get consecutive slots, column by column.
    low = np.full(columns, rows, np.int64)
    high = np.full(columns, -1, np.int64)
    reach = np.full(columns, -1.0)  # squared
    sample_range = np.empty(total, np.float32)
    depth = max(-np.float64(constants[4]), 0.0) + 1e-3
    el_offset, el_step = np.float64(constants[1]), np.float64(constants[3])
    for t in range(total):
        x, y, z = offsets[t, 0], offsets[t, 1], offsets[t, 2]
        sample_range[t] = np.float32(math.sqrt(x * x + y * y + z * z))  # as einsum sums
        r, c = sample_cell[t, 0], sample_cell[t, 1]
        low[c] = min(low[c], r)
        high[c] = max(high[c], r)
        reach[c] = max(reach[c], (np.float64(sample_range[t]) + depth) ** 2)
    slot = np.zeros(columns, np.int64)
    slope_low = np.full(columns, np.inf)  # elevations of the wanted rows (see slopes)
    slope_high = np.full(columns, -np.inf)
    slots = 0
    for c in range(columns):
        slot[c] = slots
        if high[c] < 0:
            continue
        slots += high[c] - low[c] + 1
        down = low[c] * el_step - el_offset - _ANGLE_SLACK
        up = (high[c] + 1) * el_step - el_offset + _ANGLE_SLACK
        slope_low[c] = -np.inf if low[c] == 0 or down <= -math.pi / 2 else math.tan(down)
        slope_high[c] = np.inf if high[c] >= rows - 2 or up >= math.pi / 2 else math.tan(up)
        # as the points' slopes are stored: slope * |slope|
        slope_low[c] *= abs(slope_low[c])
        slope_high[c] *= abs(slope_high[c])
    # 3. The points that may hide a sample: in a wanted column's direction bin, within its
    #    rows' elevations and near enough (no trigonometry: most points stop here).
    candidate = np.empty(points.shape[0], np.int64)
    near = np.empty((points.shape[0], 3), np.float32)
    found = 0
    for i in range(points.shape[0]):
        b = bins[i]
        if b == -1:
            continue
        # Seam bins (first < 0) and points straight above or below (b = -2): no shortcut.
        first = az_first[b] if b >= 0 else -1
        second = az_second[b] if b >= 0 else -1
        if first >= 0:
            if high[first] < 0 and high[second] < 0:
                continue
            slope = np.float64(slopes[i])
            if slope < min(slope_low[first], slope_low[second]):
                continue
            if slope > max(slope_high[first], slope_high[second]):
                continue
        x = np.float32(points[i, 0]) - vx
        y = np.float32(points[i, 1]) - vy
        z = np.float32(points[i, 2]) - vz
        if first >= 0:
            fx, fy, fz = np.float64(x), np.float64(y), np.float64(z)
            if fx * fx + fy * fy + fz * fz > max(reach[first], reach[second]):
                continue
        candidate[found] = i
        near[found, 0], near[found, 1], near[found, 2] = x, y, z
        found += 1
    # 4. Their cells, and the nearest range in each wanted cell of the points not cleared
    #    (the cleared boxes' BEV bounds, with slack, set most of them aside cheaply).
    bounds = np.empty((cleared.shape[0], 2))
    for k in range(cleared.shape[0]):
        c, s = abs(cleared_cos[k]), abs(cleared_sin[k])
        bounds[k, 0] = (cleared[k, 3] * c + cleared[k, 4] * s) / 2.0 + 1e-6
        bounds[k, 1] = (cleared[k, 3] * s + cleared[k, 4] * c) / 2.0 + 1e-6
    near = near[:found]
    cell = _cells(near, *tables, constants, rows)
    nearest = np.full(slots, np.inf, np.float32)
    for n in range(found):
        r, c = cell[n, 0], cell[n, 1]
        if not low[c] <= r <= high[c]:
            continue
        w = slot[c] + r - low[c]
        x, y, z = near[n, 0], near[n, 1], near[n, 2]
        distance = np.float32(math.sqrt(x * x + y * y + z * z))
        if distance >= nearest[w]:
            continue
        i = candidate[n]
        px, py, pz = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        gone = False
        for k in range(cleared.shape[0]):
            if abs(px - cleared[k, 0]) > bounds[k, 0] or abs(py - cleared[k, 1]) > bounds[k, 1]:
                continue
            if in_box(px, py, pz, cleared[k], cleared_cos[k], cleared_sin[k], 0.0):
                gone = True
                break
        if not gone:
            nearest[w] = distance
    # 5. Each box's share of hidden samples.
    hidden = np.zeros(count, np.int64)
    seen = np.zeros(count, np.int64)
    tolerance = constants[4]
    for t in range(total):
        m = sample_box[t]
        seen[m] += 1
        r, c = sample_cell[t, 0], sample_cell[t, 1]
        if np.float32(nearest[slot[c] + r - low[c]] + tolerance) < sample_range[t]:
            hidden[m] += 1
    for m in range(count):
        if seen[m] > 0:
            share[m] = hidden[m] / seen[m]


_DIRECTIONS = (*_azimuth_table(), *_elevation_table())
# The columns of each azimuth bin (first -1: a seam bin), wrapped, for the points' quick test.
_AZIMUTH_FIRST = np.where(_DIRECTIONS[1] >= 0, _DIRECTIONS[0] % OcclusionMap.COLUMNS, -1)
_AZIMUTH_SECOND = (_DIRECTIONS[0] + np.maximum(_DIRECTIONS[1], 0)) % OcclusionMap.COLUMNS
