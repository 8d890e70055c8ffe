import numpy as np
import pytest

from drcpo.database import GroundTruthDatabase, ObjectRecord
from drcpo.datasets.kitti import Calibration
from drcpo.errors import ConfigError
from drcpo.frame import Frame
from drcpo.geometry import bev_overlap_area, box_corners, from_canonical, points_in_boxes
from drcpo.pipeline import (
    BoxQuery,
    Compose,
    GlobalFlip,
    GlobalRotation,
    GlobalScaling,
    GroundTruthSampling,
    Stats,
    match_features,
    road_plane_heights,
    transform_from_config,
)

SIZES = {"Car": (3.9, 1.6, 1.56), "Pedestrian": (0.8, 0.6, 1.73), "Cyclist": (1.76, 0.6, 1.73)}
GROUND_Z = -1.73


# --------------------------------------------------------------------------------------------
# Synthetic data
# --------------------------------------------------------------------------------------------
def surface_points(rng, dims, n):
    """``(n, 4)`` canonical points on the faces of a box of size ``dims`` (no bottom face)."""
    local = rng.uniform(-0.5, 0.5, (n, 3))
    face = rng.choice([0, 1, 2], n, p=[0.35, 0.35, 0.3])
    local[np.arange(n), face] = np.where(face == 2, 0.5, 0.5 * np.sign(local[np.arange(n), face]))
    xyz = local * np.asarray(dims)
    return np.column_stack([xyz, rng.uniform(0, 1, n)]).astype(np.float32)


def synthetic_database(rng, counts, min_pts=2, max_pts=300):
    """Objects of KITTI-like sizes at random on-ground poses, surface points in canonical pose."""
    records = []
    for name, count in counts.items():
        for _ in range(count):
            dims = np.asarray(SIZES[name]) * rng.uniform(0.85, 1.15, 3)
            x, y = rng.uniform(3, 60), rng.uniform(-30, 30)
            box = np.array([x, y, GROUND_Z + dims[2] / 2, *dims, rng.uniform(-np.pi, np.pi)])
            pts = surface_points(rng, dims, int(rng.integers(min_pts, max_pts)))
            records.append(
                ObjectRecord(pts, name, box, frame_id="synthetic", difficulty=rng.integers(-1, 3))
            )
    return GroundTruthDatabase.from_records(records)


def synthetic_frame(rng, objects=4, ground=6000, features=1):
    """Flat ground, a wall and a few labelled objects; ``features`` extra point columns."""
    gx, gy = rng.uniform(0, 70, ground), rng.uniform(-40, 40, ground)
    ground_xyz = np.column_stack([gx, gy, GROUND_Z + rng.normal(0, 0.01, ground)])
    wall = np.column_stack(
        [rng.uniform(10, 30, 800), np.full(800, 12.0), rng.uniform(GROUND_Z, 2.0, 800)]
    )
    boxes, names, parts = [], [], [ground_xyz, wall]
    for i in range(objects):
        name = list(SIZES)[i % 3]
        dims = np.asarray(SIZES[name])
        box = np.array([8 + 7 * i, -6 + 3 * i, GROUND_Z + dims[2] / 2, *dims, 0.3 * i])
        boxes.append(box)
        names.append(name)
        parts.append(from_canonical(surface_points(rng, dims, 200)[:, :3], box))
    xyz = np.concatenate(parts)
    feats = rng.uniform(0, 1, (len(xyz), features))
    points = np.column_stack([xyz, feats]).astype(np.float32)
    calib = Calibration(
        P2=np.array([[721.5, 0, 609.6, 44.9], [0, 721.5, 172.9, 0.2], [0, 0, 1, 0.003]]),
        R0_rect=np.eye(3),
        Tr_velo_to_cam=np.array([[0, -1, 0, 0], [0, 0, -1, -0.08], [1, 0, 0, -0.27]]),
    )
    return Frame(
        points,
        np.array(boxes).reshape(-1, 7),
        np.array(names),
        {"frame_id": "synthetic", "calib": calib},
    )


@pytest.fixture(scope="module")
def small_db():
    return synthetic_database(
        np.random.default_rng(7), {"Car": 60, "Pedestrian": 30, "Cyclist": 20}
    )


def frame_points_set(points):
    return {tuple(row) for row in np.asarray(points).view(np.uint32).tolist()}


