"""The synthetic nuScenes-style data set: written by the world, read back by the nuScenes reader
(boxes, velocities, sweeps, features), against the world's own truth and naive references."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial import cKDTree
from test_sensor import nearest_beams

from drcpo.datasets.nuscenes import NuScenesDataset
from drcpo.datasets.nuscenes_writer import NUSCENES_MANIFEST
from drcpo.errors import ConfigError
from drcpo.synth.dataset import frame_rng
from drcpo.synth.nuscenes import (
    CATEGORY_OF,
    NuScenesSynthConfig,
    synthesize_scene,
    write_synthetic_nuscenes,
)
from drcpo.synth.sensor import hdl32e_elevations

VERSION = "v1.0-trainval"
CONFIG = NuScenesSynthConfig(samples=3, sweeps_before=4)
CLASS = {"Car": "car", "Pedestrian": "pedestrian", "Cyclist": "bicycle"}


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth_nuscenes") / "nuscenes"
    summary = write_synthetic_nuscenes(root, 1, seed=7, config=CONFIG, version=VERSION)
    scene = synthesize_scene(frame_rng(7, 0), "scene-0000", CONFIG)
    return root, summary, scene


def key_sweeps(scene) -> list[int]:
    return [i for i, s in enumerate(scene.record.sweeps) if s.key]


def labelled(scene, k: int) -> np.ndarray:
    """Actors annotated with at least one point at key sample ``k``."""
    return np.array([a.num_lidar_pts > 0 for a in scene.record.annotations[k]])


def naive_in_box(points: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Points inside one box: each point rotated into the box's frame, one by one."""
    cos, sin = math.cos(box[6]), math.sin(box[6])
    out = []
    for x, y, z in points[:, :3].astype(np.float64):
        dx, dy = x - box[0], y - box[1]
        u, v = cos * dx + sin * dy, -sin * dx + cos * dy
        out.append(abs(u) <= box[3] / 2 and abs(v) <= box[4] / 2 and abs(z - box[2]) <= box[5] / 2)
    return np.array(out)


def test_the_data_set_has_scenes_samples_and_sweeps(synthetic):
    root, summary, _ = synthetic
    assert summary["scenes"] == 1 and summary["samples"] == 3
    assert summary["sweeps"] == CONFIG.num_sweeps == 4 + 2 * 10 + 1
    assert summary["moving"] >= 2 and summary["objects"]["vehicle.car"] > 0
    marker = json.loads((root / NUSCENES_MANIFEST).read_text())
    assert marker["seed"] == 7 and marker["config"]["sensor"] == "hdl32e"
    assert len(list((root / "samples" / "LIDAR_TOP").glob("*.pcd.bin"))) == 3
    assert len(list((root / "sweeps" / "LIDAR_TOP").glob("*.pcd.bin"))) == 22
    dataset = NuScenesDataset(root, VERSION)
    assert len(dataset.frame_ids) == 3


def test_boxes_come_back_as_the_world_placed_them(synthetic):
    root, _, scene = synthetic
    dataset = NuScenesDataset(root, VERSION)
    for k, token in enumerate(dataset.frame_ids):
        frame = dataset.frame(token)
        keep = labelled(scene, k)
        truth = scene.boxes_at(key_sweeps(scene)[k])[keep]
        assert len(frame.boxes) == keep.sum() > 5
        np.testing.assert_allclose(frame.boxes[:, :6], truth[:, :6], atol=1e-4)
        heading_error = np.angle(np.exp(1j * (frame.boxes[:, 6] - truth[:, 6])))
        np.testing.assert_allclose(heading_error, 0.0, atol=1e-4)
        assert frame.names.tolist() == [CLASS[n] for n in scene.world.names[keep]]


def test_velocities_of_moving_actors_are_recovered(synthetic):
    """Actors move at constant velocity, so the devkit's finite differences (centred in the
    middle sample, one-sided at the ends) give it exactly but for float64 rounding of global
    positions of about 2 km over 0.5 s (about 1e-12 m/s): compared to 1e-6 m/s."""
    root, _, scene = synthetic
    dataset = NuScenesDataset(root, VERSION)
    moving = 0
    for k, token in enumerate(dataset.frame_ids):
        keep = labelled(scene, k)
        velocity = dataset.frame(token).metadata["velocity"]
        truth = scene.velocity_at(key_sweeps(scene)[k])[keep]
        np.testing.assert_allclose(velocity, truth, atol=1e-6)
        moving += int((np.linalg.norm(truth, axis=1) > 0.5).sum())
    assert moving >= 3


