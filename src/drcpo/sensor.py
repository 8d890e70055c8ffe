"""The LiDAR that recorded a frame: its beams, azimuth step, mount, range noise and dropout.

Sensor-true augmentation (``self_occlusion.mode: sensor``)
renders inserted objects through this model, so that they carry the frame's scan lines and the
density its sensor gives at their distance. A beam ``b`` is a cone of rays leaving the point
``mount + (0, 0, offsets[b])`` at elevation ``elevations[b]`` above the horizontal, one ray per
azimuth column ``c`` at ``azimuth = phase + c * azimuth_step``. Presets name real sensors
(``hdl64e``: KITTI's; ``hdl32e``: nuScenes' LIDAR_TOP); the synthetic world's sensor is one of
them. :mod:`drcpo.sensor_config` holds the config
section ``drcpo.sensor`` and ``auto``, the sensor estimated from a frame's own points.

Units: radians and metres throughout (the YAML keys say ``_deg`` where they take degrees).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from drcpo.errors import ConfigError

__all__ = [
    "HDL32E_MOUNT_HEIGHT",
    "SENSOR_PRESETS",
    "Sensor",
    "hdl32e_elevations_deg",
    "hdl64e_elevations_deg",
    "sensor_preset",
]

#: Height of nuScenes' LIDAR_TOP above the ground, metres: its calibrated_sensor translation
#: in the ego frame (origin on the ground under the rear axle) has z of about 1.84.
HDL32E_MOUNT_HEIGHT = 1.84


@functools.cache
def hdl64e_elevations_deg() -> tuple[float, ...]:
    """The 64 beam elevations (degrees) of a Velodyne HDL-64E, +2.0 down to -24.9.

    Two laser blocks: the upper 32 beams about 1/3 degree apart (+2.0 to -8.33), the lower 32
    about 1/2 degree apart (-8.87 to -24.9).
    """
    upper = np.linspace(2.0, -8.33, 32)
    lower = np.linspace(-8.87, -24.9, 32)
    return tuple(float(round(v, 4)) for v in np.concatenate([upper, lower]))


def hdl32e_elevations_deg() -> tuple[float, ...]:
    """The 32 beam elevations (degrees) of a Velodyne HDL-32E, +10.67 down to -30.67.

    The user manual's table of vertical angles (sorted, firing order aside): 4/3 degree apart,
    laser 9 from the top level; the values as the manual rounds them.
    """
    return _HDL32E_ELEVATIONS_DEG


_HDL32E_ELEVATIONS_DEG = (
    *(10.67, 9.33, 8.0, 6.67, 5.33, 4.0, 2.67, 1.33, 0.0, -1.33, -2.67, -4.0, -5.33, -6.66),
    *(-8.0, -9.33, -10.67, -12.0, -13.33, -14.67, -16.0, -17.33, -18.67, -20.0, -21.33),
    *(-22.67, -24.0, -25.33, -26.66, -28.0, -29.33, -30.67),
)


@dataclass(frozen=True, eq=False)
class Sensor:
    """A rotating multi-beam LiDAR (read-only arrays; safe to share between threads).

    Attributes:
        elevations: ``float64 (B,)`` beam elevations, radians, strictly descending (beam 0 is
            the top one).
        offsets: ``float64 (B,)`` height of each beam's origin above ``mount``, metres (0 for
            the presets; KITTI's lasers sit a few cm apart, which ``auto`` may fit).
        azimuth_step: radians between two firings of a beam.
        phase: azimuth of column 0, radians in ``[0, azimuth_step)``.
        mount: ``float64 (3,)`` the sensor's position in the LiDAR frame, metres (KITTI: the
            origin).
        range_noise: standard deviation of the Gaussian range error, metres.
        dropout: probability that a return is lost.
        min_range, max_range: returns nearer / farther than these are never recorded, metres.
        name: the preset's name, or ``"auto"`` / ``"custom"``.
    """

    elevations: np.ndarray
    offsets: np.ndarray | None
    azimuth_step: float
    phase: float = 0.0
    mount: np.ndarray | None = None
    range_noise: float = 0.02
    dropout: float = 0.03
    min_range: float = 1.0
    max_range: float = 120.0
    name: str = "custom"

    def __post_init__(self) -> None:
        elevations = np.array(self.elevations, dtype=np.float64).reshape(-1)
        offsets = np.array(
            np.zeros_like(elevations) if self.offsets is None else self.offsets, dtype=np.float64
        ).reshape(-1)
        mount = np.array((0.0, 0.0, 0.0) if self.mount is None else self.mount, dtype=np.float64)
        where = f"sensor {self.name!r}"
        if len(elevations) == 0 or not np.isfinite(elevations).all():
            raise ConfigError(f"{where}: elevations must be a non-empty list of finite numbers")
        if (np.abs(elevations) >= math.pi / 2).any():
            raise ConfigError(f"{where}: elevations must lie strictly within (-90, 90) degrees")
        if len(elevations) > 1 and not (np.diff(elevations) < 0).all():
            raise ConfigError(f"{where}: elevations must be distinct, listed top beam first")
        if offsets.shape != elevations.shape or not np.isfinite(offsets).all():
            raise ConfigError(f"{where}: offsets must be one finite number per beam")
        if mount.shape != (3,) or not np.isfinite(mount).all():
            raise ConfigError(f"{where}: mount must be three finite numbers (x, y, z)")
        checks = {
            "azimuth_step": 1e-4 <= self.azimuth_step <= math.radians(10.0),
            "phase": 0.0 <= self.phase < max(self.azimuth_step, 1e-12),
            "range_noise": 0.0 <= self.range_noise <= 1.0,
            "dropout": 0.0 <= self.dropout < 1.0,
            "min_range": 0.0 <= self.min_range < self.max_range,
            "max_range": self.max_range <= 1000.0,
        }
        for key, ok in checks.items():
            if not ok:
                raise ConfigError(f"{where}: {key} = {getattr(self, key)!r} is out of range")
        for array in (elevations, offsets, mount):
            array.setflags(write=False)
        object.__setattr__(self, "elevations", elevations)
        object.__setattr__(self, "offsets", offsets)
        object.__setattr__(self, "mount", mount)

    @property
    def num_beams(self) -> int:
        return len(self.elevations)

    @property
    def num_columns(self) -> int:
        """Azimuth columns per revolution."""
        return max(1, round(2.0 * math.pi / self.azimuth_step))

    @property
    def beam_width(self) -> float:
        """Half the smallest gap between neighbouring beams, radians: how far from a beam's
        elevation a return still counts as on it (the whole gap for a one-beam sensor is
        undefined, so 0.5 degree then)."""
        if self.num_beams == 1:
            return math.radians(0.5)
        return float(np.min(-np.diff(self.elevations))) / 2.0

    def beam_edges(self) -> np.ndarray:
        """``float64 (B + 1,)`` elevation boundaries between beams, descending: beam ``b``
        owns elevations in ``(edges[b + 1], edges[b]]``; the outer edges lie half the
        neighbouring gap beyond the extreme beams."""
        e = self.elevations
        if self.num_beams == 1:
            w = self.beam_width
            return np.array([e[0] + w, e[0] - w])
        middle = (e[:-1] + e[1:]) / 2.0
        return np.concatenate(
            [[e[0] + (e[0] - e[1]) / 2.0], middle, [e[-1] - (e[-2] - e[-1]) / 2.0]]
        )

    def cells(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ray cell of each point ``(N, 3+)`` (metres, LiDAR frame): ``beam int64 (N,)``,
        ``column int64 (N,)`` in ``[0, num_columns)`` and ``range float64 (N,)`` from the mount.

        A point's beam is judged by its elevation seen from each beam's own origin: among the
        beams whose elevation band (:meth:`beam_edges`) holds it, the one whose elevation it is
        nearest; -1 when no band does. Without offsets this is the band it lies in.
        """
        points = np.asarray(points)
        x, y, z = (points[:, i].astype(np.float64) - self.mount[i] for i in range(3))
        squared = x * x + y * y
        horizontal = np.sqrt(squared)
        beam = self._beams(z, horizontal)
        azimuth = np.arctan2(y, x) - self.phase
        column = np.floor(azimuth / self.azimuth_step + 0.5).astype(np.int64) % self.num_columns
        return beam, column, np.sqrt(squared + z * z)

    def _beams(self, z: np.ndarray, horizontal: np.ndarray) -> np.ndarray:
        """Beam of each point (see :meth:`cells`) from its height ``z`` over the mount and
        horizontal distance (metres)."""
        edges = self.beam_edges()
        low, high = float(self.offsets.min()), float(self.offsets.max())
        if low == high:
            return _nearest_beam(edges, np.arctan2(z - low, horizontal))
        beam = np.empty(len(z), dtype=np.int64)
        _own_origin_beams(z, horizontal, self.offsets, self.elevations, edges, beam)
        return beam

    def ray_directions(self, beam: np.ndarray, column: np.ndarray) -> np.ndarray:
        """``float64 (K, 3)`` unit directions of the rays of beams ``beam`` and columns
        ``column`` (integer arrays of one shape)."""
        elevation = self.elevations[np.asarray(beam)]
        azimuth = self.phase + np.asarray(column, dtype=np.float64) * self.azimuth_step
        cos_e = np.cos(elevation)
        return np.stack([cos_e * np.cos(azimuth), cos_e * np.sin(azimuth), np.sin(elevation)], -1)

    def ray_origins(self, beam: np.ndarray) -> np.ndarray:
        """``float64 (K, 3)`` where the rays of beams ``beam`` start (mount plus offset)."""
        origins = np.broadcast_to(self.mount, (len(np.asarray(beam)), 3)).copy()
        origins[:, 2] += self.offsets[np.asarray(beam)]
        return origins