# --------------------------------------------------------------------------------------------
# Global augmentation
# --------------------------------------------------------------------------------------------
def assert_box_membership_kept(before: Frame, after: Frame, tol=1e-3):
    """Points well inside a box stay inside it; points well outside stay outside."""
    inner_before = points_in_boxes(before.points, before.boxes, margin=-tol)
    inner_after = points_in_boxes(after.points, after.boxes, margin=-tol)
    loose_before = points_in_boxes(before.points, before.boxes, margin=tol)
    loose_after = points_in_boxes(after.points, after.boxes, margin=tol)
    assert not (inner_before & ~loose_after).any()
    assert not (inner_after & ~loose_before).any()
    assert inner_before.sum() > 0


@pytest.mark.parametrize(
    "transform",
    [
        GlobalFlip(probability=1.0),
        GlobalFlip(probability=1.0, axes=("x", "y")),
        GlobalRotation(),
        GlobalScaling(),
        Compose([GlobalFlip(1.0), GlobalRotation((-3.0, 3.0)), GlobalScaling((0.5, 2.0))]),
    ],
)
def test_global_transforms_move_points_with_their_boxes(transform, rng):
    frame = synthetic_frame(rng, features=3)
    before_points = frame.points.copy()
    out = transform(frame, np.random.default_rng(1))
    assert_box_membership_kept(frame, out)
    np.testing.assert_array_equal(out.points[:, 3:], frame.points[:, 3:])  # features untouched
    np.testing.assert_array_equal(frame.points, before_points)  # input not modified
    assert out.points.dtype == np.float32 and out.points.shape == frame.points.shape
    assert (out.boxes[:, 6] >= -np.pi).all() and (out.boxes[:, 6] < np.pi).all()


def test_flip_along_x_negates_y_and_heading(rng):
    frame = synthetic_frame(rng)
    out = GlobalFlip(probability=1.0)(frame, rng)
    np.testing.assert_array_equal(out.points[:, 1], -frame.points[:, 1])
    np.testing.assert_array_equal(out.points[:, [0, 2, 3]], frame.points[:, [0, 2, 3]])
    np.testing.assert_allclose(np.sin(out.boxes[:, 6]), -np.sin(frame.boxes[:, 6]), atol=1e-12)
    np.testing.assert_allclose(np.cos(out.boxes[:, 6]), np.cos(frame.boxes[:, 6]), atol=1e-12)
    unchanged = GlobalFlip(probability=0.0)(frame, rng)
    np.testing.assert_array_equal(unchanged.points, frame.points)
    np.testing.assert_array_equal(unchanged.boxes, frame.boxes)


def test_flip_happens_about_half_the_time(rng):
    frame = synthetic_frame(rng, objects=1, ground=10)
    flips = [GlobalFlip()(frame, rng).boxes[0, 1] < 0 for _ in range(400)]
    assert 150 < sum(flips) < 250


def test_rotation_and_scaling_stay_in_their_ranges(rng):
    frame = synthetic_frame(rng, objects=3, ground=10)
    for _ in range(50):
        rotated = GlobalRotation((-0.5, 0.5))(frame, rng)
        delta = (rotated.boxes[:, 6] - frame.boxes[:, 6] + np.pi) % (2 * np.pi) - np.pi
        assert np.ptp(delta) < 1e-9 and -0.5 <= delta[0] <= 0.5
        # Rotation keeps distances to the sensor.
        np.testing.assert_allclose(
            np.linalg.norm(rotated.points[:, :2], axis=1),
            np.linalg.norm(frame.points[:, :2], axis=1),
            rtol=1e-6,
        )
        scaled = GlobalScaling((0.9, 1.2))(frame, rng)
        factor = scaled.boxes[:, 3:6] / frame.boxes[:, 3:6]
        assert np.ptp(factor) < 1e-9 and 0.9 <= factor[0, 0] <= 1.2
        np.testing.assert_allclose(scaled.boxes[:, :3], frame.boxes[:, :3] * factor[0, 0])


def test_rotation_matches_box_corners(rng):
    frame = synthetic_frame(rng)
    out = GlobalRotation((0.7, 0.7))(frame, rng)
    c, s = np.cos(0.7), np.sin(0.7)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    np.testing.assert_allclose(box_corners(out.boxes), box_corners(frame.boxes) @ rot.T, atol=1e-9)


