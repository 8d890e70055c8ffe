"""The LiDAR model (drcpo.sensor): validation, ray cells against a per-point reference, the
synthetic world's sensor, ``sensor: auto`` on KITTI and synthetic frames, the config section."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drcpo.config_fields import from_dict, to_dict
from drcpo.errors import ConfigError, DataError
from drcpo.sensor import (
    HDL32E_MOUNT_HEIGHT,
    Sensor,
    hdl32e_elevations_deg,
    hdl64e_elevations_deg,
    sensor_preset,
)
from drcpo.sensor_config import SensorConfig, estimate_sensor
from drcpo.synth import (
    LidarConfig,
    generate_world,
    hdl64e_elevations,
    lidar_preset,
    ray_grid,
    scan,
)
from drcpo.synth.dataset import frame_rng

DEG = math.pi / 180.0


def _sensor(**changes) -> Sensor:
    args = {"elevations": np.radians([2.0, 0.0, -3.0]), "offsets": None, "azimuth_step": 0.01}
    return Sensor(**{**args, **changes})


# --------------------------------------------------------------------------------------------
# Sensor
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"elevations": []}, "elevations must be a non-empty"),
        ({"elevations": [0.1, float("nan")]}, "elevations must be a non-empty"),
        ({"elevations": [math.pi / 2, 0.0]}, r"within \(-90, 90\)"),
        ({"elevations": [0.0, 0.1]}, "top beam first"),
        ({"elevations": [0.1, 0.1]}, "distinct"),
        ({"offsets": [0.0, 0.1]}, "one finite number per beam"),
        ({"offsets": [0.0, 0.1, float("inf")]}, "one finite number per beam"),
        ({"mount": [0.0, 1.0]}, "mount must be three finite numbers"),
        ({"azimuth_step": 0.0}, "azimuth_step = 0.0 is out of range"),
        ({"azimuth_step": math.radians(11.0)}, "azimuth_step"),
        ({"phase": 0.01}, "phase = 0.01 is out of range"),
        ({"phase": -1e-9}, "phase"),
        ({"range_noise": -0.1}, "range_noise"),
        ({"dropout": 1.0}, "dropout = 1.0"),
        ({"min_range": 5.0, "max_range": 5.0}, "min_range"),
        ({"max_range": 2000.0}, "max_range"),
    ],
)
def test_sensor_rejects_bad_parameters(changes, match):
    with pytest.raises(ConfigError, match=match):
        _sensor(**changes, name="mine")
    with pytest.raises(ConfigError, match="sensor 'mine'"):
        _sensor(**changes, name="mine")


def test_sensor_arrays_are_read_only_copies():
    elevations = np.radians([2.0, 0.0, -3.0])
    sensor = _sensor(elevations=elevations, offsets=[0.0, 0.1, 0.2], mount=[1.0, 2.0, 3.0])
    elevations[0] = 0.5
    assert sensor.elevations[0] == pytest.approx(2.0 * DEG)
    for array in (sensor.elevations, sensor.offsets, sensor.mount):
        with pytest.raises(ValueError, match="read-only"):
            array[0] = 1.0


def test_unknown_preset_names_the_presets():
    with pytest.raises(ConfigError, match="unknown sensor 'vlp16'; presets: hdl32e, hdl64e"):
        sensor_preset("vlp16")
    with pytest.raises(ConfigError, match="unknown sensor 'vlp16'; presets: hdl32e, hdl64e"):
        lidar_preset("vlp16")


def test_hdl32e_preset_matches_the_published_specification():
    """The HDL-32E user manual: 32 lasers from +10.67 to -30.67 degrees (41.3 degrees of
    vertical field), 4/3 degree apart; nuScenes' sweeps at 20 Hz: about 1080 points per ring."""
    sensor = sensor_preset("hdl32e")
    degrees = np.degrees(sensor.elevations)
    assert sensor.num_beams == 32 and sensor.name == "hdl32e"
    assert degrees[0] == pytest.approx(10.67) and degrees[-1] == pytest.approx(-30.67)
    assert degrees[0] - degrees[-1] == pytest.approx(41.34)
    np.testing.assert_allclose(np.diff(degrees), -4.0 / 3.0, atol=0.01)
    assert 0.0 in hdl32e_elevations_deg()  # the manual's reference laser, level
    assert sensor.num_columns == 1080
    assert math.degrees(sensor.azimuth_step) == pytest.approx(1.0 / 3.0)
    assert sensor.range_noise == 0.02 and not sensor.mount.any() and not sensor.offsets.any()
    assert HDL32E_MOUNT_HEIGHT == pytest.approx(1.84)


