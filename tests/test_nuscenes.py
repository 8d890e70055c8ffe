"""The nuScenes layout: writer and reader round trip (boxes, velocities, sweeps) against naive
per-box and per-point references, the category mapping, and every error path."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from drcpo.datasets.nuscenes import (
    CATEGORY_TO_CLASS,
    NUSCENES_CLASSES,
    NuScenesDataset,
    read_pcd_bin,
)
from drcpo.datasets.nuscenes_geometry import yaw_quaternion
from drcpo.datasets.nuscenes_writer import (
    NUSCENES_MANIFEST,
    AnnotationRecord,
    SceneRecord,
    SweepRecord,
    write_nuscenes,
)
from drcpo.errors import DataError, OutputError

VERSION = "v1.0-mini"
SWEEP_US = 50_000  # 20 Hz
KEY_EVERY = 10  # 2 Hz


# Naive references ----------------------------------------------------------------------------
def quat_matrix(q) -> np.ndarray:
    """Rotation matrix of a w, x, y, z quaternion, written out term by term."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_multiply(a, b) -> np.ndarray:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def homogeneous(translation, rotation) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = quat_matrix(rotation)
    m[:3, 3] = translation
    return m


def random_quaternion(rng, tilt: float) -> np.ndarray:
    """A yaw anywhere plus a small tilt about a random horizontal axis (radians)."""
    yaw = yaw_quaternion(rng.uniform(-math.pi, math.pi))
    axis = np.array([*rng.normal(size=2), 0.0])
    axis /= np.linalg.norm(axis)
    half = rng.uniform(-tilt, tilt) / 2
    return quat_multiply(yaw, [math.cos(half), *(math.sin(half) * axis)])


# A hand-made scene ---------------------------------------------------------------------------
LIDAR_T = np.array([0.94, 0.0, 1.84])


def ego_pose(t: float, start: np.ndarray, yaw: float, speed: float):
    """The ego pose at ``t`` seconds: driving straight at ``speed`` along ``yaw``."""
    position = start + speed * t * np.array([math.cos(yaw), math.sin(yaw), 0.0])
    return position, yaw_quaternion(yaw + 0.02 * t)  # turning slowly


def make_scene(
    rng, name: str, samples: int = 4, sweeps_before: int = 3, categories=None, still=(1,)
):
    """A scene of ``samples`` key sweeps 0.5 s apart (with 9 sweeps between them), objects
    moving at constant velocity in the global frame; returns the record and the truth."""
    categories = categories or ["vehicle.car", "human.pedestrian.adult", "vehicle.bicycle"]
    lidar_q = quat_multiply(yaw_quaternion(-math.pi / 2), random_quaternion(rng, 0.02))
    start, yaw, speed = rng.uniform(-500, 500, 3) * [1, 1, 0], rng.uniform(-3, 3), 6.0
    count = (samples - 1) * KEY_EVERY + 1 + sweeps_before
    t0 = 1_531_000_000_000_000 + int(rng.integers(0, 10**9))
    sweeps, key_times = [], []
    for i in range(count):
        time_us = t0 + i * SWEEP_US
        key = i >= sweeps_before and (i - sweeps_before) % KEY_EVERY == 0
        points = np.column_stack(
            [rng.uniform(-40, 40, (200, 2)), rng.uniform(-2, 2, 200), rng.uniform(0, 255, 200)]
        )
        points = np.column_stack([points, rng.integers(0, 32, 200)]).astype(np.float32)
        position, rotation = ego_pose((time_us - t0) * 1e-6, start, yaw, speed)
        sweeps.append(SweepRecord(time_us, points, position, rotation, key))
        if key:
            key_times.append(time_us)
    instances, annotations = [], [[] for _ in key_times]
    truth = {"positions": [], "velocity": [], "samples": [], "size": [], "rotation": []}
    for n, category in enumerate(categories):
        first = n % 2  # some tracks start at the second sample
        centre = start + rng.uniform(-30, 30, 3) * [1, 1, 0.05]
        velocity = np.array([*rng.uniform(-8, 8, 2), 0.1]) if n not in still else np.zeros(3)
        size = rng.uniform(0.5, 5.0, 3)
        rotation = random_quaternion(rng, 0.05)
        instances.append(category)
        for k in range(first, len(key_times)):
            t = (key_times[k] - t0) * 1e-6
            annotations[k].append(
                AnnotationRecord(n, centre + velocity * t, size, rotation, int(rng.integers(1, 99)))
            )
        truth["velocity"].append(velocity)
        truth["samples"].append(list(range(first, len(key_times))))
        truth["positions"].append([centre + velocity * (kt - t0) * 1e-6 for kt in key_times])
        truth["size"].append(size)
        truth["rotation"].append(rotation)
    scene = SceneRecord(name, sweeps, annotations, instances, LIDAR_T, lidar_q)
    return scene, truth


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    rng = np.random.default_rng(18)
    root = tmp_path_factory.mktemp("nuscenes") / "data"
    scenes = [make_scene(rng, f"scene-{i:04d}") for i in range(2)]
    write_nuscenes(root, [s for s, _ in scenes], VERSION)
    return root, scenes