def test_num_points_are_the_key_sweeps_points_in_each_box(synthetic):
    root, _, _ = synthetic
    dataset = NuScenesDataset(root, VERSION)
    frame = dataset.frame(dataset.frame_ids[1])
    counts = [naive_in_box(frame.points, box).sum() for box in frame.boxes]
    assert frame.metadata["num_points_in_gt"].tolist() == counts
    assert min(counts) >= 1


def test_points_carry_intensity_and_ring(synthetic):
    root, _, _ = synthetic
    dataset = NuScenesDataset(root, VERSION)
    frame = dataset.frame(dataset.frame_ids[0])
    intensity, ring = frame.points[:, 3], frame.points[:, 4]
    assert (
        0 <= intensity.min() and intensity.max() <= 255 and (intensity == np.round(intensity)).all()
    )
    assert intensity.max() > 100
    beam, miss = nearest_beams(frame.points, hdl32e_elevations())  # beam 0: the top one
    assert np.median(miss) < 0.05
    np.testing.assert_array_equal(ring, 31 - beam)
    assert len(np.unique(ring)) == 32


def test_sweeps_join_where_the_sensor_was(synthetic):
    """Origins: each sweep's LiDAR position in the key LiDAR frame, from the world's own ego
    path; time lags: 50 ms apart, as float32."""
    root, _, scene = synthetic
    dataset = NuScenesDataset(root, VERSION, sweeps=6)
    k, key = 1, key_sweeps(scene)[1]
    frame = dataset.frame(dataset.frame_ids[k])
    used = np.arange(key, key - 7, -1)
    yaw = scene.sensor_yaw[key]
    offset = scene.sensor_position[used] - scene.sensor_position[key]
    cos, sin = math.cos(yaw), math.sin(yaw)
    expected = np.column_stack(
        [
            cos * offset[:, 0] + sin * offset[:, 1],
            -sin * offset[:, 0] + cos * offset[:, 1],
            offset[:, 2],
        ]
    )
    np.testing.assert_allclose(frame.metadata["sweep_origins"], expected, atol=1e-6)
    lags = np.float32((key - used) * 0.05)
    np.testing.assert_array_equal(frame.metadata["sweep_time_lags"], lags.astype(np.float64))
    assert set(np.unique(frame.points[:, 4])) == set(lags.tolist())
    assert frame.metadata["point_features"] == ("intensity", "time_lag")


def test_joined_sweeps_line_up_on_the_static_world(synthetic):
    """The static world's points above the ground (poles, trunks, walls, parked cars left out)
    of a sweep 0.2 s earlier, moved into the key frame, fall on the key sweep's surfaces
    (beams differ, so within a few cm: 90 % within 30 cm); left where the sensor saw them they
    are off by the ego car's travel. (The ground is left out: its rings circle the sensor, so
    unmoved they would match better.)"""
    root, _, scene = synthetic
    key = key_sweeps(scene)[1]
    dataset = NuScenesDataset(root, VERSION, sweeps=4)
    joined = dataset.frame(dataset.frame_ids[1])
    points = joined.points
    above = (np.linalg.norm(points[:, :2], axis=1) < 30) & (points[:, 2] > -1.2)
    static_key = points[above & (points[:, 4] == 0)]
    earlier = points[above & (points[:, 4] > 0.19)]
    near_actor = np.zeros(len(earlier), dtype=bool)
    for box in scene.boxes_at(key):  # actors move: leave them out
        near_actor |= np.linalg.norm(earlier[:, :2] - box[:2], axis=1) < np.hypot(*box[3:5]) + 2.5
    earlier = earlier[~near_actor]
    assert len(earlier) > 1000
    tree = cKDTree(static_key[:, :3])
    moved, _ = tree.query(earlier[:, :3])
    origin = joined.metadata["sweep_origins"][4]
    assert np.linalg.norm(origin) > 0.5  # 0.2 s at 3-8 m/s
    unmoved, _ = tree.query(earlier[:, :3] - origin)  # the join only translates (no turn)
    assert np.percentile(moved, 90) < 0.3
    assert np.percentile(unmoved, 90) > 3 * np.percentile(moved, 90)