@pytest.mark.parametrize("features", [0, 1, 4])
def test_empty_frames_and_any_feature_count(features, small_db, rng):
    empty = Frame(np.zeros((0, 3 + features), np.float32))
    pipeline = Compose([GroundTruthSampling(small_db), GlobalFlip(), GlobalRotation()])
    out = pipeline(empty, rng)
    assert out.points.shape[1] == 3 + features
    assert len(out.boxes) > 0  # ground truth sampling still fills the empty frame
    inserted = points_in_boxes(out.points, out.boxes, margin=1e-3).any(axis=1)
    assert inserted.all()


def test_dict_in_dict_out_keeps_other_keys(small_db, rng):
    frame = synthetic_frame(rng)
    data = frame.to_dict()
    data["custom"] = {"anything": [1, 2]}
    data["frame_id"] = "000123"
    pipeline = Compose([GroundTruthSampling(small_db), GlobalFlip(), GlobalScaling()])
    out = pipeline(data, np.random.default_rng(0))
    assert isinstance(out, dict)
    assert out["custom"] is data["custom"] and out["frame_id"] == "000123"
    assert out["points"].dtype == np.float32 and out["gt_boxes"].shape[1] == 7
    assert len(out["gt_names"]) == len(out["gt_boxes"])
    assert "augment_stats" in out and "augment_stats" not in data
    assert isinstance(GlobalRotation()(frame, rng), Frame)


def test_rng_must_be_a_generator(rng):
    with pytest.raises(TypeError, match="Generator"):
        GlobalFlip()(synthetic_frame(rng), 42)
    with pytest.raises(TypeError, match="Frame or an OpenPCDet"):
        GlobalFlip()(np.zeros((3, 4)), rng)


def test_same_seed_same_output(small_db, rng):
    frame = synthetic_frame(rng)
    pipeline = Compose(
        [GroundTruthSampling(small_db), GlobalFlip(), GlobalRotation(), GlobalScaling()]
    )
    a = pipeline(frame, np.random.default_rng(5))
    b = pipeline(frame, np.random.default_rng(5))
    c = pipeline(frame, np.random.default_rng(6))
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.boxes, b.boxes)
    assert not np.array_equal(a.boxes, c.boxes)


# --------------------------------------------------------------------------------------------
# Config round trip, repr, validation
# --------------------------------------------------------------------------------------------
def test_transforms_round_trip_their_config(small_db):
    pipeline = Compose(
        [
            GroundTruthSampling(small_db, targets={"Car": 5}, min_points={"Car": 9}),
            GlobalFlip(0.3, axes=("x", "y")),
            GlobalRotation((-1.0, 0.5)),
            GlobalScaling((0.9, 1.1)),
        ]
    )
    config = pipeline.to_config()
    assert config["transforms"][1] == {"type": "GlobalFlip", "probability": 0.3, "axes": ["x", "y"]}
    rebuilt = transform_from_config(config, database=small_db)
    assert rebuilt == pipeline and rebuilt.to_config() == config
    assert "GlobalRotation(range=[-1.0, 0.5])" in repr(pipeline)
    assert "targets={'Car': 5}" in repr(pipeline[0])
    with pytest.raises(ConfigError, match="type"):
        transform_from_config({"type": "Jitter"})
    with pytest.raises(ConfigError, match="database"):
        transform_from_config(config["transforms"][0])


def test_bad_parameters_raise_config_errors(small_db):
    with pytest.raises(ConfigError, match="range"):
        GlobalScaling((1.1, 0.9))
    with pytest.raises(ConfigError, match="probability"):
        GlobalFlip(1.5)
    with pytest.raises(ConfigError, match="axes"):
        GlobalFlip(axes=("z",))
    with pytest.raises(ConfigError, match=r"targets\.Car"):
        GroundTruthSampling(small_db, targets={"Car": -1})


# --------------------------------------------------------------------------------------------
# Ground-truth sampling
# --------------------------------------------------------------------------------------------
def test_gt_sampling_fills_up_to_targets_without_overlaps(small_db, rng):
    frame = synthetic_frame(rng, objects=4)
    targets = {"Car": 20, "Pedestrian": 15, "Cyclist": 15}
    out = GroundTruthSampling(small_db, targets=targets)(frame, rng)
    new = out.boxes[len(frame.boxes) :]
    stats = out.metadata["augment_stats"]["objects"]["gt_sampling"]
    for name, target in targets.items():
        existing = int((frame.names == name).sum())
        entry = stats[name]
        assert entry["tried"] == max(0, target - existing)
        assert entry["tried"] == entry["added"] + sum(entry["rejected"].values())
        assert (out.names[len(frame.boxes) :] == name).sum() == entry["added"]
        assert (out.names == name).sum() <= max(target, existing)
    assert sum(s["added"] for s in stats.values()) == len(new) > 0
    overlap = bev_overlap_area(new, out.boxes)
    overlap[np.arange(len(new)), len(frame.boxes) + np.arange(len(new))] = 0
    assert overlap.max() == 0