def sensor_to_global(scene: SceneRecord, sweep: SweepRecord) -> np.ndarray:
    return homogeneous(sweep.ego_translation, sweep.ego_rotation) @ homogeneous(
        scene.lidar_translation, scene.lidar_rotation
    )


def key_sweeps(scene: SceneRecord) -> list[int]:
    return [i for i, s in enumerate(scene.sweeps) if s.key]


# Round trip ----------------------------------------------------------------------------------
def test_frame_ids_are_the_samples_scene_by_scene(written):
    root, scenes = written
    dataset = NuScenesDataset(root, VERSION)
    assert len(dataset.frame_ids) == sum(len(key_sweeps(s)) for s, _ in scenes) == len(dataset)
    times = [dataset.frame(t).metadata["timestamp"] for t in dataset.frame_ids]
    assert times[:4] == sorted(times[:4]) and times[4:] == sorted(times[4:])
    assert [dataset.frame(t).metadata["scene"] for t in dataset.frame_ids[::4]] == [
        "scene-0000",
        "scene-0001",
    ]
    second = NuScenesDataset(root, VERSION, scenes=["scene-0001"])
    assert second.frame_ids == dataset.frame_ids[4:]


def test_a_split_file_names_the_scenes(written, tmp_path):
    root, _ = written
    split = tmp_path / "val.txt"
    split.write_text("# the val split\nscene-0001\n\nscene-0000\n")
    dataset = NuScenesDataset(root, VERSION, scenes=split)
    everything = NuScenesDataset(root, VERSION).frame_ids
    assert dataset.frame_ids == everything[4:] + everything[:4]
    split.write_text("# nothing\n")
    with pytest.raises(DataError, match="val.txt: the scene list names no scene"):
        NuScenesDataset(root, VERSION, scenes=str(split))


