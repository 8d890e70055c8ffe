"""Objects as the sensor records them (``self_occlusion.mode: sensor``).

Each point of a placed, constructed object is a small surface element (a disk facing the
sensor, its radius from the local point spacing, :func:`surfel_radii`); every beam ray of the
:class:`~drcpo.sensor.Sensor` that crosses an element returns at the nearest one it crosses,
with the sensor's range noise and dropout (:func:`render_object`). Density that falls with
distance, scan lines and self-occlusion come out of this one step.

The sensor's ray cells are found without trigonometry (a pseudo-angle table for the azimuth
column, the tangents of the beam edges for the beam) by the rule of :meth:`Sensor.cells`.
Imports :mod:`drcpo.errors`,
:mod:`drcpo.sensor` and :mod:`drcpo.occlusion.checks` only.
"""

from __future__ import annotations

import math
import weakref

import numba
import numpy as np

from drcpo.errors import ConfigError, DataError
from drcpo.occlusion.checks import _check_points
from drcpo.sensor import Sensor

__all__ = [
    "RADIUS_FACTOR",
    "RADIUS_RANGE",
    "VOXEL",
    "radius_cap",
    "render_object",
    "surfel_radii",
]

#: Edge of the voxels whose point counts give the local spacing, metres.
VOXEL = 0.15
#: Surface-element radius per unit of local point spacing.
RADIUS_FACTOR = 0.9
#: The radii are clipped to this range, metres.
RADIUS_RANGE = (0.01, 0.15)


def surfel_radii(points: np.ndarray, max_radius: float | None = None) -> np.ndarray:
    """``float64 (n,)``: each point's surface-element radius, metres.

    The local spacing of the points on a surface is ``3 VOXEL / sqrt(k)``, ``k`` the points in
    the point's voxel and its 26 neighbours (a surface crosses about ``9 VOXEL**2`` of them);
    the radius is :data:`RADIUS_FACTOR` times that, clipped to :data:`RADIUS_RANGE`. So a dense
    object's elements close the gaps between its points while its silhouette grows by less
    than a spacing.

    Args:
        points: ``(n, 3+)`` an object's points, metres (any frame).
        max_radius: the upper clip, metres (``RADIUS_RANGE[1]`` when None; see
            :func:`radius_cap`); a clip below ``RADIUS_RANGE[0]`` gives every point that.
    """
    xyz = _check_points(points)
    high = RADIUS_RANGE[1] if max_radius is None else _check_cap(max_radius)
    low = min(RADIUS_RANGE[0], high)
    radii = np.empty(len(xyz))
    starts = np.array([0, len(xyz)], dtype=np.int64)
    _voxel_radii(xyz, starts, VOXEL, RADIUS_FACTOR, low, high, radii)
    return radii


def radius_cap(dims: np.ndarray, share: float | None) -> float | None:
    """The upper clip of an object's surface-element radii (``self_occlusion.radius_share``):
    ``share`` times the narrower horizontal side of its box, at most ``RADIUS_RANGE[1]``;
    ``None`` (the plain clip) when ``share`` is None.

    A thin object (a person: legs and arms a few centimetres across, boxes about 0.6 m
    wide) is hit by a ray only where a limb is; elements as wide as a car's spacing would
    widen each limb by their radius on both sides, so its elements are kept below a share
    of its width.

    Args:
        dims: ``(3,)`` the box's size dx, dy, dz, metres.
        share: the share of ``min(dx, dy)``, or None.
    """
    if share is None:
        return None
    size = np.asarray(dims, dtype=np.float64).reshape(-1)
    if size.shape != (3,) or not (np.isfinite(size).all() and (size > 0).all()):
        raise DataError(f"box dims must be 3 finite sizes > 0 metres, got {size.tolist()}")
    return min(float(share) * float(min(size[0], size[1])), RADIUS_RANGE[1])


def _check_cap(max_radius: float) -> float:
    value = float(max_radius)
    if not (math.isfinite(value) and value > 0):
        raise DataError(f"max_radius must be a finite number > 0 metres, got {max_radius!r}")
    return value


