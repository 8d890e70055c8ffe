"""Velocities (``metadata["velocity"]``) and extra point features through every stage: the
frame's check, per-box bookkeeping, the database (format 2, and format 1 still read), building
from any data set, ground-truth sampling, DR.CPO and the global augmentations. Each op is
checked against a naive reference written here."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
from test_pipeline import synthetic_database, synthetic_frame

from drcpo import occlusion
from drcpo.database import GroundTruthDatabase, ObjectRecord
from drcpo.database.build import build_database_from, frame_records
from drcpo.errors import DataError
from drcpo.frame import VELOCITY, Frame, rotate_velocities, validate_frame
from drcpo.geometry import wrap_angle
from drcpo.index import IndexConfig
from drcpo.index_build import build_index
from drcpo.transforms import DRCPO, GlobalFlip, GlobalRotation, GlobalScaling, GroundTruthSampling
from drcpo.transforms.insertion import placed_object, update_box_metadata

FEATURES = ("intensity", "time_lag")
#: Database intensities lie in [DB_INTENSITY, DB_INTENSITY + 1), the frames' below 1, so an
#: output point's intensity tells where it came from.
DB_INTENSITY = 2.0
DB_TIME_LAG = 0.25  # every database point's time lag: inserted points must come out with 0
#: Canonical velocity of each class in the database (vx along the heading, vy across it).
CANONICAL = {"Car": (5.0, 0.5), "Pedestrian": (0.0, 1.2), "Cyclist": (3.0, -0.4)}


def naive_rotation(v, angle):
    """``R(angle) v`` with the rotation matrix written out, one row at a time."""
    out, v = [], np.reshape(v, (-1, 2))
    for (vx, vy), a in zip(v, np.broadcast_to(angle, len(v)), strict=True):
        matrix = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        out.append(matrix @ np.array([vx, vy]))
    return np.array(out).reshape(-1, 2)


def feature_database(rng, counts=None, velocity=True) -> GroundTruthDatabase:
    """The pipeline tests' synthetic database with points (x, y, z, intensity, time_lag) and,
    with ``velocity``, each class's canonical velocity (:data:`CANONICAL`)."""
    db = synthetic_database(rng, counts or {"Car": 40, "Pedestrian": 20, "Cyclist": 10})
    points = np.column_stack(
        [
            db.points[:, :3],
            DB_INTENSITY + db.points[:, 3],
            np.full(len(db.points), DB_TIME_LAG, np.float32),
        ]
    ).astype(np.float32)
    columns = {"difficulty": db.difficulty}
    if velocity:
        columns["velocity"] = np.array([CANONICAL[str(n)] for n in db.names])
    out = GroundTruthDatabase.from_arrays(points, db.offsets, db.names, db.boxes, **columns)
    out.manifest["point_features"] = list(FEATURES)
    return out


def feature_frame(rng, features=FEATURES) -> Frame:
    """The pipeline tests' synthetic frame with (intensity, time_lag): intensity = row + 1
    scaled below 1 (unique per point), time lags of three sweeps; random velocities."""
    frame = synthetic_frame(rng)
    n = len(frame)
    intensity = (np.arange(n, dtype=np.float64) + 1) / (n + 1)
    lags = rng.choice(np.array([0.0, 0.05, 0.1], dtype=np.float32), n)
    points = np.column_stack([frame.points[:, :3], intensity, lags]).astype(np.float32)
    velocity = rng.normal(0, 3, (len(frame.boxes), 2))
    metadata = {**frame.metadata, VELOCITY: velocity, "point_features": features}
    return frame.replace(points=points, metadata=metadata)


@pytest.fixture(scope="module")
def world():
    db = feature_database(np.random.default_rng(7))
    return db, build_index(db, IndexConfig(k=10))


# The frame's check ----------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("velocity", "message"),
    [
        (np.zeros((3, 2)), r"'velocity' must have shape \(2, 2\)"),
        (np.zeros(2), r"'velocity' must have shape \(2, 2\)"),
        (np.array([[0.0, 1.0], [np.nan, 0.0]]), r"'velocity' row 1 holds a NaN"),
        (np.array([[0.0, 1.0], [0.0, np.inf]]), r"'velocity' row 1 holds a NaN or infinite"),
        (np.array([["a", "b"], ["c", "d"]]), "'velocity' must be real numbers"),
        ([[0.0, 1.0], [2.0]], "'velocity' must be real numbers"),
    ],
)
def test_validate_frame_checks_velocities(velocity, message):
    box = [1.0, 0, 0, 4, 2, 1.5, 0]
    frame = Frame(np.zeros((4, 4), np.float32), np.tile(box, (2, 1)), np.array(["Car"] * 2))
    validate_frame(frame.replace(metadata={VELOCITY: np.ones((2, 2))}))
    validate_frame(frame.replace(metadata={VELOCITY: None}))
    with pytest.raises(DataError, match=f"my frame: metadata {message}"):
        validate_frame(frame.replace(metadata={VELOCITY: velocity}), "my frame")