def test_boxes_come_back_in_the_lidar_frame(written):
    """Each box against a naive per-box reference: centre moved by the 4x4 inverse pose,
    heading from the rotated box x axis, size w, l, h -> l, w, h."""
    root, scenes = written
    dataset = NuScenesDataset(root, VERSION)
    for number, token in enumerate(dataset.frame_ids):
        scene, truth = scenes[number // 4]
        k = number % 4
        sweep = scene.sweeps[key_sweeps(scene)[k]]
        to_lidar = np.linalg.inv(sensor_to_global(scene, sweep))
        frame = dataset.frame(token)
        expected = []
        for n in range(len(scene.instances)):
            if k not in truth["samples"][n]:
                continue
            centre = to_lidar @ [*truth["positions"][n][k], 1.0]
            axis = to_lidar[:3, :3] @ quat_matrix(truth["rotation"][n])[:, 0]
            w, length, h = truth["size"][n]
            expected.append([*centre[:3], length, w, h, math.atan2(axis[1], axis[0])])
        np.testing.assert_allclose(frame.boxes, np.array(expected).reshape(-1, 7), atol=1e-9)
        assert frame.names.tolist() == [
            ["car", "pedestrian", "bicycle"][n] for n in range(3) if k in truth["samples"][n]
        ]


def test_velocities_are_the_devkits_finite_differences(written):
    """Objects move at constant global velocity, so the devkit's finite difference (centred
    or one-sided) is that velocity exactly, up to float64 rounding of global positions of a few
    hundred metres (about 1e-13 m) over 0.5 s or more: 1e-9 m/s is ample. A still object reads
    0. Rotated into the lidar frame with the key pose (naive 4x4 reference)."""
    root, scenes = written
    dataset = NuScenesDataset(root, VERSION)
    for number, token in enumerate(dataset.frame_ids):
        scene, truth = scenes[number // 4]
        k = number % 4
        sweep = scene.sweeps[key_sweeps(scene)[k]]
        rotate = np.linalg.inv(sensor_to_global(scene, sweep))[:3, :3]
        expected = [
            (rotate @ truth["velocity"][n])[:2] for n in range(3) if k in truth["samples"][n]
        ]
        velocity = dataset.frame(token).metadata["velocity"]
        assert velocity.shape == (len(expected), 2) and velocity.dtype == np.float64
        np.testing.assert_allclose(velocity, np.array(expected), atol=1e-9)
    assert np.abs(velocity).max() > 1.0  # moving objects were there


def test_num_points_and_tokens_come_along(written):
    root, scenes = written
    dataset = NuScenesDataset(root, VERSION)
    frame = dataset.frame(dataset.frame_ids[1])
    scene, _ = scenes[0]
    expected = [a.num_lidar_pts for a in scene.annotations[1]]
    assert frame.metadata["num_points_in_gt"].tolist() == expected
    assert frame.metadata["num_points_in_gt"].dtype == np.int64
    assert len(frame.metadata["annotation_tokens"]) == len(frame.boxes)
    assert len(set(frame.metadata["instance_tokens"])) == len(frame.boxes)


def test_a_single_sweep_keeps_the_ring(written):
    root, scenes = written
    dataset = NuScenesDataset(root, VERSION)
    frame = dataset.frame(dataset.frame_ids[0])
    scene, _ = scenes[0]
    raw = scene.sweeps[key_sweeps(scene)[0]].points
    np.testing.assert_array_equal(frame.points, raw)
    assert frame.metadata["point_features"] == ("intensity", "ring")
    np.testing.assert_array_equal(frame.metadata["sweep_origins"], np.zeros((1, 3)))
    np.testing.assert_array_equal(frame.metadata["sweep_time_lags"], [0.0])
    assert frame.metadata["lidar_path"].startswith("samples/LIDAR_TOP/")


@pytest.mark.parametrize(
    ("sample", "sweeps", "close"), [(0, 5, 0.0), (1, 9, 0.0), (1, 12, 10.0), (3, 30, 0.0)]
)
def test_sweeps_join_in_the_key_frame(written, sample, sweeps, close):
    """Against a per-point loop of 4x4 products: each earlier sweep's points in the key
    sweep's frame, time lag = key time - sweep time (s); origins = the sweep sensor's position
    in the key frame. Sample 0 has only 3 sweeps before it; the last ones the whole scene.
    ``remove_close``: earlier sweeps lose their points within 10 m of their sensor in x and y."""
    root, scenes = written
    dataset = NuScenesDataset(root, VERSION, sweeps=sweeps, remove_close=close)
    frame = dataset.frame(dataset.frame_ids[sample])
    scene, _ = scenes[0]
    key = key_sweeps(scene)[sample]
    used = list(range(key, max(key - sweeps, 0) - 1, -1))
    to_key = np.linalg.inv(sensor_to_global(scene, scene.sweeps[key]))
    expected, origins, lags = [], [], []
    for i in used:
        sweep = scene.sweeps[i]
        matrix = to_key @ sensor_to_global(scene, sweep)
        lag = (scene.sweeps[key].timestamp - sweep.timestamp) / 1e6
        for p in sweep.points.astype(np.float64):
            if i != key and abs(p[0]) < close and abs(p[1]) < close:
                continue
            expected.append([*(matrix @ [*p[:3], 1.0])[:3], p[3], lag])
        origins.append(matrix[:3, 3])
        lags.append(lag)
    assert len(frame.metadata["sweep_time_lags"]) == len(used) == min(sweeps, key) + 1
    np.testing.assert_allclose(frame.points, np.array(expected), atol=1e-4, rtol=0)
    np.testing.assert_allclose(frame.metadata["sweep_origins"], origins, atol=1e-9)
    np.testing.assert_allclose(frame.metadata["sweep_time_lags"], lags, atol=1e-7)
    assert frame.metadata["point_features"] == ("intensity", "time_lag")
    # a point's sweep: the row whose time lag equals its time-lag column, exactly
    row = np.searchsorted(frame.metadata["sweep_time_lags"], frame.points[:, 4])
    assert (frame.metadata["sweep_time_lags"][row] == frame.points[:, 4]).all()
    counts = [len(scene.sweeps[i].points) for i in used]
    assert (
        (np.bincount(row)[1:] < counts[1:]).all() if close else (np.bincount(row) == counts).all()
    )


def test_categories_map_to_the_detection_classes(tmp_path):
    rng = np.random.default_rng(3)
    categories = ["vehicle.bus.bendy", "animal", "vehicle.emergency.police", "vehicle.trailer"]
    scene, _ = make_scene(rng, "scene-a", samples=2, categories=categories)
    write_nuscenes(tmp_path / "d", [scene], VERSION)
    dataset = NuScenesDataset(tmp_path / "d", VERSION)
    assert dataset.frame(dataset.frame_ids[1]).names.tolist() == ["bus", "trailer"]
    only = NuScenesDataset(tmp_path / "d", VERSION, classes=["trailer"])
    assert only.frame(only.frame_ids[1]).names.tolist() == ["trailer"]
    assert set(CATEGORY_TO_CLASS.values()) == set(NUSCENES_CLASSES)


def test_boxes_without_points_go_unless_kept(tmp_path):
    rng = np.random.default_rng(4)
    scene, _ = make_scene(rng, "scene-b", samples=2)
    empty = [
        [AnnotationRecord(a.instance, a.translation, a.size, a.rotation, 0) for a in s]
        for s in scene.annotations
    ]
    scene = SceneRecord(scene.name, scene.sweeps, empty, scene.instances, LIDAR_T, [1, 0, 0, 0])
    write_nuscenes(tmp_path / "d", [scene], VERSION)
    assert len(NuScenesDataset(tmp_path / "d", VERSION).frame_ids) == 2
    assert (
        len(
            NuScenesDataset(tmp_path / "d", VERSION)
            .frame(NuScenesDataset(tmp_path / "d", VERSION).frame_ids[1])
            .boxes
        )
        == 0
    )
    kept = NuScenesDataset(tmp_path / "d", VERSION, keep_empty=True)
    assert len(kept.frame(kept.frame_ids[1]).boxes) == 3


def test_velocity_gaps_follow_the_devkit(tmp_path):
    """One-sided differences over more than 1.5 s and centred ones over more than 3 s are
    unknown (0); a lone annotation has no velocity; every object moves."""
    rng = np.random.default_rng(5)
    categories = ["vehicle.car", "vehicle.car", "vehicle.bicycle", "vehicle.truck"]
    scene, truth = make_scene(rng, "scene-c", samples=9, categories=categories, still=())
    keep = {0: [0, 4], 1: [5], 2: [0, 1, 5], 3: [1, 2, 8]}  # instance -> its samples
    known = {(0, 2), (1, 2), (1, 3)}  # (sample, instance) with a velocity
    annotations = [
        [a for a in boxes if k in keep[a.instance]] for k, boxes in enumerate(scene.annotations)
    ]
    scene = SceneRecord(
        scene.name, scene.sweeps, annotations, scene.instances, LIDAR_T, scene.lidar_rotation
    )
    write_nuscenes(tmp_path / "d", [scene], VERSION)
    dataset = NuScenesDataset(tmp_path / "d", VERSION)
    checked = 0
    for k, token in enumerate(dataset.frame_ids):
        rotate = np.linalg.inv(sensor_to_global(scene, scene.sweeps[key_sweeps(scene)[k]]))
        velocity = dataset.frame(token).metadata["velocity"]
        instances = [n for n in range(4) if k in keep[n]]
        assert len(velocity) == len(instances)
        for row, n in enumerate(instances):
            expected = (rotate[:3, :3] @ truth["velocity"][n])[:2] if (k, n) in known else 0.0
            np.testing.assert_allclose(velocity[row], expected, atol=1e-9)
            checked += 1
    assert checked == sum(len(v) for v in keep.values())


# The writer ----------------------------------------------------------------------------------
def test_the_writer_marks_its_output_and_overwrites_only_its_own(tmp_path, written):
    root, scenes = written
    marker = json.loads((root / NUSCENES_MANIFEST).read_text())
    assert marker["format"] == "drcpo-nuscenes" and marker["version"] == VERSION
    tables = sorted(p.stem for p in (root / VERSION).glob("*.json"))
    assert len(tables) == 13 and "map" in tables and "visibility" in tables
    with pytest.raises(OutputError):
        write_nuscenes(root, [scenes[0][0]], VERSION)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("mine")
    with pytest.raises(OutputError):
        write_nuscenes(foreign, [scenes[0][0]], VERSION, overwrite=True)
    assert (foreign / "keep.txt").read_text() == "mine"
    again = tmp_path / "again"
    write_nuscenes(again, [scenes[0][0]], VERSION)
    write_nuscenes(again, [scenes[0][0]], VERSION, overwrite=True)
    assert (again / VERSION / "sample.json").read_bytes() == (
        (tmp_path / "again" / VERSION / "sample.json").read_bytes()
    )


def test_the_writer_is_deterministic(tmp_path, written):
    root, scenes = written
    write_nuscenes(tmp_path / "a", [s for s, _ in scenes], VERSION)
    for table in ("sample", "sample_data", "sample_annotation", "instance", "ego_pose"):
        assert (tmp_path / "a" / VERSION / f"{table}.json").read_bytes() == (
            root / VERSION / f"{table}.json"
        ).read_bytes()


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (
            lambda s: SceneRecord("", s.sweeps, s.annotations, s.instances, LIDAR_T, [1, 0, 0, 0]),
            "unique and non-empty",
        ),
        (
            lambda s: SceneRecord(
                s.name, s.sweeps, s.annotations[:-1], s.instances, LIDAR_T, [1, 0, 0, 0]
            ),
            "annotation lists for 4 key sweeps",
        ),
        (
            lambda s: SceneRecord(
                s.name, s.sweeps[::-1], s.annotations, s.instances, LIDAR_T, [1, 0, 0, 0]
            ),
            "timestamps must increase",
        ),
        (
            lambda s: SceneRecord(
                s.name, s.sweeps, s.annotations, s.instances[:1], LIDAR_T, [1, 0, 0, 0]
            ),
            "sample 0: instance 2 out of range",
        ),
        (
            lambda s: SceneRecord(
                s.name, s.sweeps, s.annotations, s.instances, [0, 0, np.nan], [1, 0, 0, 0]
            ),
            "lidar translation",
        ),
        (
            lambda s: SceneRecord(
                s.name,
                [SweepRecord(1, np.zeros((3, 4), np.float32), [0, 0, 0], [1, 0, 0, 0], True)],
                [[]],
                [],
                LIDAR_T,
                [1, 0, 0, 0],
            ),
            r"shape \(N, 5\)",
        ),
    ],
)
def test_the_writer_rejects_bad_scenes(tmp_path, written, change, match):
    scene = change(written[1][0][0])
    with pytest.raises(DataError, match=match):
        write_nuscenes(tmp_path / "bad", [scene], VERSION)
    assert not (tmp_path / "bad").exists()


