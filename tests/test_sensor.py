"""The synthetic world's LiDAR presets (drcpo.synth.sensor): the published HDL-32E and the
HDL-64E model, and sweeps that fall on their beams."""

from __future__ import annotations

import numpy as np
import pytest

from drcpo.errors import ConfigError
from drcpo.synth import (
    HDL32E_MOUNT_HEIGHT,
    LidarConfig,
    generate_world,
    hdl32e_elevations,
    hdl64e_elevations,
    lidar_preset,
    scan,
)


def nearest_beams(points: np.ndarray, elevations_deg) -> tuple[np.ndarray, np.ndarray]:
    """Per point, the beam (0: the top one) whose elevation, seen from the origin, lies nearest
    its own, and the miss in degrees."""
    beams = np.sort(np.asarray(elevations_deg, dtype=np.float64))[::-1]
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    elevation = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    miss = np.abs(elevation[:, None] - beams[None, :])
    beam = miss.argmin(axis=1)
    return beam, miss[np.arange(len(beam)), beam]


def test_unknown_preset_names_the_presets():
    with pytest.raises(ConfigError, match="unknown sensor 'vlp16'; presets: hdl32e, hdl64e"):
        lidar_preset("vlp16")


def test_hdl32e_preset_matches_the_published_specification():
    """The HDL-32E user manual: 32 lasers from +10.67 to -30.67 degrees (41.3 degrees of
    vertical field), 4/3 degree apart; nuScenes' sweeps at 20 Hz: about 1080 points per ring."""
    config = lidar_preset("hdl32e")
    degrees = np.asarray(config.elevations_deg)
    assert config.num_beams == 32 and config.elevations_deg == hdl32e_elevations()
    assert degrees[0] == pytest.approx(10.67) and degrees[-1] == pytest.approx(-30.67)
    assert degrees[0] - degrees[-1] == pytest.approx(41.34)
    np.testing.assert_allclose(np.diff(degrees), -4.0 / 3.0, atol=0.01)
    assert 0.0 in hdl32e_elevations()  # the manual's reference laser, level
    assert config.num_columns == 1080
    assert (config.range_noise, config.max_range) == (0.02, 100.0)
    assert config.mount_height == HDL32E_MOUNT_HEIGHT == pytest.approx(1.84)


def test_hdl64e_is_the_default_model():
    assert lidar_preset("hdl64e") == LidarConfig()
    degrees = np.asarray(hdl64e_elevations())
    assert len(degrees) == 64 and degrees[0] == 2.0 and degrees[-1] == -24.9
    assert (np.diff(degrees) < 0).all()
    # the upper block about 1/3 degree apart, the lower about 1/2
    assert np.diff(degrees[:32]).mean() == pytest.approx(-10.33 / 31)
    assert np.diff(degrees[32:]).mean() == pytest.approx(-16.03 / 31)


@pytest.mark.parametrize("name", ["hdl32e", "hdl64e"])
def test_a_synthetic_sweep_falls_on_the_presets_rings(rng, name):
    """Every return of a sweep lies on the beam it was fired from (its elevation seen from the
    origin, noise aside) and the sweep has one return per ray at most."""
    config = lidar_preset(name)
    world = generate_world(rng, mount_height=config.mount_height)
    sweep = scan(world, rng, config)
    beam, miss = nearest_beams(sweep.points, config.elevations_deg)
    rank = np.argsort(np.argsort(-np.asarray(config.elevations_deg)))
    np.testing.assert_array_equal(beam, rank[sweep.ray // config.num_columns])
    assert np.median(miss) < 0.05
    assert len(np.unique(sweep.ray)) == len(sweep.ray) <= config.num_rays
    distance = np.linalg.norm(sweep.points[:, :3], axis=1)
    assert distance.min() >= config.min_range - 0.2