def test_synthetic_hdl32e_fires_the_presets_beams_and_columns():
    config, preset = lidar_preset("hdl32e"), sensor_preset("hdl32e")
    assert lidar_preset("hdl64e") == LidarConfig()
    assert config.elevations_deg == hdl32e_elevations_deg()
    assert config.mount_height == HDL32E_MOUNT_HEIGHT
    assert config.num_beams == 32 and config.num_columns == preset.num_columns == 1080
    sensor = config.sensor(0.0)
    np.testing.assert_allclose(sensor.elevations, preset.elevations, atol=1e-15)
    assert sensor.azimuth_step == pytest.approx(preset.azimuth_step, abs=1e-15)
    assert (sensor.max_range, sensor.range_noise) == (preset.max_range, preset.range_noise)


def test_a_synthetic_hdl32e_sweep_falls_on_the_presets_rings(rng):
    """Every return of a 32-beam sweep lies on one of the preset's beams (its elevation seen
    from the origin, noise aside) and the sweep has one return per ray at most."""
    config = lidar_preset("hdl32e")
    world = generate_world(rng, mount_height=config.mount_height)
    sweep = scan(world, rng, config)
    beam, _, distance = sensor_preset("hdl32e").cells(sweep.points)
    assert (beam >= 0).all()
    rank = np.argsort(np.argsort(-np.asarray(config.elevations_deg)))
    np.testing.assert_array_equal(beam, rank[sweep.ray // config.num_columns])
    assert len(np.unique(sweep.ray)) == len(sweep.ray) <= config.num_rays
    assert distance.min() >= config.min_range - 0.2


def test_beam_edges_and_width():
    sensor = _sensor()
    edges = np.degrees(sensor.beam_edges())
    np.testing.assert_allclose(edges, [3.0, 1.0, -1.5, -4.5])
    assert sensor.beam_width == pytest.approx(1.0 * DEG)
    one = _sensor(elevations=[0.1])
    np.testing.assert_allclose(one.beam_edges(), [0.1 + 0.5 * DEG, 0.1 - 0.5 * DEG])


def _reference_cells(sensor: Sensor, points: np.ndarray):
    """Per point and per beam, as :meth:`Sensor.cells` documents: the beam whose band holds the
    point's elevation seen from that beam's own origin, nearest its elevation; -1 if none."""
    edges = sensor.beam_edges()
    beams, columns, ranges = [], [], []
    for x, y, z in np.asarray(points, dtype=np.float64)[:, :3] - sensor.mount:
        horizontal = math.hypot(x, y)
        best, best_miss = -1, math.inf
        for b in range(sensor.num_beams):
            own = math.atan2(z - sensor.offsets[b], horizontal)
            miss = abs(own - sensor.elevations[b])
            if edges[b + 1] < own <= edges[b] and miss < best_miss:
                best, best_miss = b, miss
        beams.append(best)
        column = math.floor((math.atan2(y, x) - sensor.phase) / sensor.azimuth_step + 0.5)
        columns.append(column % sensor.num_columns)
        ranges.append(math.sqrt(x * x + y * y + z * z))
    return np.array(beams), np.array(columns), np.array(ranges)


def _random_points(rng: np.random.Generator, sensor: Sensor, n: int) -> np.ndarray:
    """Points near the beams (and some outside them all), 1 to 60 m away, float32 with a
    feature column."""
    low, high = sensor.elevations[-1] - 2 * DEG, sensor.elevations[0] + 2 * DEG
    elevation = rng.uniform(low, high, n)
    azimuth = rng.uniform(-math.pi, math.pi, n)
    distance = rng.uniform(1.0, 60.0, n)
    xyz = np.column_stack(
        [
            distance * np.cos(elevation) * np.cos(azimuth),
            distance * np.cos(elevation) * np.sin(azimuth),
            distance * np.sin(elevation),
        ]
    )
    return np.column_stack([xyz + sensor.mount, rng.random(n)]).astype(np.float32)


@pytest.mark.parametrize("with_offsets", [False, True])
def test_cells_match_the_per_point_reference(rng, with_offsets):
    base = sensor_preset("hdl64e")
    offsets = rng.uniform(-0.25, 0.25, base.num_beams) if with_offsets else None
    sensor = Sensor(
        elevations=base.elevations,
        offsets=offsets,
        azimuth_step=base.azimuth_step,
        phase=0.37 * base.azimuth_step,
        mount=[0.3, -0.2, 1.5] if with_offsets else None,
    )
    points = _random_points(rng, sensor, 3000)
    beam, column, distance = sensor.cells(points)
    want_beam, want_column, want_range = _reference_cells(sensor, points)
    np.testing.assert_array_equal(beam, want_beam)
    np.testing.assert_array_equal(column, want_column)
    np.testing.assert_allclose(distance, want_range, rtol=1e-12)
    assert (beam == -1).any() and (beam >= 0).mean() > 0.6  # both cases are exercised
    assert beam.dtype == column.dtype == np.int64


def test_points_on_a_ray_give_back_its_cell(rng):
    """What render promises: a return on ray (b, c), seen from its beam's origin, maps back
    to (b, c), whatever the beams' origin heights."""
    base = sensor_preset("hdl64e")
    sensor = Sensor(
        elevations=base.elevations,
        offsets=rng.uniform(-0.2, 0.2, base.num_beams),
        azimuth_step=base.azimuth_step,
        phase=0.8 * base.azimuth_step,
        mount=[0.0, 0.0, 1.7],
    )
    beam = rng.integers(0, sensor.num_beams, 5000)
    column = rng.integers(0, sensor.num_columns, 5000)
    t = rng.uniform(1.0, 80.0, 5000)[:, None]
    points = sensor.ray_origins(beam) + t * sensor.ray_directions(beam, column)
    got_beam, got_column, _ = sensor.cells(points)
    np.testing.assert_array_equal(got_beam, beam)
    np.testing.assert_array_equal(got_column, column)


# --------------------------------------------------------------------------------------------
# The synthetic world's sensor
# --------------------------------------------------------------------------------------------
def test_synthetic_world_uses_the_preset_elevations():
    assert hdl64e_elevations() == hdl64e_elevations_deg() == LidarConfig().elevations_deg
    np.testing.assert_array_equal(
        sensor_preset("hdl64e").elevations, np.radians(hdl64e_elevations_deg())
    )
    assert sensor_preset("hdl64e").num_columns == LidarConfig().num_columns


@pytest.mark.parametrize(
    ("config", "offset"),
    [
        (LidarConfig(), 0.0),
        (LidarConfig(), 0.0021),
        (LidarConfig(azimuth_step_deg=0.1), -3.0),
        (LidarConfig(azimuth_step_deg=0.35, range_noise=0.05, dropout=0.2), 7.5),
        (LidarConfig(elevations_deg=(-5.0, 3.0, 0.5), min_range=2.0, max_range=80.0), 0.001),
        (lidar_preset("hdl32e"), 0.0),
        (lidar_preset("hdl32e"), 0.004),
    ],
)
def test_lidar_config_sensor_rays_map_one_to_one_onto_cells(config, offset):
    grid = ray_grid(config, offset)
    sensor = config.sensor(offset)
    beam, column, _ = sensor.cells(grid.directions * 25.0)
    grid_beam = np.repeat(np.arange(config.num_beams), config.num_columns)
    rank = np.argsort(np.argsort(-np.asarray(config.elevations_deg)))  # top beam first
    np.testing.assert_array_equal(beam, rank[grid_beam])
    cells = beam * sensor.num_columns + column
    assert len(np.unique(cells)) == config.num_rays  # one ray per cell, every cell once
    assert sensor.num_columns == config.num_columns
    np.testing.assert_allclose(sensor.ray_directions(beam, column), grid.directions, atol=1e-12)
    assert (sensor.range_noise, sensor.dropout) == (config.range_noise, config.dropout)
    assert (sensor.min_range, sensor.max_range) == (config.min_range, config.max_range)
    assert not sensor.offsets.any() and not sensor.mount.any()


# --------------------------------------------------------------------------------------------
# sensor: auto
# --------------------------------------------------------------------------------------------
def _kitti_frames(kitti_sample):
    paths = sorted((kitti_sample / "training" / "velodyne").glob("*.bin"))
    assert len(paths) == 6
    return [np.fromfile(p, dtype=np.float32).reshape(-1, 4) for p in paths]


def test_auto_finds_the_64_beams_of_every_kitti_frame(kitti_sample):
    for points in _kitti_frames(kitti_sample):
        sensor = estimate_sensor(points)
        assert sensor.num_beams == 64 and sensor.name == "auto"
        assert 0.08 <= math.degrees(sensor.azimuth_step) <= 0.2
        assert 1.0 <= math.degrees(sensor.elevations[0]) <= 3.5
        assert -27.0 <= math.degrees(sensor.elevations[-1]) <= -22.0
        assert np.abs(sensor.offsets).max() < 0.5
        # The fitted beams explain the returns: seen from its beam's origin, a return lies
        # within 0.1 degree of its beam's elevation.
        beam, _, _ = sensor.cells(points)
        horizontal = np.hypot(points[:, 0], points[:, 1])
        assert (beam >= 0).mean() > 0.99
        on = (beam >= 0) & (horizontal >= 2.0)
        own = np.arctan2(points[on, 2] - sensor.offsets[beam[on]], horizontal[on])
        assert (np.abs(own - sensor.elevations[beam[on]]) <= 0.1 * DEG).mean() > 0.95


SYNTHETIC = [(21, 0.17), (22, 0.17), (23, 0.1), (24, 0.3)]


@pytest.fixture(scope="module")
def synthetic_frames():
    """``(config, sweep)`` of a few synthetic worlds, some with other azimuth steps."""
    frames = []
    for seed, step in SYNTHETIC:
        rng = frame_rng(seed, 0)
        config = LidarConfig(azimuth_step_deg=step)
        world = generate_world(rng, None, mount_height=config.mount_height)
        frames.append((config, scan(world, rng, config)))
    return frames


def _true_sensor(config: LidarConfig, sweep) -> Sensor:
    step = 2 * math.pi / config.num_columns
    return config.sensor(sweep.grid.azimuth[0] + math.pi - 0.5 * step)


def _assert_recovers(sensor: Sensor, config: LidarConfig, sweep) -> None:
    truth = _true_sensor(config, sweep)
    assert sensor.num_beams == config.num_beams
    assert np.abs(sensor.elevations - truth.elevations).max() < 0.05 * DEG
    assert sensor.azimuth_step == pytest.approx(truth.azimuth_step, rel=1e-9)
    assert np.abs(sensor.offsets).max() < 1e-3
    # the phase too: every return falls in the ray cell it was fired in
    beam, column, _ = sensor.cells(sweep.points)
    want_beam, want_column, _ = truth.cells(sweep.points)
    np.testing.assert_array_equal(beam, want_beam)
    np.testing.assert_array_equal(column, want_column)


@pytest.mark.parametrize("index", range(len(SYNTHETIC)))
def test_auto_recovers_the_synthetic_sensor(synthetic_frames, index):
    config, sweep = synthetic_frames[index]
    _assert_recovers(estimate_sensor(sweep.points), config, sweep)


@pytest.mark.parametrize("start_deg", [0.0, 37.0])
def test_auto_finds_where_the_rings_start(synthetic_frames, start_deg):
    """KITTI's rings start near azimuth 0 (and pass +-180 midway): the same returns, each beam
    swept from ``start_deg``, give the same sensor."""
    config, sweep = synthetic_frames[0]
    points = sweep.points
    beam = sweep.ray // sweep.grid.num_columns
    turned = np.mod(np.arctan2(points[:, 1], points[:, 0]) - math.radians(start_deg), 2 * math.pi)
    reordered = points[np.lexsort((turned, beam))]
    _assert_recovers(estimate_sensor(reordered), config, sweep)


def test_auto_tries_the_other_ring_starts_when_the_best_fits_badly(synthetic_frames, monkeypatch):
    """An object spanning every ring can look like the rings' start; the cut whose rings fit
    their lines wins then."""
    import drcpo.sensor_config as sensor_module

    config, sweep = synthetic_frames[0]
    found = sensor_module._sweep_starts
    wrong = [math.radians(-100.0), math.radians(40.0)]
    monkeypatch.setattr(sensor_module, "_sweep_starts", lambda *args: [*wrong, *found(*args)][:3])
    _assert_recovers(estimate_sensor(sweep.points), config, sweep)


@pytest.mark.parametrize("index", [0, 2, 3])
def test_auto_falls_back_on_the_elevation_histogram_for_shuffled_points(synthetic_frames, index):
    config, sweep = synthetic_frames[index]
    points = sweep.points[np.random.default_rng(index).permutation(len(sweep.points))]
    sensor = estimate_sensor(points)
    assert not sensor.offsets.any()  # the histogram's beams have no origin heights
    _assert_recovers(sensor, config, sweep)


def test_auto_keeps_the_base_sensors_noise_and_mount(synthetic_frames):
    config, sweep = synthetic_frames[0]
    base = Sensor(elevations=[0.0], offsets=None, azimuth_step=0.01, range_noise=0.07, dropout=0.2)
    sensor = estimate_sensor(sweep.points, base)
    assert (sensor.range_noise, sensor.dropout) == (0.07, 0.2)
    assert sensor.num_beams == 64
    lifted = Sensor(elevations=[0.0], offsets=None, azimuth_step=0.01, mount=[0.0, 0.0, 1.0])
    moved = sweep.points.copy()
    moved[:, 2] += 1.0
    sensor = estimate_sensor(moved, lifted)
    np.testing.assert_array_equal(sensor.mount, [0.0, 0.0, 1.0])
    truth = _true_sensor(config, sweep)
    assert np.abs(sensor.elevations - truth.elevations).max() < 0.05 * DEG


@pytest.mark.parametrize(
    ("points", "match"),
    [
        (np.zeros((100,), np.float32), r"numeric \(N, 3\+\) array"),
        (np.zeros((100, 2), np.float32), r"numeric \(N, 3\+\) array"),
        (np.array([["a", "b", "c"]]), r"numeric \(N, 3\+\) array"),
        (np.ones((150, 4), np.float32) * [10.0, 0.0, 0.0, 0.0], "150 of 150 points.*at least 200"),
        (np.ones((5000, 4), np.float32) * [1.0, 0.5, 0.0, 0.0], "0 of 5000 points"),
    ],
)
def test_auto_rejects_frames_it_cannot_estimate_from(points, match):
    with pytest.raises(DataError, match=match):
        estimate_sensor(points)


def test_auto_names_rows_with_nan(synthetic_frames):
    points = synthetic_frames[0][1].points.copy()
    points[[7, 9], 1] = np.nan
    points[11, 2] = np.inf
    with pytest.raises(DataError, match="3 points have NaN or infinite.*first at row 7"):
        estimate_sensor(points)
    points = synthetic_frames[0][1].points.copy()
    points[:, 3] = np.nan  # features are not the sensor's business
    assert estimate_sensor(points).num_beams == 64


def test_auto_rejects_points_without_beams(rng):
    # a blob of points at random elevations: no histogram peak stands out
    points = rng.uniform([-40, -40, -3], [40, 40, 3], (5000, 3))
    with pytest.raises(DataError, match="no beams|successive returns"):
        estimate_sensor(points)


# --------------------------------------------------------------------------------------------
# SensorConfig (drcpo.sensor)
# --------------------------------------------------------------------------------------------
def test_sensor_config_defaults_to_the_preset():
    config = SensorConfig()
    assert config.model == "hdl64e"
    sensor, preset = config.sensor_for(None), sensor_preset("hdl64e")
    np.testing.assert_array_equal(sensor.elevations, preset.elevations)
    assert sensor.azimuth_step == preset.azimuth_step
    assert (sensor.range_noise, sensor.dropout) == (preset.range_noise, preset.dropout)
    assert config.resolve(np.zeros((3, 4))).num_beams == 64  # presets ignore the points
    assert to_dict(config) == {
        "model": "hdl64e",
        "elevations_deg": None,
        "azimuth_step_deg": None,
        "mount": None,
        "range_noise": None,
        "dropout": None,
    }


def test_sensor_config_takes_the_hdl32e_preset():
    config = from_dict(SensorConfig, {"model": "hdl32e", "mount": [0.0, 0.0, 0.1]})
    sensor, preset = config.sensor_for(None), sensor_preset("hdl32e")
    np.testing.assert_array_equal(sensor.elevations, preset.elevations)
    assert sensor.azimuth_step == preset.azimuth_step and sensor.num_beams == 32
    assert sensor.max_range == preset.max_range and sensor.name == "hdl32e"
    np.testing.assert_array_equal(sensor.mount, [0.0, 0.0, 0.1])
    assert to_dict(config)["model"] == "hdl32e"


@pytest.mark.parametrize(
    "data",
    [
        {"model": "hdl64e", "azimuth_step_deg": 0.08, "range_noise": 0.0, "dropout": 0.1},
        {"model": "auto", "mount": [0, 0, 1.73], "dropout": 0.0},
        {
            "model": "custom",
            "elevations_deg": [-15, 15, -1, 1, -3, 3, -5, 5, -7, 7, -9, 9, -11, 11, -13, 13],
            "azimuth_step_deg": 0.2,
            "mount": [0.5, 0.0, 1.8],
            "range_noise": 0.03,
            "dropout": 0.05,
        },
    ],
)
def test_sensor_config_round_trip(data):
    config = from_dict(SensorConfig, data, "drcpo.sensor")
    assert from_dict(SensorConfig, to_dict(config), "drcpo.sensor") == config
    assert hash(from_dict(SensorConfig, to_dict(config))) == hash(config)
    if config.model == "auto":
        return
    sensor = config.sensor_for()
    assert sensor.name == config.model
    if config.model == "custom":
        np.testing.assert_allclose(
            np.degrees(sensor.elevations), sorted(data["elevations_deg"], reverse=True)
        )
        np.testing.assert_array_equal(sensor.mount, data["mount"])
    assert math.degrees(sensor.azimuth_step) == pytest.approx(data["azimuth_step_deg"])
    assert (sensor.range_noise, sensor.dropout) == (data["range_noise"], data["dropout"])


def test_sensor_config_auto_estimates_each_frame(synthetic_frames):
    config, sweep = synthetic_frames[2]
    auto = SensorConfig(model="auto", range_noise=0.05)
    sensor = auto.sensor_for(sweep.points)
    _assert_recovers(sensor, config, sweep)
    assert sensor.range_noise == 0.05 and sensor.dropout == sensor_preset("hdl64e").dropout
    with pytest.raises(ConfigError, match="model auto needs the frame's points"):
        auto.sensor_for(None)


@pytest.mark.parametrize(
    ("data", "match"),
    [
        ({"model": "vlp16"}, "drcpo.sensor.model' = 'vlp16' is not allowed.*hdl64e, auto, custom"),
        ({"model": "custom", "azimuth_step_deg": 0.2}, "elevations_deg' must be set for model"),
        ({"model": "custom", "elevations_deg": [1, 0]}, "azimuth_step_deg' must be set for"),
        ({"elevations_deg": [1.0, 0.0]}, "elevations_deg' is for model custom only; model hdl64e"),
        ({"model": "auto", "elevations_deg": [1.0]}, "for model custom only; model auto"),
        ({"model": "auto", "azimuth_step_deg": 0.1}, "cannot be set with model auto"),
        (
            {"model": "custom", "elevations_deg": [1, 0, 1], "azimuth_step_deg": 0.2},
            r"lists an elevation twice \(1.0\)",
        ),
        ({"model": "custom", "elevations_deg": [], "azimuth_step_deg": 0.2}, "at least one"),
        ({"model": "custom", "elevations_deg": [95], "azimuth_step_deg": 0.2}, r"\[0\]' = 95"),
        ({"model": "custom", "elevations_deg": "1, 2", "azimuth_step_deg": 0.2}, "list of"),
        ({"mount": [0, 0]}, "'drcpo.sensor.mount' must be a list of 3 numbers, got 2"),
        ({"mount": [0, 0, "high"]}, r"mount\[2\]' must be a number"),
        ({"mount": [0, 0, float("nan")]}, r"mount\[2\]' must be finite"),
        ({"azimuth_step_deg": 0}, "azimuth_step_deg' = 0 is out of range"),
        ({"range_noise": -1}, "range_noise' = -1 is out of range"),
        ({"dropout": 1}, "dropout' = 1 is out of range"),
        ({"beams": 64}, "unknown config key 'drcpo.sensor.beams'"),
    ],
)
def test_sensor_config_errors_name_the_key(data, match):
    with pytest.raises(ConfigError, match=match):
        from_dict(SensorConfig, data, "drcpo.sensor")


def test_sensor_config_built_in_code_is_checked():
    with pytest.raises(ConfigError, match="'drcpo.sensor.dropout' = 2.0 is out of range"):
        SensorConfig(dropout=2.0)
    with pytest.raises(ConfigError, match="elevations_deg' must be set for model custom"):
        SensorConfig(model="custom")