def test_gt_sampling_keeps_original_pose_points_and_untouched_frame_points(small_db, rng):
    frame = synthetic_frame(rng, objects=2)
    sampler = GroundTruthSampling(small_db, targets={"Car": 12, "Pedestrian": 6})
    out = sampler(frame, rng)
    new = out.boxes[len(frame.boxes) :]
    rows = [int(np.flatnonzero((small_db.boxes == box).all(axis=1))[0]) for box in new]
    assert all(small_db.num_points[r] >= 5 for r in rows)  # min_points filter
    # Original place and heading (no road plane in this frame).
    np.testing.assert_array_equal(new, small_db.boxes[rows])
    # Frame points outside the sampled boxes are kept bit for bit, in order, as a prefix.
    keep = ~points_in_boxes(frame.points, new).any(axis=1)
    np.testing.assert_array_equal(out.points[: keep.sum()], frame.points[keep])
    objects = np.concatenate(
        [from_canonical(small_db.object_points(r), small_db.boxes[r]) for r in rows]
    ).astype(np.float32)
    np.testing.assert_array_equal(out.points[keep.sum() :], objects)


def test_gt_sampling_filters_difficulty_and_min_points(rng):
    db = synthetic_database(rng, {"Car": 80}, min_pts=1, max_pts=12)
    sampler = GroundTruthSampling(db, targets={"Car": 40}, min_points=8, exclude_difficulty=[-1, 2])
    out = sampler(Frame(np.zeros((0, 4), np.float32)), rng)
    rows = [int(np.flatnonzero((db.boxes == box).all(axis=1))[0]) for box in out.boxes]
    assert len(rows) > 0
    assert (db.num_points[rows] >= 8).all()
    assert not np.isin(db.difficulty[rows], [-1, 2]).any()


def test_gt_sampling_drops_both_boxes_of_a_colliding_pair(rng):
    pts = surface_points(rng, SIZES["Car"], 50)
    box_a = np.array([10.0, 0.0, -0.95, *SIZES["Car"], 0.0])
    box_b = box_a + np.array([1.0, 0.5, 0, 0, 0, 0, 0.2])
    db = GroundTruthDatabase.from_records(
        [ObjectRecord(pts, "Car", box_a), ObjectRecord(pts, "Car", box_b)]
    )
    frame = Frame(np.zeros((0, 4), np.float32))
    out = GroundTruthSampling(db, targets={"Car": 2})(frame, rng)
    assert len(out.boxes) == 0
    stats = out.metadata["augment_stats"]["objects"]["gt_sampling"]["Car"]
    assert stats == {"tried": 2, "added": 0, "rejected": {"collision": 2}}
    # A frame box at the same place blocks a single draw too.
    blocked = Frame(np.zeros((0, 4), np.float32), box_a[None] + [0.5, 0, 0, 0, 0, 0, 0], ["Van"])
    out = GroundTruthSampling(db, targets={"Car": 1})(blocked, rng)
    assert len(out.boxes) == 1


def test_gt_sampling_with_targets_met_or_empty_pool_changes_nothing(small_db, rng):
    frame = synthetic_frame(rng, objects=3)
    out = GroundTruthSampling(small_db, targets={"Car": 1, "Truck": 4})(frame, rng)
    np.testing.assert_array_equal(out.points, frame.points)
    np.testing.assert_array_equal(out.boxes, frame.boxes)