def test_rotate_velocities_is_the_rotation_matrix(rng):
    v = rng.normal(size=(9, 2))
    angles = rng.uniform(-np.pi, np.pi, 9)
    np.testing.assert_allclose(rotate_velocities(v, angles), naive_rotation(v, angles), atol=1e-12)
    np.testing.assert_allclose(rotate_velocities(v, 0.7), naive_rotation(v, 0.7), atol=1e-12)
    back = rotate_velocities(rotate_velocities(v, angles), -angles)
    np.testing.assert_allclose(back, v, atol=1e-12)


def test_update_box_metadata_keeps_two_dimensional_arrays_in_step():
    velocity = np.arange(8, dtype=np.float64).reshape(4, 2)
    metadata = {VELOCITY: velocity, "difficulty": np.array([0, 1, 2, 1])}
    out = update_box_metadata(metadata, 4, keep=np.array([3, 1]), added=2)
    np.testing.assert_array_equal(out[VELOCITY], [[6, 7], [2, 3], [0, 0], [0, 0]])
    np.testing.assert_array_equal(out["difficulty"], [1, 1, -1, -1])
    given = update_box_metadata(metadata, 4, added=1, added_values={VELOCITY: [[9.0, -9.0]]})
    np.testing.assert_array_equal(given[VELOCITY], [*velocity.tolist(), [9, -9]])
    assert given[VELOCITY].dtype == np.float64
    assert VELOCITY not in update_box_metadata({"difficulty": np.zeros(4)}, 4, added=1)
    stale = {VELOCITY: np.zeros((3, 2))}  # not one row per box: left as it is
    assert update_box_metadata(stale, 4, added=1)[VELOCITY].shape == (3, 2)


# The database ---------------------------------------------------------------------------------
def _records(rng, n=5, velocity=True):
    return [
        ObjectRecord(
            points=rng.normal(size=(int(rng.integers(1, 30)), 5)).astype(np.float32),
            name=["car", "truck"][i % 2],
            box=np.array([*rng.normal(size=3), 4.0, 2.0, 1.5, rng.uniform(-3, 3)]),
            frame_id=f"f{i}",
            index_in_frame=i,
            velocity=rng.normal(size=2) if velocity else None,
        )
        for i in range(n)
    ]


def test_format_2_stores_features_and_velocities(tmp_path, rng):
    records = _records(rng)
    db = GroundTruthDatabase.from_records(records, point_dim=5, point_features=FEATURES)
    db.save(tmp_path / "db")
    opened = GroundTruthDatabase.open(tmp_path / "db")
    manifest = json.loads((tmp_path / "db" / "manifest.json").read_text())
    assert manifest["format_version"] == 2 and manifest["velocity"] is True
    assert manifest["point_features"] == list(FEATURES) == list(opened.point_features)
    np.testing.assert_array_equal(opened.velocity, [r.velocity for r in records])
    assert opened.velocity.dtype == np.float64
    for i, record in enumerate(records):
        np.testing.assert_array_equal(opened.object_points(i), record.points)
    headings = rng.uniform(-3, 3, 2)
    expected = naive_rotation(np.array([records[3].velocity, records[1].velocity]), headings)
    np.testing.assert_allclose(opened.velocities([3, 1], headings), expected, atol=1e-12)
    # the checksum covers the velocities
    np.save(tmp_path / "db" / "velocity.npy", opened.velocity + 1.0)
    with pytest.raises(DataError, match=r"velocity\.npy.*checksum"):
        GroundTruthDatabase.open(tmp_path / "db")


def test_a_database_without_velocities_has_none_and_the_version_1_checksum(tmp_path, rng):
    records = _records(rng, velocity=False)
    db = GroundTruthDatabase.from_records(records, point_dim=5)
    assert db.velocity is None and db.velocities([0], [0.0]) is None
    assert db.point_features == ("intensity", "feature_4")
    db.save(tmp_path / "db")
    assert not (tmp_path / "db" / "velocity.npy").exists()
    assert GroundTruthDatabase.open(tmp_path / "db").checksum == naive_checksum(db)