def test_the_same_seed_gives_the_same_files(synthetic, tmp_path):
    root, _, _ = synthetic
    write_synthetic_nuscenes(tmp_path / "again", 1, seed=7, config=CONFIG, version=VERSION)
    for path in sorted((root / VERSION).glob("*.json")):
        assert (tmp_path / "again" / VERSION / path.name).read_bytes() == path.read_bytes()
    for path in sorted((root / "sweeps" / "LIDAR_TOP").glob("*.bin"))[:3]:
        assert (tmp_path / "again" / "sweeps" / "LIDAR_TOP" / path.name).read_bytes() == (
            path.read_bytes()
        )


def test_every_class_maps_to_a_detection_category():
    from drcpo.datasets.nuscenes import CATEGORY_TO_CLASS
    from drcpo.synth import CLASSES

    assert {CATEGORY_TO_CLASS[CATEGORY_OF[c]] for c in CLASSES} == {"car", "pedestrian", "bicycle"}


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"samples": 0}, "samples = 0 is out of range"),
        ({"sweeps_per_sample": 0}, "sweeps_per_sample"),
        ({"ego_speed": (5.0, 1.0)}, "ego_speed"),
        ({"moving_probability": 1.5}, "moving_probability"),
        ({"sensor": "vlp16"}, "unknown sensor 'vlp16'"),
    ],
)
def test_bad_parameters_are_named(changes, match):
    with pytest.raises(ConfigError, match=match):
        NuScenesSynthConfig(**changes)
    with pytest.raises(ConfigError, match="scenes must be >= 1"):
        write_synthetic_nuscenes("/nonexistent/never", 0)


# The command ---------------------------------------------------------------------------------
def test_drcpo_synth_writes_a_nuscenes_layout(tmp_path):
    from typer.testing import CliRunner

    from drcpo.cli import app

    out = tmp_path / "nusc"
    command = ["synth", "--layout", "nuscenes", "--out", str(out), "--frames", "3"]
    result = CliRunner().invoke(app, [*command, "--scene-samples", "2", "--version", "v1.0-mini"])
    assert result.exit_code == 0, result.output
    assert "moving objects" in result.output and "sweeps (20 Hz)" in result.output
    dataset = NuScenesDataset(out, "v1.0-mini", sweeps=10)
    assert len(dataset.frame_ids) == 4
    frame = dataset.frame(dataset.frame_ids[1])
    assert len(frame.metadata["sweep_time_lags"]) == 11 and len(frame.boxes) > 0


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--layout", "waymo"], "--layout 'waymo' is not one of kitti, nuscenes"),
        (["--sensor", "vlp16"], "unknown sensor 'vlp16'; presets: hdl32e, hdl64e"),
        (["--layout", "nuscenes", "--azimuth-step", "0.2"], "--azimuth-step is for --layout kitti"),
    ],
)
def test_drcpo_synth_refuses_bad_options_in_one_line(tmp_path, extra, message):
    from typer.testing import CliRunner

    from drcpo.cli import app

    result = CliRunner().invoke(app, ["synth", "--out", str(tmp_path / "o"), *extra])
    assert result.exit_code == 1
    assert message in result.output and "Traceback" not in result.output
    assert not (tmp_path / "o").exists()


def test_drcpo_synth_kitti_with_the_32_beam_sensor(tmp_path):
    from typer.testing import CliRunner

    from drcpo.cli import app
    from drcpo.datasets.kitti import KittiDataset

    out = tmp_path / "kitti"
    result = CliRunner().invoke(
        app, ["synth", "--out", str(out), "--frames", "1", "--sensor", "hdl32e"]
    )
    assert result.exit_code == 0, result.output
    points = KittiDataset(out, "trainval").frame("000000").points
    beam, miss = nearest_beams(points, hdl32e_elevations())
    assert np.median(miss) < 0.05 and len(np.unique(beam)) == 32


def test_frames_pass_validation_and_cut_into_database_records(synthetic):
    """What the database builder takes: valid frames whose objects' points (5 columns) are
    cut out per box: at least the frame's num_points_in_gt of them (the builder's rule,
    OpenPCDet's, adds 1 cm around the tight box, where the synthetic objects' sides are)."""
    from drcpo.database.build import frame_records

    root, _, _ = synthetic
    dataset = NuScenesDataset(root, VERSION)
    frame = dataset.frame(dataset.frame_ids[2]).validate()
    records = frame_records(frame)
    assert len(records) == len(frame.boxes)
    assert all(r.points.shape[1] == 5 for r in records)
    counts = np.array([len(r.points) for r in records])
    assert (counts >= frame.metadata["num_points_in_gt"]).all() and counts.min() > 0
    assert [r.name for r in records] == frame.names.tolist()