# Errors of the reader ------------------------------------------------------------------------
@pytest.fixture
def copy(tmp_path, written):
    import shutil

    root = tmp_path / "copy"
    shutil.copytree(written[0], root)
    return root


def _edit(root, table, edit):
    path = root / VERSION / f"{table}.json"
    rows = json.loads(path.read_text())
    rows = edit(rows)
    path.write_text(json.dumps(rows))


def test_a_missing_table_is_named(copy):
    (copy / VERSION / "ego_pose.json").unlink()
    with pytest.raises(DataError, match=r"ego_pose.json: table 'ego_pose' missing"):
        NuScenesDataset(copy, VERSION)


def test_a_missing_version_lists_those_present(copy):
    with pytest.raises(
        DataError,
        match=r"v1.0-trainval: nuScenes version directory missing "
        r"\(found: v1.0-mini\)",
    ):
        NuScenesDataset(copy, "v1.0-trainval")


@pytest.mark.parametrize(
    ("table", "edit", "match"),
    [
        ("sample", lambda rows: {"a": rows}, "expected a JSON list of records, got dict"),
        ("sample", lambda rows: [*rows, rows[0]], "appears twice"),
        ("sample", lambda rows: [*rows, {"name": 1}], "has no string 'token'"),
        (
            "scene",
            lambda rows: [{**rows[0], "first_sample_token": "nope"}, *rows[1:]],
            r"sample.json: no record with token 'nope' \(referenced by scene.json",
        ),
        (
            "scene",
            lambda rows: [{**rows[0], "first_sample_token": 7}, *rows[1:]],
            "field 'first_sample_token' must be a str, got 7",
        ),
        (
            "sample_data",
            lambda rows: [{k: v for k, v in r.items() if k != "is_key_frame"} for r in rows],
            "field 'is_key_frame' must be a bool",
        ),
        (
            "sample_data",
            lambda rows: [{**r, "calibrated_sensor_token": "x"} for r in rows],
            r"calibrated_sensor.json: no record with token 'x'",
        ),
    ],
)
def test_bad_tables_are_named(copy, table, edit, match):
    _edit(copy, table, edit)
    with pytest.raises(DataError, match=match):
        NuScenesDataset(copy, VERSION)


