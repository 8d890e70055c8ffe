"""A rotating multi-beam LiDAR, by default KITTI's Velodyne HDL-64E; :func:`lidar_preset`
also gives nuScenes' 32-beam HDL-32E (``"hdl32e"``).

The sensor sits at the origin of the LiDAR frame (x forward, y left, z up) and is mounted
``mount_height`` metres above the ground. One sweep fires every beam at every azimuth column.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from drcpo.errors import ConfigError
from drcpo.sensor import (
    HDL32E_MOUNT_HEIGHT,
    Sensor,
    hdl32e_elevations_deg,
    hdl64e_elevations_deg,
    sensor_preset,
)

__all__ = [
    "LIDAR_PRESETS",
    "LidarConfig",
    "RayGrid",
    "hdl64e_elevations",
    "lidar_preset",
    "ray_grid",
]


def hdl64e_elevations() -> tuple[float, ...]:
    """The 64 beam elevations (degrees) of an HDL-64E, +2.0 down to -24.9 (the ``hdl64e``
    preset's, :func:`drcpo.sensor.hdl64e_elevations_deg`)."""
    return hdl64e_elevations_deg()


@dataclass(frozen=True)
class LidarConfig:
    """Sensor model parameters.

    Attributes:
        elevations_deg: beam elevations, degrees (one per beam).
        azimuth_step_deg: angle between successive firings of a beam, degrees (HDL-64E at
            10 Hz: about 0.08 to 0.17 depending on the mode).
        mount_height: sensor height above the ground, metres.
        max_range: returns beyond this range are lost, metres.
        min_range: returns closer than this are discarded (the sensor's blind zone), metres.
        range_noise: standard deviation of the Gaussian range error, metres.
        dropout: probability that any return is lost, before material and incidence effects.
        intensity_noise: standard deviation of the additive intensity noise.
    """

    elevations_deg: tuple[float, ...] = field(default_factory=hdl64e_elevations)
    azimuth_step_deg: float = 0.17
    mount_height: float = 1.73
    max_range: float = 120.0
    min_range: float = 1.0
    range_noise: float = 0.02
    dropout: float = 0.03
    intensity_noise: float = 0.02

    def __post_init__(self) -> None:
        elevations = np.asarray(self.elevations_deg, dtype=np.float64)
        if elevations.ndim != 1 or len(elevations) == 0 or not np.isfinite(elevations).all():
            raise ConfigError("LidarConfig.elevations_deg must be a non-empty list of numbers")
        if (np.abs(elevations) >= 90).any():
            raise ConfigError("LidarConfig.elevations_deg must lie strictly within (-90, 90)")
        checks = {
            "azimuth_step_deg": 0.01 <= self.azimuth_step_deg <= 10.0,
            "mount_height": 0.0 < self.mount_height <= 10.0,
            "max_range": self.min_range < self.max_range <= 1000.0,
            "min_range": self.min_range >= 0.0,
            "range_noise": 0.0 <= self.range_noise <= 1.0,
            "dropout": 0.0 <= self.dropout < 1.0,
            "intensity_noise": 0.0 <= self.intensity_noise <= 1.0,
        }
        for name, ok in checks.items():
            if not ok:
                raise ConfigError(f"LidarConfig.{name} = {getattr(self, name)!r} is out of range")

    @property
    def num_beams(self) -> int:
        return len(self.elevations_deg)

    @property
    def num_columns(self) -> int:
        """Azimuth columns per sweep."""
        return round(360.0 / self.azimuth_step_deg)

    @property
    def num_rays(self) -> int:
        return self.num_beams * self.num_columns

    def sensor(self, azimuth_offset: float = 0.0) -> Sensor:
        """The :class:`~drcpo.sensor.Sensor` firing exactly the rays of
        ``ray_grid(self, azimuth_offset)``: ray (beam ``b``, column ``c``) of the grid is the
        sensor's ray cell (beam rank of ``b`` by elevation, top first; the column of its
        azimuth), with this range noise, dropout and range limits, at the origin.
        """
        step = 2.0 * math.pi / self.num_columns
        elevations = np.sort(np.radians(np.asarray(self.elevations_deg, dtype=np.float64)))
        return Sensor(
            elevations=elevations[::-1],
            offsets=None,
            azimuth_step=step,
            # ray_grid's column c points at -pi + (c + 1/2) step + offset
            phase=float((0.5 * step + azimuth_offset - math.pi) % step) % step,
            range_noise=self.range_noise,
            dropout=self.dropout,
            min_range=self.min_range,
            max_range=self.max_range,
            name="synthetic",
        )


def _hdl32e() -> LidarConfig:
    preset = sensor_preset("hdl32e")
    return LidarConfig(
        elevations_deg=hdl32e_elevations_deg(),
        # the preset's whole number of columns (1080) per turn
        azimuth_step_deg=360.0 / preset.num_columns,
        mount_height=HDL32E_MOUNT_HEIGHT,
        max_range=preset.max_range,
        min_range=preset.min_range,
        range_noise=preset.range_noise,
        dropout=preset.dropout,
    )


#: The synthetic world's sensors by the name of the :mod:`drcpo.sensor` preset they emulate.
LIDAR_PRESETS = {"hdl32e": _hdl32e, "hdl64e": LidarConfig}


def lidar_preset(name: str) -> LidarConfig:
    """The :class:`LidarConfig` emulating sensor preset ``name`` (``"hdl64e"``: KITTI's, the
    default; ``"hdl32e"``: nuScenes' LIDAR_TOP, 32 beams, 1080 columns, 1.84 m above the
    ground). Its :meth:`LidarConfig.sensor` fires the preset's beams and columns."""
    try:
        return LIDAR_PRESETS[name]()
    except KeyError:
        raise ConfigError(
            f"unknown sensor {name!r}; presets: {', '.join(sorted(LIDAR_PRESETS))}"
        ) from None


@dataclass(frozen=True, eq=False)
class RayGrid:
    """The rays of one sweep, beam-major: ray ``b * num_columns + c`` is beam b, column c.

    Attributes:
        directions: ``float64 (R, 3)`` unit vectors.
        azimuth: ``float64 (num_columns,)`` column azimuths in ``[-pi, pi)``, ascending, radians.
        elevation: ``float64 (num_beams,)`` beam elevations, radians.
    """

    directions: np.ndarray
    azimuth: np.ndarray
    elevation: np.ndarray

    @property
    def num_columns(self) -> int:
        return len(self.azimuth)


def ray_grid(config: LidarConfig, azimuth_offset: float = 0.0) -> RayGrid:
    """Unit ray directions of one sweep; ``azimuth_offset`` (radians) shifts every column.

    A real sensor does not start each sweep at the same angle, so callers pass a random offset
    in ``[0, step)`` per frame.
    """
    step = 2.0 * np.pi / config.num_columns
    azimuth = -np.pi + (np.arange(config.num_columns) + 0.5) * step + azimuth_offset
    azimuth = (azimuth + np.pi) % (2.0 * np.pi) - np.pi
    azimuth.sort()
    elevation = np.deg2rad(np.asarray(config.elevations_deg, dtype=np.float64))
    cos_e = np.cos(elevation)[:, None]
    directions = np.stack(
        [
            cos_e * np.cos(azimuth)[None, :],
            cos_e * np.sin(azimuth)[None, :],
            np.broadcast_to(np.sin(elevation)[:, None], (len(elevation), len(azimuth))),
        ],
        axis=-1,
    ).reshape(-1, 3)
    return RayGrid(directions, azimuth, elevation)
