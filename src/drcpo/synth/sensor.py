"""A rotating multi-beam LiDAR, by default KITTI's Velodyne HDL-64E; :func:`lidar_preset`
also gives nuScenes' 32-beam HDL-32E (``"hdl32e"``).

The sensor sits at the origin of the LiDAR frame (x forward, y left, z up) and is mounted
``mount_height`` metres above the ground. One sweep fires every beam at every azimuth column.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from drcpo.errors import ConfigError

__all__ = [
    "HDL32E_MOUNT_HEIGHT",
    "LIDAR_PRESETS",
    "LidarConfig",
    "RayGrid",
    "hdl32e_elevations",
    "hdl64e_elevations",
    "lidar_preset",
    "ray_grid",
]


#: Height of nuScenes' LIDAR_TOP above the ground, metres: its calibrated_sensor translation
#: in the ego frame (origin on the ground under the rear axle) has z of about 1.84.
HDL32E_MOUNT_HEIGHT = 1.84


@functools.cache
def hdl64e_elevations() -> tuple[float, ...]:
    """The 64 beam elevations (degrees) of a Velodyne HDL-64E, +2.0 down to -24.9.

    Two laser blocks: the upper 32 beams about 1/3 degree apart (+2.0 to -8.33), the lower 32
    about 1/2 degree apart (-8.87 to -24.9).
    """
    upper = np.linspace(2.0, -8.33, 32)
    lower = np.linspace(-8.87, -24.9, 32)
    return tuple(float(round(v, 4)) for v in np.concatenate([upper, lower]))


def hdl32e_elevations() -> tuple[float, ...]:
    """The 32 beam elevations (degrees) of a Velodyne HDL-32E, +10.67 down to -30.67.

    The user manual's table of vertical angles (sorted, firing order aside): 4/3 degree apart,
    laser 9 from the top level; the values as the manual rounds them.
    """
    return _HDL32E_ELEVATIONS


_HDL32E_ELEVATIONS = (
    *(10.67, 9.33, 8.0, 6.67, 5.33, 4.0, 2.67, 1.33, 0.0, -1.33, -2.67, -4.0, -5.33, -6.66),
    *(-8.0, -9.33, -10.67, -12.0, -13.33, -14.67, -16.0, -17.33, -18.67, -20.0, -21.33),
    *(-22.67, -24.0, -25.33, -26.66, -28.0, -29.33, -30.67),
)


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


def _hdl32e() -> LidarConfig:
    return LidarConfig(
        elevations_deg=hdl32e_elevations(),
        # 20 Hz: one firing of the 32 lasers every 46.08 us, about 1085 per turn; nuScenes'
        # sweeps hold about 1080 points per ring, so 1080 columns (1/3 degree)
        azimuth_step_deg=360.0 / 1080,
        mount_height=HDL32E_MOUNT_HEIGHT,
        max_range=100.0,  # the spec's usable returns
        min_range=1.0,
        range_noise=0.02,  # the spec's +-2 cm
        dropout=0.03,
    )


#: The synthetic world's sensors: ``hdl64e`` (KITTI's Velodyne HDL-64E) and ``hdl32e``
#: (nuScenes' LIDAR_TOP, a Velodyne HDL-32E at 20 Hz).
LIDAR_PRESETS = {"hdl32e": _hdl32e, "hdl64e": LidarConfig}


def lidar_preset(name: str) -> LidarConfig:
    """The :class:`LidarConfig` emulating sensor preset ``name`` (``"hdl64e"``: KITTI's, the
    default; ``"hdl32e"``: nuScenes' LIDAR_TOP, 32 beams, 1080 columns, 1.84 m above the
    ground)."""
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