def test_unreadable_json_is_named(copy):
    (copy / VERSION / "instance.json").write_text("[{")
    with pytest.raises(DataError, match=r"instance.json: cannot read table 'instance'"):
        NuScenesDataset(copy, VERSION)


@pytest.mark.parametrize(
    ("table", "field", "value", "match"),
    [
        ("sample_annotation", "translation", [0.0, float("nan"), 1.0], "field 'translation'"),
        ("sample_annotation", "rotation", [0, 0, 0, 0], "has zero norm"),
        ("sample_annotation", "size", [1.0, -2.0, 1.0], "must be positive"),
        ("sample_annotation", "num_lidar_pts", "12", "'num_lidar_pts' must be a int"),
        ("ego_pose", "rotation", [1.0, 0.0], "rotation: expected 4 finite numbers"),
        ("calibrated_sensor", "translation", None, "translation: expected 3 finite numbers"),
        ("sample_data", "filename", "../../etc/passwd", "must be a path inside the data root"),
    ],
)
def test_bad_fields_are_named_when_a_frame_is_read(copy, table, field, value, match):
    _edit(copy, table, lambda rows: [{**r, field: value} for r in rows])
    dataset = NuScenesDataset(copy, VERSION)
    with pytest.raises(DataError, match=match) as error:
        dataset.frame(dataset.frame_ids[1])
    assert f"{table}.json" in str(error.value)