def render_object(
    points: np.ndarray,
    sensor: Sensor,
    rng: np.random.Generator,
    radii: np.ndarray | None = None,
    max_radius: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """An object's points as ``sensor`` records them.

    Every ray (beam ``b``, column ``c``: from ``sensor.ray_origins(b)`` along
    ``sensor.ray_directions(b, c)``) that passes within ``radii[i]`` of a point ``i`` returns
    at the nearest such point's projection on the ray, plus ``N(0, sensor.range_noise)``, and
    is lost with probability ``sensor.dropout`` (the noise of all returns is drawn first, then
    their dropout, in the order beam, then column); returns nearer than ``sensor.min_range``
    or farther than ``sensor.max_range`` from the mount are lost too. A ray behind a nearer
    element is not seen, so the object hides its own far side.

    Args:
        points: ``(n, F)`` the object's points placed in the LiDAR frame, metres; columns
            ``3:`` are features (intensity, ...).
        sensor: the LiDAR.
        rng: the only source of randomness.
        radii: ``float64 (n,)`` surface-element radii, metres (:func:`surfel_radii` when
            None).
        max_radius: with ``radii`` None, the upper clip of :func:`surfel_radii` (metres;
            e.g. :func:`radius_cap`).

    Returns:
        ``returns float32 (m, F)``, exactly on their rays (``sensor.cells(returns)`` gives
        their beam and column back), features copied from the point hit; ``source int64
        (m,)``: the index of that point.
    """
    xyz = _check_points(points)
    radii = surfel_radii(xyz, max_radius) if radii is None else _check_radii(radii, len(xyz))
    tables = sensor_tables(sensor)
    hits = _render(xyz, radii, *tables.geometry)
    noise = rng.normal(0.0, sensor.range_noise, len(hits[0]))
    lost = rng.random(len(hits[0])) < sensor.dropout
    features = np.asarray(points, dtype=np.float32)
    limits = np.array([sensor.min_range, sensor.max_range])
    return _returns(*hits, noise, lost, features, limits, *tables.geometry)


def _check_radii(radii: np.ndarray, count: int) -> np.ndarray:
    array = np.asarray(radii)
    if array.shape != (count,):
        raise DataError(f"radii must have shape ({count},), one per point, got {array.shape}")
    if not np.issubdtype(array.dtype, np.number) or np.issubdtype(array.dtype, np.complexfloating):
        raise DataError(f"radii must be real numbers, got dtype {array.dtype}")
    array = np.ascontiguousarray(array, dtype=np.float64)
    bad = ~(np.isfinite(array) & (array >= 0))
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise DataError(
            f"radii must be finite and >= 0 metres; {int(bad.sum())} are not "
            f"(first: radii[{first}] = {array[first]})"
        )
    return array


class SensorTables:
    """A sensor's rays and ray cells as the kernels use them (read-only, shared by every call).

    ``geometry`` is the tuple every kernel takes, in this order: the tangents of the beam edges
    (``float64 (B + 1,)``, descending) and their look-up table (see :func:`_descending_lut`),
    the tangents of the beams' elevations and their look-up table, the beams' origin offsets
    ``(B,)``, the mount ``(3,)``, the cosine and sine of each beam's elevation ``(B,)`` and of
    each column's azimuth ``(C,)``, the pseudo-angle table of the columns (per bin: the column
    at its start, whether a column boundary lies inside it (1) or not (0; -1: more than one,
    the kernel falls back on ``atan2``), that boundary's unit vector), and ``float64 (9,)``
    constants: azimuth step, phase, smallest and largest offset, columns per radian, and the
    start and bins per unit of the two look-up tables.
    """

    def __init__(self, sensor: Sensor) -> None:
        edges = np.clip(sensor.beam_edges(), -math.pi / 2 + 1e-9, math.pi / 2 - 1e-9)
        elevation = np.array(sensor.elevations, dtype=np.float64)
        azimuth = sensor.phase + np.arange(sensor.num_columns) * sensor.azimuth_step
        self.offsets = np.array(sensor.offsets, dtype=np.float64)
        self.beam_cos, self.beam_sin = np.cos(elevation), np.sin(elevation)
        self.column_cos, self.column_sin = np.cos(azimuth), np.sin(azimuth)
        edge_slopes, beam_slopes = np.tan(edges), np.tan(elevation)
        edge_lut, edge_start, edge_scale = _descending_lut(edge_slopes)
        beam_lut, beam_start, beam_scale = _descending_lut(beam_slopes)
        constants = np.array(
            [
                sensor.azimuth_step,
                sensor.phase,
                self.offsets.min(),
                self.offsets.max(),
                1.0 / sensor.azimuth_step,
                edge_start,
                edge_scale,
                beam_start,
                beam_scale,
            ]
        )
        self.geometry = (
            edge_slopes,
            edge_lut,
            beam_slopes,
            beam_lut,
            self.offsets,
            np.array(sensor.mount, dtype=np.float64),
            self.beam_cos,
            self.beam_sin,
            self.column_cos,
            self.column_sin,
            *_column_table(sensor.azimuth_step, sensor.phase, sensor.num_columns),
            constants,
        )
        for array in self.geometry:
            array.setflags(write=False)


_TABLES: weakref.WeakKeyDictionary[Sensor, SensorTables] = weakref.WeakKeyDictionary()


def sensor_tables(sensor: Sensor) -> SensorTables:
    """The :class:`SensorTables` of ``sensor``, built once per sensor object."""
    tables = _TABLES.get(sensor)
    if tables is None:
        tables = _TABLES[sensor] = SensorTables(sensor)
    return tables


def _descending_lut(table: np.ndarray) -> tuple[np.ndarray, float, float]:
    """A look-up table for counting the entries of a descending ``table`` above a value
    (see :func:`_lut_bin`): bins of half the smallest gap from ``start`` on (``scale`` bins
    per unit), each holding how many entries lie surely above it and the next two entries
    (``-inf`` past the end), of which only those may lie above a value in the bin."""
    gaps = -np.diff(table)
    width = float(gaps.min()) / 2.0 if len(gaps) else 1e-3
    start = float(table[-1]) - width
    bins = math.ceil((float(table[0]) + width - start) / width)
    if not 0 < bins <= 1 << 20:
        raise ConfigError(
            f"beam elevations {gaps.min():.3g} rad apart are too close for the ray tables"
        )
    ends = start + (np.arange(bins) + 1.0) * width
    above = (table[None, :] > ends[:, None] + 1e-9 * width).sum(axis=1)
    padded = np.concatenate([table, [-np.inf, -np.inf]])
    lut = np.column_stack([above, padded[above], padded[above + 1]]).astype(np.float64)
    return lut, start, 1.0 / width


@numba.njit(cache=True, nogil=True, inline="always")
def _lut_bin(value, start, scale, bins):  # pragma: no cover - numba
    # The bin of `value` in a _descending_lut table: -1 below it (every entry lies above the
    # value), `bins` above it (none does). The count is then, in the caller (arrays passed to
    # helpers are reference-counted on every call): lut[k, 0] + (lut[k, 1] > value) +
    # (lut[k, 2] > value).
    position = (value - start) * scale
    if not position >= 0.0:
        return -1
    if position >= bins:
        return bins
    return int(position)


def _column_table(step: float, phase: float, columns: int) -> tuple[np.ndarray, ...]:
    """Per pseudo-angle bin (see :func:`_pseudo_bin`): the column ``floor((azimuth - phase)
    / step + 0.5) mod columns`` at the bin's start, whether a column boundary lies inside
    the bin (1), none (0) or several (-1), and the unit vector of that boundary."""
    # A bin spans at most 8 / bins radians: at most half a step, so one boundary at most.
    bins = 4 * math.ceil(4.0 / step)
    p = np.arange(bins + 1) * (4.0 / bins)
    x = np.select([p < 1, p < 2, p < 3], [1 - p, 1 - p, p - 3], p - 3)
    y = np.select([p < 1, p < 2, p < 3], [p, 2 - p, 2 - p], p - 4)
    angle = np.arctan2(y, x)
    low, high = angle[:-1].copy(), angle[1:].copy()
    low[bins // 2] = -math.pi  # the lower half-turn starts at -pi (atan2's seam)
    first = np.floor((low - phase) / step + 0.5)
    last = np.floor((high - phase) / step + 0.5)
    crosses = (last - first).astype(np.int64)
    crosses[(crosses < 0) | (crosses > 1)] = -1
    boundary = phase + (first + 0.5) * step
    column = first.astype(np.int64) % columns
    return column, crosses, np.cos(boundary), np.sin(boundary)


@numba.njit(cache=True, nogil=True, inline="always")
def _pseudo_bin(x, y, bins):  # pragma: no cover - numba
    # The bin of the direction (x, y) (not both 0) among `bins` of the pseudo-angle, a
    # quantity monotone in the angle from +x counter-clockwise, in [0, 4), without
    # trigonometry.
    share = abs(y) / (abs(x) + abs(y))
    base = 0.0 if x >= 0.0 and y >= 0.0 else (4.0 if x >= 0.0 else 2.0)
    angle = base + share if (x >= 0.0) == (y >= 0.0) else base - share
    return min(int(angle * (bins / 4.0)), bins - 1)


@numba.njit(cache=True, nogil=True, inline="always")
def _column_at(x, y, first, cross, bound_cos, bound_sin, columns, step, phase):
    # pragma: no cover - numba
    # Sensor.cells' column of the direction (x, y) from its pseudo-angle bin's entries.
    if cross < 0:
        return math.floor((math.atan2(y, x) - phase) / step + 0.5) % columns
    c = first + cross * (bound_cos * y - bound_sin * x >= 0.0)
    return c - columns if c >= columns else c


@numba.njit(cache=True, nogil=True, inline="always")
def _cone(x, y, z, radius, per_radian, offset_lo, offset_hi):  # pragma: no cover - numba
    # The directions, from any beam origin, whose rays pass within `radius` of the point
    # (x, y, z) (relative to the mount): those within a = asin(radius / d) of the point's
    # direction, d its distance from the origin. Returns their azimuth half-width in columns
    # (inf: every azimuth) and a range of elevation tangents that holds theirs. The
    # half-width, asin(radius / horizontal), is the same from every origin (they differ in
    # height only); its tangent bounds it from above. The tangents of elevation e +- a differ
    # from s = tan(e) by t (1 + s^2) / (1 -+ s t), t = tan(a): at most by t (1 + s^2) /
    # (1 - |s| t).
    grown = radius * (1.0 + 1e-9) + 1e-12  # clear of rounding at the cone's edge
    g2 = grown * grown
    h2 = x * x + y * y
    half = grown / math.sqrt(h2 - g2) * per_radian if h2 > g2 else np.inf
    reach = max(abs(offset_lo), abs(offset_hi))
    if reach > 0.0:
        near = max(math.sqrt(h2 + z * z) - reach, 0.0)
        near2 = near * near
    else:
        near2 = h2 + z * z
    if near2 <= g2 or h2 <= 0.0:
        return half, -np.inf, np.inf
    tangent = grown / math.sqrt(near2 - g2)
    inverse = 1.0 / math.sqrt(h2)
    slope_a = (z - offset_lo) * inverse
    slope_b = (z - offset_hi) * inverse
    steep = max(abs(slope_a), abs(slope_b))
    below = 1.0 - steep * tangent
    if below <= 0.0:
        return half, -np.inf, np.inf
    spread = tangent * (1.0 + steep * steep) / below
    return half, min(slope_a, slope_b) - spread, max(slope_a, slope_b) + spread


@numba.njit(cache=True, nogil=True)
def _render(
    xyz,
    radii,
    edge_slopes,
    edge_lut,
    beam_slopes,
    beam_lut,
    offsets,
    mount,
    beam_cos,
    beam_sin,
    column_cos,
    column_sin,
    first,
    crosses,
    bound_cos,
    bound_sin,
    constants,
):  # pragma: no cover - numba
    # The nearest element each ray crosses: beam, column, depth along the ray and the point,
    # beam by beam, columns in the object's window order (counter-clockwise).
    n, beams, columns, bins = xyz.shape[0], offsets.shape[0], column_cos.shape[0], first.shape[0]
    step, phase, per_radian = constants[0], constants[1], constants[4]
    lut_start, lut_scale, lut_bins = constants[7], constants[8], beam_lut.shape[0]
    beam_first = np.empty(n, np.int64)
    beam_last = np.empty(n, np.int64)
    start = np.empty(n, np.int64)
    count = np.empty(n, np.int64)
    # 1. Each point's window of rays (the beams with elevations in its cone, the columns
    #    within its half-width plus half a column of its direction's column), and the beams
    #    and (unwrapped) columns of all of them.
    beam_lo, beam_hi, lo, hi, reference, referenced = beams, -1, 0, -1, 0, False
    for i in range(n):
        x, y, z = xyz[i, 0] - mount[0], xyz[i, 1] - mount[1], xyz[i, 2] - mount[2]
        half, low, high = _cone(x, y, z, radii[i], per_radian, constants[2], constants[3])
        k = _lut_bin(high, lut_start, lut_scale, lut_bins)
        if k < 0:
            b0 = beams
        elif k >= lut_bins:
            b0 = 0
        else:
            b0 = int(beam_lut[k, 0]) + (beam_lut[k, 1] > high) + (beam_lut[k, 2] > high)
        b1 = b0 - 1
        while b1 + 1 < beams and beam_slopes[b1 + 1] >= low:
            b1 += 1
        beam_first[i], beam_last[i] = b0, b1
        if b0 > b1:
            continue
        if half * 2.0 + 2.0 >= columns:
            c0, count[i] = 0, columns
        else:
            reach = int(half + 0.5)
            k = _pseudo_bin(x, y, bins)
            centre = _column_at(
                x, y, first[k], crosses[k], bound_cos[k], bound_sin[k], columns, step, phase
            )
            c0, count[i] = centre - reach, 2 * reach + 1
        if not referenced:  # (c0 may be negative: a window across column 0)
            reference, referenced = c0, True
            lo, hi = c0, c0
        # unwrapped next to the first point's window
        shift = c0 - reference
        if shift >= columns // 2:
            shift -= columns
        elif shift < -(columns // 2):
            shift += columns
        start[i] = reference + shift
        lo, hi = min(lo, start[i]), max(hi, start[i] + count[i] - 1)
        beam_lo, beam_hi = min(beam_lo, b0), max(beam_hi, b1)
    if beam_hi < 0:
        empty = np.empty(0, np.int64)
        return empty, empty, np.empty(0), empty
    full = hi - lo + 1 >= columns
    width = columns if full else hi - lo + 1
    depth = np.full((beam_hi - beam_lo + 1, width), np.inf)
    source = np.full((beam_hi - beam_lo + 1, width), -1, np.int64)
    # 2. Each point against the rays of its window.
    for i in range(n):
        if beam_first[i] > beam_last[i]:
            continue
        r2 = radii[i] * radii[i]
        vx, vy = xyz[i, 0] - mount[0], xyz[i, 1] - mount[1]
        c0 = start[i] % columns  # start lies within a few turns of 0
        w0 = c0 if full else start[i] - lo
        for b in range(beam_first[i], beam_last[i] + 1):
            vz = xyz[i, 2] - mount[2] - offsets[b]
            vv = vx * vx + vy * vy + vz * vz
            ce, se = beam_cos[b], beam_sin[b]
            row = b - beam_lo
            c, w = c0, w0
            for _ in range(count[i]):
                t = ce * (vx * column_cos[c] + vy * column_sin[c]) + se * vz
                if t > 0.0 and vv - t * t <= r2 and t < depth[row, w]:
                    depth[row, w] = t
                    source[row, w] = i
                c += 1  # the next column, counter-clockwise, without a modulo
                w += 1
                if c == columns:
                    c = 0
                    if full:
                        w = 0
    # 3. The hits, in order.
    hits = 0
    for b in range(depth.shape[0]):
        for w in range(width):
            hits += source[b, w] >= 0
    beam_out = np.empty(hits, np.int64)
    column_out = np.empty(hits, np.int64)
    depth_out = np.empty(hits)
    source_out = np.empty(hits, np.int64)
    m = 0
    for b in range(depth.shape[0]):
        for w in range(width):
            if source[b, w] >= 0:
                beam_out[m] = beam_lo + b
                column_out[m] = w if full else (lo + w) % columns
                depth_out[m] = depth[b, w]
                source_out[m] = source[b, w]
                m += 1
    return beam_out, column_out, depth_out, source_out


@numba.njit(cache=True, nogil=True)
def _returns(
    beam,
    column,
    depth,
    source,
    noise,
    lost,
    points,
    limits,
    edge_slopes,
    edge_lut,
    beam_slopes,
    beam_lut,
    offsets,
    mount,
    beam_cos,
    beam_sin,
    column_cos,
    column_sin,
    first,
    crosses,
    bound_cos,
    bound_sin,
    constants,
):  # pragma: no cover - numba
    # The recorded returns: each hit moved along its ray by its noise, unless lost (dropout,
    # or out of the sensor's range), with the features of the point it hit.
    m = 0
    keep = np.zeros(beam.shape[0], np.bool_)
    position = np.empty((beam.shape[0], 3))
    for k in range(beam.shape[0]):
        b, c = beam[k], column[k]
        t = depth[k] + noise[k]
        x = mount[0] + t * beam_cos[b] * column_cos[c]
        y = mount[1] + t * beam_cos[b] * column_sin[c]
        z = mount[2] + offsets[b] + t * beam_sin[b]
        dx, dy, dz = x - mount[0], y - mount[1], z - mount[2]
        distance = math.sqrt(dx * dx + dy * dy + dz * dz)
        if lost[k] or t <= 0.0 or not limits[0] <= distance <= limits[1]:
            continue
        keep[k] = True
        position[k, 0], position[k, 1], position[k, 2] = x, y, z
        m += 1
    returns = np.empty((m, points.shape[1]), np.float32)
    kept_source = np.empty(m, np.int64)
    j = 0
    for k in range(beam.shape[0]):
        if not keep[k]:
            continue
        returns[j, 0], returns[j, 1], returns[j, 2] = position[k, 0], position[k, 1], position[k, 2]
        returns[j, 3:] = points[source[k], 3:]
        kept_source[j] = source[k]
        j += 1
    return returns, kept_source


@numba.njit(cache=True, nogil=True)
def _voxel_radii(xyz, starts, voxel, factor, low, high, out):  # pragma: no cover - numba
    # Per group of points xyz[starts[g]:starts[g + 1]] (one object each): the points in each
    # point's voxel and its 26 neighbours, counted on a dense grid over the group's extent
    # (one voxel of margin), or on its sorted occupied voxels when that grid would be large.
    for g in range(starts.shape[0] - 1):
        a, z = starts[g], starts[g + 1]
        if z <= a:
            continue
        lo = np.empty(3)
        size = np.empty(3, np.int64)
        for axis in range(3):
            lo[axis] = xyz[a:z, axis].min() / voxel
            size[axis] = math.floor(xyz[a:z, axis].max() / voxel - lo[axis]) + 3
        key = np.empty(z - a, np.int64)
        for i in range(a, z):
            ix = math.floor(xyz[i, 0] / voxel - lo[0]) + 1
            iy = math.floor(xyz[i, 1] / voxel - lo[1]) + 1
            iz = math.floor(xyz[i, 2] / voxel - lo[2]) + 1
            key[i - a] = (ix * size[1] + iy) * size[2] + iz
        strides = (size[1] * size[2], size[2], 1)
        cells = size[0] * size[1] * size[2]
        if cells <= 4 * (z - a) + 16384:
            grid = np.zeros(cells, np.int32)
            for j in range(z - a):
                grid[key[j]] += 1
            # the 27-voxel sums by three passes of 3-voxel sums (z, y, x); exact in the
            # interior, where every point's voxel lies (the margin is one voxel)
            total = np.zeros(cells, np.int32)
            for c in range(1, cells - 1):
                total[c] = grid[c - 1] + grid[c] + grid[c + 1]
            for c in range(strides[1], cells - strides[1]):
                grid[c] = total[c - strides[1]] + total[c] + total[c + strides[1]]
            for c in range(strides[0], cells - strides[0]):
                total[c] = grid[c - strides[0]] + grid[c] + grid[c + strides[0]]
            for j in range(z - a):
                out[a + j] = _radius(total[key[j]], voxel, factor, low, high)
        else:
            ordered = np.sort(key)
            for j in range(z - a):
                k = 0
                for dx in range(-1, 2):
                    for dy in range(-1, 2):
                        for dz in range(-1, 2):
                            near = key[j] + dx * strides[0] + dy * strides[1] + dz
                            k += np.searchsorted(ordered, near, side="right") - np.searchsorted(
                                ordered, near, side="left"
                            )
                out[a + j] = _radius(k, voxel, factor, low, high)


@numba.njit(cache=True, nogil=True, inline="always")
def _radius(count, voxel, factor, low, high):  # pragma: no cover - numba
    return min(max(factor * 3.0 * voxel / math.sqrt(count), low), high)