def test_velocities_of_some_records_only_fill_zero(rng):
    records = _records(rng)
    records[2] = ObjectRecord(records[2].points, "car", records[2].box)
    db = GroundTruthDatabase.from_records(records, point_dim=5)
    np.testing.assert_array_equal(db.velocity[2], [0.0, 0.0])


def naive_checksum(db) -> str:
    """The version-1 checksum, as documented: each array's name, dtype and shape, then its
    bytes, in a fixed order."""
    digest = hashlib.sha256()
    order = (
        "points offsets boxes names frame_ids index_in_frame num_points difficulty occlusion "
        "truncation"
    ).split()
    for name in order:
        array = np.ascontiguousarray(getattr(db, name))
        digest.update(f"{name}:{array.dtype.str}:{array.shape}".encode())
        digest.update(array.reshape(-1).view(np.uint8))
    return "sha256:" + digest.hexdigest()


def write_version_1(path, rng) -> dict[str, np.ndarray]:
    """A database directory in format version 1, as drcpo wrote it before format 2: the ten
    arrays and the manifest keys of then, nothing of format 2."""
    n = 4
    sizes = np.array([3, 0, 5, 2])
    arrays = {
        "points": rng.normal(size=(int(sizes.sum()), 4)).astype(np.float32),
        "offsets": np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
        "boxes": np.column_stack([rng.normal(size=(n, 3)), np.ones((n, 3)), np.zeros(n)]),
        "names": np.array(["Car", "Car", "Pedestrian", "Cyclist"]),
        "frame_ids": np.array(["000000", "000000", "000001", "000002"]),
        "index_in_frame": np.array([0, 1, 0, 0], dtype=np.int32),
        "num_points": sizes.astype(np.int64),
        "difficulty": np.array([0, 1, -1, 2], dtype=np.int8),
        "occlusion": np.array([0, 1, 2, -1], dtype=np.int8),
        "truncation": np.array([0.0, 0.1, np.nan, 0.3], dtype=np.float32),
    }
    path.mkdir()
    for name, array in arrays.items():
        np.save(path / f"{name}.npy", array, allow_pickle=False)

    class Arrays:  # what naive_checksum reads
        pass

    holder = Arrays()
    for name, array in arrays.items():
        setattr(holder, name, array)
    manifest = {
        "format": "drcpo-gt-database",
        "format_version": 1,
        "parameters": {"source": "kitti"},
        "num_objects": n,
        "num_points": int(sizes.sum()),
        "point_dim": 4,
        "classes": {},
        "checksum": naive_checksum(holder),
    }
    (path / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return arrays


def test_version_1_databases_open_unchanged(tmp_path, rng):
    arrays = write_version_1(tmp_path / "v1", rng)
    db = GroundTruthDatabase.open(tmp_path / "v1")
    assert db.manifest["format_version"] == 1
    assert db.velocity is None and db.point_features == ("intensity",)
    for name, array in arrays.items():
        np.testing.assert_array_equal(getattr(db, name), array)
    # saved again: format 2, same data, same checksum
    db.save(tmp_path / "v2")
    again = GroundTruthDatabase.open(tmp_path / "v2")
    assert again.manifest["format_version"] == 2 and again.checksum == db.checksum
    # a version-1 database is still checked against its checksum
    points = arrays["points"].copy()
    points[0, 0] += 1.0
    np.save(tmp_path / "v1" / "points.npy", points)
    with pytest.raises(DataError, match="checksum"):
        GroundTruthDatabase.open(tmp_path / "v1")


def test_format_versions_and_feature_names_are_checked(tmp_path, rng):
    GroundTruthDatabase.from_records(_records(rng), point_dim=5).save(tmp_path / "db")
    path = tmp_path / "db" / "manifest.json"
    manifest = json.loads(path.read_text())
    for version in (3, 0, True):
        path.write_text(json.dumps({**manifest, "format_version": version}))
        with pytest.raises(DataError, match="this drcpo reads 1 or 2"):
            GroundTruthDatabase.open(tmp_path / "db")
    path.write_text(json.dumps({**manifest, "point_features": ["intensity"]}))
    with pytest.raises(DataError, match="point_features.*2 point columns after x, y, z"):
        GroundTruthDatabase.open(tmp_path / "db")
    with pytest.raises(DataError, match="name 1 columns, the points have 2"):
        GroundTruthDatabase.from_records(_records(rng), point_dim=5, point_features=["a"])


class ListDataset:
    """The datasets protocol at its smallest: frame ids and frames."""

    def __init__(self, frames):
        self.frames = {f.frame_id: f for f in frames}
        self.frame_ids = list(self.frames)

    def frame(self, frame_id):
        return self.frames[frame_id]


def dataset_frames(rng, count=3):
    """``count`` feature frames ``s0``, ``s1``, ..., each moved sideways by its own 15 m (the
    synthetic frames all put their objects at the same places)."""
    frames = []
    for k in range(count):
        frame = feature_frame(rng)
        shift = np.array([0.0, 15.0 * (k - (count - 1) / 2), 0.0])
        points = frame.points.copy()
        points[:, :3] += shift.astype(np.float32)
        boxes = frame.boxes.copy()
        boxes[:, :3] += shift
        metadata = {**frame.metadata, "frame_id": f"s{k}"}
        frames.append(frame.replace(points=points, boxes=boxes, metadata=metadata))
    return frames


def test_build_from_any_dataset_stores_features_and_canonical_velocities(tmp_path, rng):
    frames = dataset_frames(rng)
    db = build_database_from(ListDataset(frames), tmp_path / "db", classes="all")
    assert db.point_features == FEATURES and db.points.shape[1] == 5
    assert db.manifest["parameters"]["source"] == "ListDataset"
    assert len(db) == sum(len(f.boxes) for f in frames)
    for row in range(len(db)):
        frame = frames[int(db.frame_ids[row][1:])]
        i = int(db.index_in_frame[row])
        # stored in the canonical frame: R(-heading) v; turned back it is the frame's own
        expected = naive_rotation(frame.metadata[VELOCITY][i], -frame.boxes[i, 6])
        np.testing.assert_allclose(db.velocity[row], expected[0], atol=1e-12)
        np.testing.assert_allclose(
            db.velocities([row], [frame.boxes[i, 6]])[0], frame.metadata[VELOCITY][i], atol=1e-12
        )
    # every column of the object's points is kept (the features as the frame had them)
    record = frame_records(frames[0])[0]
    inside = np.isin(frames[0].points[:, 3], record.points[:, 3])
    np.testing.assert_array_equal(record.points[:, 3:], frames[0].points[inside, 3:])
    parallel = build_database_from(ListDataset(frames), tmp_path / "p", classes="all", workers=2)
    assert parallel.checksum == db.checksum


def test_build_refuses_frames_of_other_feature_counts(tmp_path, rng):
    frames = dataset_frames(rng, 2)
    frames[1] = frames[1].replace(points=frames[1].points[:, :4])
    with pytest.raises(DataError, match="frame s1 has 4 point columns, the first frame 5"):
        build_database_from(ListDataset(frames), tmp_path / "db", classes="all")
    bad = frames[0].replace(metadata={**frames[0].metadata, VELOCITY: np.zeros((1, 2))})
    with pytest.raises(DataError, match="frame s0: metadata 'velocity' must be"):
        frame_records(bad)


# Ground-truth sampling ------------------------------------------------------------------------
def test_gt_sampling_gives_objects_their_velocity_and_database_features(tmp_path, rng):
    frames = dataset_frames(rng, 6)
    db = build_database_from(ListDataset(frames), tmp_path / "db", classes="all")
    target = feature_frame(np.random.default_rng(99))
    out = GroundTruthSampling(db, targets={"Car": 8, "Pedestrian": 6, "Cyclist": 6}, min_points=1)(
        target, np.random.default_rng(1)
    )
    added = np.flatnonzero(out.metadata["box_source"] == "gt_sampling")
    assert len(added) > 0
    assert out.metadata[VELOCITY].shape == (len(out.boxes), 2)
    kept = np.flatnonzero(out.metadata["box_source"] == "")
    np.testing.assert_array_equal(out.metadata[VELOCITY][kept], target.metadata[VELOCITY][kept])
    inserted = 0
    for k in added:
        row = int(np.flatnonzero((db.boxes == out.boxes[k]).all(axis=1))[0])
        inserted += int(db.num_points[row])
        source = frames[int(db.frame_ids[row][1:])]
        i = int(db.index_in_frame[row])
        np.testing.assert_allclose(out.metadata[VELOCITY][k], source.metadata[VELOCITY][i], 1e-9)
        # its points: the database's, placed at the box, features as stored, time lag 0
        expected = placed_object(db.object_points(row), out.boxes[k], 5)
        expected[:, 4] = 0.0
        rows = {r.tobytes() for r in out.points}
        assert all(r.tobytes() in rows for r in expected)
    # the frame's own points that are kept (they come first) keep their features bit for bit
    original = out.points[: len(out) - inserted]
    by_intensity = {float(v): r for r, v in enumerate(target.points[:, 3])}
    source_rows = [by_intensity[float(v)] for v in original[:, 3]]
    assert len(set(source_rows)) == len(source_rows)
    np.testing.assert_array_equal(original, target.points[source_rows])


def test_gt_sampling_without_velocities_leaves_them_out(world):
    db, _ = world
    frame = feature_frame(np.random.default_rng(3))
    frame = frame.replace(metadata={k: v for k, v in frame.metadata.items() if k != VELOCITY})
    out = GroundTruthSampling(db)(frame, np.random.default_rng(1))
    assert VELOCITY not in out.metadata and len(out.boxes) > len(frame.boxes)


def test_a_database_without_velocities_gives_added_boxes_zero(rng):
    db = feature_database(np.random.default_rng(7), velocity=False)
    frame = feature_frame(rng)
    out = GroundTruthSampling(db)(frame, np.random.default_rng(1))
    added = out.metadata["box_source"] == "gt_sampling"
    assert added.any() and (out.metadata[VELOCITY][added] == 0).all()


# DR.CPO ---------------------------------------------------------------------------------------
def test_drcpo_velocities_follow_the_new_headings(world):
    db, index = world
    frame = feature_frame(np.random.default_rng(5))
    transform = DRCPO(db, index)
    added_any = False
    for seed in range(4):
        out = transform(frame, np.random.default_rng(seed))
        source = out.metadata["box_source"]
        added = np.flatnonzero(source == "drcpo")
        added_any |= len(added) > 0
        velocity = out.metadata[VELOCITY]
        assert velocity.shape == (len(out.boxes), 2)
        for k in added:
            canonical = np.array(CANONICAL[str(out.names[k])])
            expected = naive_rotation(canonical[None], out.boxes[k, 6])[0]
            np.testing.assert_allclose(velocity[k], expected, atol=1e-12)
        # the frame's own boxes that are left keep theirs (in order)
        own = np.flatnonzero(source == "")
        left = [int(np.flatnonzero((frame.boxes == b).all(axis=1))[0]) for b in out.boxes[own]]
        np.testing.assert_array_equal(velocity[own], frame.metadata[VELOCITY][left])
    assert added_any


def test_drcpo_keeps_untouched_features_and_inserts_the_databases(world):
    db, index = world
    frame = feature_frame(np.random.default_rng(5))
    out = DRCPO(db, index)(frame, np.random.default_rng(2))
    inserted = out.points[:, 3] >= DB_INTENSITY
    assert inserted.any() and (~inserted).any()
    # untouched points: bit for bit (intensity is unique per frame point)
    by_intensity = {float(v): r for r, v in enumerate(frame.points[:, 3])}
    rows = [by_intensity[float(v)] for v in out.points[~inserted, 3]]
    np.testing.assert_array_equal(out.points[~inserted], frame.points[rows])
    # inserted: the database's intensities, time lag 0 (the key sweep)
    assert np.isin(out.points[inserted, 3], db.points[:, 3]).all()
    assert (out.points[inserted, 4] == 0).all()


def test_inserted_points_keep_every_database_column_when_no_time_lag_is_named(world):
    db, index = world
    frame = feature_frame(np.random.default_rng(5), features=("intensity", "ring"))
    out = DRCPO(db, index)(frame, np.random.default_rng(2))
    inserted = out.points[:, 3] >= DB_INTENSITY
    assert inserted.any() and (out.points[inserted, 4] == np.float32(DB_TIME_LAG)).all()
    wider = frame.replace(points=np.column_stack([frame.points, np.ones(len(frame), np.float32)]))
    out = DRCPO(db, index)(wider, np.random.default_rng(2))
    inserted = out.points[:, 3] >= DB_INTENSITY
    assert inserted.any() and (out.points[inserted, 5] == 0).all()  # beyond the database's


# The global augmentations ---------------------------------------------------------------------
def naive_openpcdet(boxes9, axis=None, angle=None, scale=None):
    """OpenPCDet's augmentor arithmetic on 9-value boxes, written out (our own reference)."""
    b = boxes9.copy()
    if axis == "x":
        b[:, 1], b[:, 6], b[:, 8] = -b[:, 1], -b[:, 6], -b[:, 8]
    if axis == "y":
        b[:, 0], b[:, 6], b[:, 7] = -b[:, 0], -(b[:, 6] + np.pi), -b[:, 7]
    if angle is not None:
        b[:, 0:2] = naive_rotation(b[:, 0:2], angle)
        b[:, 6] += angle
        b[:, 7:9] = naive_rotation(b[:, 7:9], angle)
    if scale is not None:
        b[:, :6] *= scale
        b[:, 7:] *= scale
    return b


def _nine(frame):
    return np.column_stack([frame.boxes, frame.metadata[VELOCITY]])


def assert_boxes_match(out, expected):
    np.testing.assert_allclose(out.boxes[:, :6], expected[:, :6], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(out.boxes[:, 6] - expected[:, 6]), 0, atol=1e-9)
    np.testing.assert_allclose(out.metadata[VELOCITY], expected[:, 7:], atol=1e-9)


@pytest.mark.parametrize("axis", ["x", "y"])
def test_global_flip_flips_velocities(rng, axis):
    frame = feature_frame(rng)
    out = GlobalFlip(probability=1.0, axes=(axis,))(frame, np.random.default_rng(0))
    assert_boxes_match(out, naive_openpcdet(_nine(frame), axis=axis))
    both = GlobalFlip(probability=1.0, axes=("x", "y"))(frame, np.random.default_rng(0))
    expected = naive_openpcdet(naive_openpcdet(_nine(frame), axis="x"), axis="y")
    assert_boxes_match(both, expected)
    none = GlobalFlip(probability=0.0, axes=("x", "y"))(frame, np.random.default_rng(0))
    assert none.metadata[VELOCITY] is frame.metadata[VELOCITY]


def test_global_rotation_and_scaling_move_velocities(rng):
    frame = feature_frame(rng)
    out = GlobalRotation()(frame, np.random.default_rng(4))
    angle = out.metadata["augment_stats"]["stages"]["global_rotation"]["angle"][0]
    assert_boxes_match(out, naive_openpcdet(_nine(frame), angle=angle))
    out = GlobalScaling()(frame, np.random.default_rng(4))
    scale = out.metadata["augment_stats"]["stages"]["global_scaling"]["scale"][0]
    assert_boxes_match(out, naive_openpcdet(_nine(frame), scale=scale))


# The nuscenes preset: per-class defaults for the ten classes ----------------------------------
NUSCENES = {"Car": "car", "Pedestrian": "pedestrian", "Cyclist": "bicycle"}
KITTI_NAME = {nuscenes: kitti for kitti, nuscenes in NUSCENES.items()}


def test_nuscenes_preset_names_the_ten_classes_their_mirroring_and_grids():
    from drcpo.config import load_config
    from drcpo.partitions import DEFAULT_GRIDS, NUSCENES_MIRRORED

    config = load_config("nuscenes")
    ten = [
        "car",
        "truck",
        "construction_vehicle",
        "bus",
        "trailer",
        "barrier",
        "motorcycle",
        "bicycle",
        "pedestrian",
        "traffic_cone",
    ]
    assert config.known_classes == ten
    assert set(config.drcpo.sample) == set(config.gt_sampling.targets) == set(ten)
    assert config.drcpo.construction.mirror == list(NUSCENES_MIRRORED) == config.index.mirror
    for name in ten:  # every class has its own grid; the long vehicles more cells along x
        assert config.drcpo.construction.grid(name) == DEFAULT_GRIDS[name]
    assert DEFAULT_GRIDS["bus"][0] > DEFAULT_GRIDS["truck"][0] > DEFAULT_GRIDS["car"][0]
    assert config.drcpo.placement.x_range == [-51.2, 51.2]


def test_nuscenes_preset_places_objects_all_around_the_sensor():
    from drcpo.config import load_config

    config = load_config("nuscenes")
    base = feature_database(np.random.default_rng(7), {"Car": 30, "Pedestrian": 15, "Cyclist": 15})
    names = np.array([NUSCENES[str(n)] for n in base.names])
    columns = {"difficulty": base.difficulty, "velocity": base.velocity}
    db = GroundTruthDatabase.from_arrays(base.points, base.offsets, names, base.boxes, **columns)
    index = build_index(db, config.index)
    assert index.config.mirror == config.drcpo.construction.mirror
    frame = feature_frame(np.random.default_rng(5))
    frame = frame.replace(names=np.array([NUSCENES[str(n)] for n in frame.names]))
    transform = DRCPO(db, index, config.drcpo)
    behind = 0
    for seed in range(6):
        out = transform(frame, np.random.default_rng(seed))
        added = out.metadata["box_source"] == "drcpo"
        behind += int(np.count_nonzero(out.boxes[added, 0] < 0))
        for k in np.flatnonzero(added):
            canonical = np.array(CANONICAL[KITTI_NAME[str(out.names[k])]])
            expected = naive_rotation(canonical[None], out.boxes[k, 6])[0]
            np.testing.assert_allclose(out.metadata[VELOCITY][k], expected, atol=1e-12)
    assert behind > 0  # no camera cut: the full circle


# Multi-sweep frames ---------------------------------------------------------------------------
LAGS = np.array([0.0, 0.05, 0.1])  # the feature frames' three sweeps (float32-exact? see below)
ORIGINS = np.array([[0.0, 0.0, 0.0], [-0.6, 0.1, 0.0], [-1.2, 0.2, 0.01]])


def multi_sweep_frame(rng) -> Frame:
    frame = feature_frame(rng)
    lags = LAGS.astype(np.float32).astype(np.float64)  # the points hold float32 values
    return frame.replace(
        metadata={**frame.metadata, "sweep_origins": ORIGINS, "sweep_time_lags": lags}
    )


def naive_hidden_behind(originals, objects, boxes, viewpoint, radius):
    """Original points hidden with the objects and visible without them, in the boxes' view
    windows (e-HPR's inserted scope, step 2), from two plain HPR calls."""
    from drcpo.occlusion.view_windows import grown_boxes, view_windows

    with_objects = occlusion.hidden_point_removal(
        np.concatenate([originals, objects]), viewpoint, radius
    )[: len(originals)]
    alone = occlusion.hidden_point_removal(originals, viewpoint, radius)
    windows = view_windows(originals, grown_boxes(boxes), viewpoint, behind=True)
    return windows & ~with_objects & alone


def test_multi_sweep_key_sweep_goes_through_drcpo_alone(world):
    db, index = world
    frame = multi_sweep_frame(np.random.default_rng(5))
    transform = DRCPO(db, index)
    key = frame.points[:, 4] == 0
    alone = transform(frame.replace(points=frame.points[key]), np.random.default_rng(1))
    out = transform(frame, np.random.default_rng(1))
    np.testing.assert_array_equal(out.boxes, alone.boxes)
    np.testing.assert_array_equal(out.points[: len(alone)], alone.points)
    assert (out.metadata["box_source"] == "drcpo").any()


def test_multi_sweep_earlier_sweeps_are_settled_from_their_own_origins(world):
    from drcpo.occlusion.view_windows import grown_boxes

    db, index = world
    frame = multi_sweep_frame(np.random.default_rng(5))
    transform = DRCPO(db, index)
    key = frame.points[:, 4] == 0
    alone = transform(frame.replace(points=frame.points[key]), np.random.default_rng(1))
    out = transform(frame, np.random.default_rng(1))
    rest = out.points[len(alone) :]
    added = out.metadata["box_source"] == "drcpo"
    boxes = out.boxes[added]
    objects = alone.points[transform_inside(alone.points, boxes)]
    setting = transform.config.external_occlusion
    expected, from_key_origin = [], []
    for s in (1, 2):
        points = frame.points[frame.points[:, 4] == np.float32(LAGS[s])]
        points = points[~transform_inside(points, grown_boxes(boxes, transform.room))]
        viewpoint = ORIGINS[s] + [0.0, 0.0, setting.viewpoint_z]
        hidden = naive_hidden_behind(
            points[:, :3], objects[:, :3], boxes, viewpoint, setting.radius
        )
        expected.append(points[~hidden])
        key_view = np.array([0.0, 0.0, setting.viewpoint_z])
        hidden = naive_hidden_behind(points[:, :3], objects[:, :3], boxes, key_view, setting.radius)
        from_key_origin.append(points[~hidden])
    assert any(len(a) != len(b) for a, b in zip(expected, from_key_origin, strict=True))
    expected = np.concatenate(expected)
    # the same points (every feature bit for bit), as a set: the order is the frame's
    as_set = lambda p: sorted(map(bytes, np.ascontiguousarray(p)))  # noqa: E731
    assert as_set(rest) == as_set(expected)
    assert len(rest) < int(np.count_nonzero(~key))  # the objects took some away


def transform_inside(points, boxes):
    from drcpo.geometry import points_in_boxes

    if len(boxes) == 0:
        return np.zeros(len(points), dtype=bool)
    return points_in_boxes(points, boxes).any(axis=1)


def test_multi_sweep_metadata_is_checked(world):
    db, index = world
    frame = multi_sweep_frame(np.random.default_rng(5))
    transform = DRCPO(db, index)
    points = frame.points.copy()
    points[7, 4] = 0.07
    with pytest.raises(DataError, match="point row 7 has time lag 0.07.*sweep_time_lags"):
        transform(frame.replace(points=points), np.random.default_rng(0))
    bad = {**frame.metadata, "sweep_origins": ORIGINS[:2]}
    with pytest.raises(DataError, match=r"'sweep_origins' must be \(3, 3\)"):
        transform(frame.replace(metadata=bad), np.random.default_rng(0))
    one = {**frame.metadata, "sweep_origins": ORIGINS[:1], "sweep_time_lags": LAGS[:1]}
    single = frame.replace(points=frame.points[frame.points[:, 4] == 0], metadata=one)
    plain = {k: v for k, v in single.metadata.items() if not k.startswith("sweep_")}
    np.testing.assert_array_equal(
        transform(single, np.random.default_rng(0)).points,
        transform(single.replace(metadata=plain), np.random.default_rng(0)).points,
    )


def test_a_dict_of_nine_value_boxes_gives_its_velocities_to_the_frame():
    boxes = np.array([[1.0, 2, 0, 4, 2, 1.5, 0.3, 5.0, -1.0], [9.0, 2, 0, 4, 2, 1.5, 1.0, 0, 2]])
    data = {"points": np.zeros((3, 5), np.float32), "gt_boxes": boxes, "gt_names": ["car"] * 2}
    frame = Frame.from_dict(data)
    np.testing.assert_array_equal(frame.boxes, boxes[:, :7])
    np.testing.assert_array_equal(frame.metadata[VELOCITY], boxes[:, 7:])
    given = Frame.from_dict({**data, VELOCITY: np.ones((2, 2))})
    np.testing.assert_array_equal(given.metadata[VELOCITY], np.ones((2, 2)))
    eight = Frame.from_dict({**data, "gt_boxes": boxes[:, :8]})  # a class column: dropped
    assert VELOCITY not in eight.metadata and eight.boxes.shape == (2, 7)
    boxes[1, 8] = np.nan
    with pytest.raises(DataError, match="'velocity' row 1 holds a NaN"):
        GlobalRotation()({**data, "gt_boxes": boxes}, np.random.default_rng(0))


def test_importing_nine_value_dbinfos_keeps_canonical_velocities(tmp_path):
    import pickle

    from conftest import KITTI_SAMPLE

    from drcpo.database import safe_pickle
    from drcpo.database.dbinfos import import_openpcdet

    if not KITTI_SAMPLE.is_dir():
        pytest.skip(f"KITTI sample not found at {KITTI_SAMPLE} (only CI and developers have it)")
    infos = safe_pickle.load(KITTI_SAMPLE / "kitti_dbinfos_train.pkl")
    rng = np.random.default_rng(0)
    given = {}
    for objects in infos.values():
        for info in objects:
            velocity = rng.normal(0, 3, 2)
            info["box3d_lidar"] = np.concatenate([info["box3d_lidar"], velocity])
            given[(str(info["image_idx"]), int(info["gt_idx"]))] = (velocity, info["box3d_lidar"])
    (tmp_path / "nine.pkl").write_bytes(pickle.dumps(infos))
    db = import_openpcdet(tmp_path / "nine.pkl", tmp_path / "db", root=KITTI_SAMPLE)
    assert db.velocity is not None and len(db) == len(given)
    for row in range(len(db)):
        velocity, box = given[(str(db.frame_ids[row]), int(db.index_in_frame[row]))]
        np.testing.assert_allclose(db.velocity[row], naive_rotation(velocity, -box[6])[0], 1e-12)
    plain = import_openpcdet(KITTI_SAMPLE / "kitti_dbinfos_train.pkl", tmp_path / "plain")
    assert plain.velocity is None
    np.testing.assert_array_equal(plain.points, db.points)
    first = next(iter(infos.values()))[0]
    first["box3d_lidar"][8] = np.nan
    (tmp_path / "bad.pkl").write_bytes(pickle.dumps(infos))
    with pytest.raises(DataError, match="velocities .* are finite"):
        import_openpcdet(tmp_path / "bad.pkl", tmp_path / "bad", root=KITTI_SAMPLE)