def test_an_unknown_frame_id_is_named(written):
    dataset = NuScenesDataset(written[0], VERSION)
    with pytest.raises(
        DataError,
        match=r"sample.json: no record with token 'nope' \(referenced "
        "by a frame id\\)",
    ):
        dataset.frame("nope")


def test_a_truncated_point_file_is_named(copy):
    dataset = NuScenesDataset(copy, VERSION)
    path = copy / dataset.frame(dataset.frame_ids[0]).metadata["lidar_path"]
    path.write_bytes(path.read_bytes()[:-3])
    with pytest.raises(DataError, match=rf"{path.name}: 3997 bytes is not a multiple of 20"):
        dataset.frame(dataset.frame_ids[0])


def test_nan_points_are_named(copy):
    dataset = NuScenesDataset(copy, VERSION, sweeps=2)
    frame = dataset.frame(dataset.frame_ids[1])
    points = read_pcd_bin(copy / frame.metadata["lidar_path"])
    points[7, 2] = np.nan
    (copy / frame.metadata["lidar_path"]).write_bytes(points.tobytes())
    with pytest.raises(DataError, match="point 7 holds a NaN"):
        dataset.frame(dataset.frame_ids[1])
    (copy / frame.metadata["lidar_path"]).unlink()
    with pytest.raises(DataError, match="cannot read point cloud"):
        dataset.frame(dataset.frame_ids[1])