def _band(edges: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    """Index ``k`` of the band ``(edges[k + 1], edges[k]]`` holding each elevation: -1 above
    ``edges[0]``, ``B`` at or below ``edges[-1]`` (``edges`` descending, ``B + 1`` of them)."""
    # edges descend; searchsorted wants ascending
    return np.searchsorted(-edges, -elevation, side="right").astype(np.int64) - 1


def _nearest_beam(edges: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    """Beam owning each elevation (see :meth:`Sensor.beam_edges`), -1 outside them all."""
    k = _band(edges, elevation)
    k[k >= len(edges) - 1] = -1
    return k


@nb.njit(cache=True, nogil=True)
def _own_origin_beams(z, horizontal, offsets, elevations, edges, out):  # pragma: no cover
    """:meth:`Sensor.cells`' beams when the beams' origins differ: per point, of the beams
    between those its elevation seen from the lowest and from the highest origin falls in (no
    other can hold it), the band holding its elevation seen from the beam's own origin,
    nearest the beam's elevation; -1 when none does."""
    low, high = offsets.min(), offsets.max()
    beams = len(elevations)
    for i in range(len(z)):
        first = max(_band_of(edges, math.atan2(z[i] - low, horizontal[i])), 0)
        last = min(_band_of(edges, math.atan2(z[i] - high, horizontal[i])), beams - 1)
        best, best_miss = -1, math.inf
        for b in range(first, last + 1):
            own = math.atan2(z[i] - offsets[b], horizontal[i])
            miss = abs(own - elevations[b])
            if edges[b + 1] < own <= edges[b] and miss < best_miss:
                best, best_miss = b, miss
        out[i] = best


@nb.njit(cache=True, nogil=True, inline="always")
def _band_of(edges, elevation):  # pragma: no cover - numba
    """:func:`_band` of one elevation: -1 above ``edges[0]``, ``B`` at or below ``edges[-1]``."""
    lo, hi = 0, len(edges)  # first edge below the elevation: the band is that index - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if edges[mid] < elevation:
            hi = mid
        else:
            lo = mid + 1
    return lo - 1


def _hdl64e() -> Sensor:
    return Sensor(
        elevations=np.radians(hdl64e_elevations_deg()),
        offsets=None,
        # a whole number of columns per turn, as the world's sweep fires them
        azimuth_step=2.0 * math.pi / round(360.0 / 0.17),
        name="hdl64e",
    )


def _hdl32e() -> Sensor:
    return Sensor(
        elevations=np.radians(hdl32e_elevations_deg()),
        offsets=None,
        # 20 Hz: one firing of the 32 lasers every 46.08 us, about 1085 per turn; nuScenes'
        # sweeps hold about 1080 points per ring, so 1080 columns (1/3 degree)
        azimuth_step=2.0 * math.pi / 1080,
        range_noise=0.02,  # the spec's +-2 cm
        max_range=100.0,  # the spec's usable returns
        name="hdl32e",
    )


#: Named sensors. ``hdl64e``: KITTI's Velodyne HDL-64E as the synthetic world models it;
#: ``hdl32e``: nuScenes' LIDAR_TOP, a Velodyne HDL-32E at 20 Hz (mounted about
#: :data:`HDL32E_MOUNT_HEIGHT` metres above the ground; its points are in its own frame, so the
#: mount is the origin).
SENSOR_PRESETS = {"hdl32e": _hdl32e, "hdl64e": _hdl64e}


def sensor_preset(name: str) -> Sensor:
    """The :class:`Sensor` of preset ``name`` (see :data:`SENSOR_PRESETS`)."""
    try:
        return SENSOR_PRESETS[name]()
    except KeyError:
        raise ConfigError(
            f"unknown sensor {name!r}; presets: {', '.join(sorted(SENSOR_PRESETS))}"
        ) from None