def test_gt_sampling_puts_boxes_on_the_road_plane(small_db, rng):
    frame = synthetic_frame(rng, objects=0)
    # KITTI-style plane (camera coords, y down): the road 1.5 m below the camera, slightly tilted.
    plane = np.array([0.01, -1.0, 0.02, 1.5])
    frame = frame.replace(metadata={**frame.metadata, "plane": plane})
    out = GroundTruthSampling(small_db, targets={"Car": 10})(frame, rng)
    assert len(out.boxes) > 0
    bottoms = out.boxes[:, 2] - out.boxes[:, 5] / 2
    expected = road_plane_heights(plane, frame.metadata["calib"], out.boxes[:, :3])
    np.testing.assert_allclose(bottoms, expected, atol=1e-4)
    # The points moved with their boxes.
    assert points_in_boxes(out.points, out.boxes, margin=1e-3).any(axis=1).sum() >= sum(
        small_db.num_points[(small_db.boxes[:, 3:6] == box[3:6]).all(axis=1)].sum()
        for box in out.boxes
    )
    off = GroundTruthSampling(small_db, targets={"Car": 10}, use_road_plane=False)(frame, rng)
    bottoms_off = off.boxes[:, 2] - off.boxes[:, 5] / 2
    np.testing.assert_allclose(bottoms_off, GROUND_Z, atol=1e-9)


def test_gt_sampling_extends_openpcdet_box_mask(small_db, rng):
    frame = synthetic_frame(rng, objects=2)
    data = frame.to_dict()
    data["gt_boxes_mask"] = np.array([True, False])
    out = GroundTruthSampling(small_db)(data, rng)
    assert out["gt_boxes_mask"].shape == (len(out["gt_boxes"]),)
    assert out["gt_boxes_mask"][:2].tolist() == [True, False] and out["gt_boxes_mask"][2:].all()


def test_match_features_pads_and_cuts():
    pts = np.arange(8, dtype=np.float32).reshape(2, 4)
    assert match_features(pts, 3).shape == (2, 3)
    padded = match_features(pts, 6)
    np.testing.assert_array_equal(padded[:, :4], pts)
    assert (padded[:, 4:] == 0).all()


# --------------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------------
def test_stats_accumulate_over_a_pipeline(small_db, rng):
    frame = synthetic_frame(rng)
    pipeline = Compose([GroundTruthSampling(small_db), GlobalFlip(), GlobalRotation()])
    out = pipeline(frame, rng)
    stats = out.metadata["augment_stats"]
    assert list(stats["stages"]) == ["gt_sampling", "global_flip", "global_rotation"]
    first = stats["stages"]["gt_sampling"]
    assert first["points_in"] == len(frame) and first["points_out"] == len(out)
    assert all(s["ms"] >= 0 for s in stats["stages"].values())
    # Applying another transform later keeps accumulating, without touching the old frame.
    again = GlobalScaling()(out, rng)
    assert "global_scaling" in again.metadata["augment_stats"]["stages"]
    assert "global_scaling" not in out.metadata["augment_stats"]["stages"]


def test_stats_helper_counts():
    stats = Stats()
    stats.tried("drcpo", "Car", 3)
    stats.rejected("drcpo", "Car", "collision")
    stats.rejected("drcpo", "Car", "collision", 0)
    stats.added("drcpo", "Car", 2)
    stats.construction("Car", 4)
    with stats.stage("x", 10) as record:
        record["points_out"] = 7
    with stats.stage("x", 7):
        pass
    d = stats.to_dict()
    assert d["objects"]["drcpo"]["Car"] == {"tried": 3, "added": 2, "rejected": {"collision": 1}}
    assert d["construction_iterations"] == {"Car": [4]}
    assert d["stages"]["x"]["points_in"] == 10 and d["stages"]["x"]["points_out"] == 7
    copy = Stats(d)
    copy.added("drcpo", "Car")
    assert d["objects"]["drcpo"]["Car"]["added"] == 2  # a deep copy


def test_box_query_equals_points_in_boxes(rng):
    from conftest import random_boxes

    boxes = random_boxes(rng, 12, spread=4.0)
    points = rng.uniform(-6, 6, (4000, 4)).astype(np.float32)
    # Points exactly on faces and corners must follow the same closed-box rule.
    on_faces = box_corners(boxes[:3]).reshape(-1, 3)
    points = np.concatenate([points, np.column_stack([on_faces, np.zeros(len(on_faces))])])
    points = points.astype(np.float32)
    query = BoxQuery(points)
    for margin in (0.0, 0.2):
        reference = points_in_boxes(points, boxes, margin)
        for m, box in enumerate(boxes):
            np.testing.assert_array_equal(
                query.inside(box, margin), np.flatnonzero(reference[:, m])
            )
        np.testing.assert_array_equal(query.inside_any(boxes, margin), reference.any(axis=1))
        np.testing.assert_array_equal(query.counts(boxes, margin), reference.sum(axis=0))
    assert query.inside_any(np.zeros((0, 7))).sum() == 0