def test_sweeps_out_of_time_order_are_named(copy):
    def swap(rows):
        return [
            {**r, "timestamp": r["timestamp"] + (10**6 if not r["is_key_frame"] else 0)}
            for r in rows
        ]

    _edit(copy, "sample_data", swap)
    dataset = NuScenesDataset(copy, VERSION, sweeps=3)
    with pytest.raises(DataError, match="is not earlier than it"):
        dataset.frame(dataset.frame_ids[1])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"sweeps": -1}, "sweeps must be an integer from 0 to 30"),
        ({"sweeps": 31}, "sweeps must be an integer from 0 to 30"),
        ({"sweeps": True}, "sweeps must be an integer"),
        ({"remove_close": -1.0}, "remove_close must be a finite number >= 0"),
        ({"remove_close": float("nan")}, "remove_close must be a finite number >= 0"),
        ({"classes": ["Car"]}, r"classes \['Car'\] not among the nuScenes detection classes"),
        ({"classes": []}, "not among"),
        ({"scenes": "no_such_split.txt"}, "no_such_split.txt: cannot read the scene list"),
        ({"scenes": ["scene-9"]}, r"scene.json: no scene named 'scene-9' \(have: scene-0000"),
    ],
)
def test_bad_arguments_are_named(written, kwargs, match):
    with pytest.raises(DataError, match=match):
        NuScenesDataset(written[0], VERSION, **kwargs)


def test_a_sample_without_lidar_is_named(copy):
    _edit(copy, "sample_data", lambda rows: [{**r, "is_key_frame": False} for r in rows])
    dataset = NuScenesDataset(copy, VERSION)
    with pytest.raises(DataError, match="has no LIDAR_TOP key frame"):
        dataset.frame(dataset.frame_ids[0])


def _scenes_by_name(copy):
    return {s["name"]: s for s in json.loads((copy / VERSION / "scene.json").read_text())}


def test_a_next_chain_running_into_another_scene_is_refused(copy):
    """A chain that runs on past last_sample_token into the next scene would hand that scene's
    samples to a split of this one (a train/val leak)."""
    by_name = _scenes_by_name(copy)
    first, second = by_name["scene-0000"], by_name["scene-0001"]

    def link(rows):
        for row in rows:
            if row["token"] == first["last_sample_token"]:
                row["next"] = second["first_sample_token"]
        return rows

    _edit(copy, "sample", link)
    # the chain stops at last_sample_token: scene-0000 keeps its own 4 samples only
    one = NuScenesDataset(copy, VERSION, scenes=["scene-0000"])
    assert len(one.frame_ids) == 4
    assert {one.frame(t).metadata["scene"] for t in one.frame_ids} == {"scene-0000"}
    _edit(
        copy,
        "scene",
        lambda rows: [
            {**r, "last_sample_token": second["last_sample_token"]}
            if r["name"] == "scene-0000"
            else r
            for r in rows
        ],
    )
    with pytest.raises(DataError, match=r"belongs to scene .*, reached along|reached along"):
        NuScenesDataset(copy, VERSION, scenes=["scene-0000"])


def test_a_chain_that_ends_early_or_a_scene_listed_twice_is_refused(copy):
    by_name = _scenes_by_name(copy)
    first = by_name["scene-0000"]

    def cut(rows):
        samples = {r["token"]: r for r in rows}
        samples[samples[first["first_sample_token"]]["next"]]["next"] = ""
        return rows

    _edit(copy, "sample", cut)
    with pytest.raises(DataError, match="ends at .*, not at its last_sample_token"):
        NuScenesDataset(copy, VERSION, scenes=["scene-0000"])
    with pytest.raises(DataError, match="is reached from scene .* and from scene"):
        NuScenesDataset(copy, VERSION, scenes=["scene-0001", "scene-0001"])
