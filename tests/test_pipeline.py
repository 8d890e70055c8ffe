import numpy as np
import pytest

from drcpo.database import GroundTruthDatabase, ObjectRecord
from drcpo.datasets.kitti_coordinates import Calibration
from drcpo.errors import ConfigError
from drcpo.frame import Frame
from drcpo.geometry import bev_overlap_area, box_corners, from_canonical, points_in_boxes
from drcpo.occlusion.view_windows import view_windows
from drcpo.pipeline import build_pipeline
from drcpo.placement import frame_ground
from drcpo.transforms import (
    DRCPO,
    Compose,
    GlobalFlip,
    GlobalRotation,
    GlobalScaling,
    GroundTruthSampling,
    Stats,
    transform_from_config,
)
from drcpo.transforms.drcpo_insertion import (
    Inserted,
    Insertion,
    _sparse_originals,
    scoped_e_hpr,
)
from drcpo.transforms.insertion import (
    BoxQuery,
    match_features,
    placed_object,
    placed_objects,
    road_plane_heights,
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


@pytest.mark.parametrize("dim", [3, 4, 6])
def test_placed_object_is_from_canonical_bit_for_bit(dim, rng):
    from drcpo.transforms.insertion import placed_object

    canonical = (rng.normal(size=(300, 4)) * [2.0, 1.0, 0.8, 1.0]).astype(np.float32)
    for heading in (0.0, 1.0, -2.9, np.pi):
        box = np.array([31.7, -12.3, -0.9, 4.0, 1.7, 1.5, heading])
        expected = match_features(from_canonical(canonical, box), dim)
        got = placed_object(canonical, box, dim)
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got, expected)


def naive_place(canonical, box, dim):
    """One row at a time in Python floats: x, y turned by the heading (numpy's cos and sin)
    and moved to the box, z moved, each cast to float32 once; the features copied, missing
    columns left 0."""
    cos, sin = float(np.cos(np.float64(box[6]))), float(np.sin(np.float64(box[6])))
    out = np.zeros((len(canonical), dim), np.float32)
    for i, row in enumerate(np.asarray(canonical, np.float32).tolist()):
        x, y, z = row[0], row[1], row[2]
        out[i, :3] = [(cos * x - sin * y) + box[0], (sin * x + cos * y) + box[1], z + box[2]]
        features = row[3:dim]
        out[i, 3 : 3 + len(features)] = features
    return out


def test_placing_and_scaling_kernels_follow_the_naive_rows():
    rng = np.random.default_rng(31)
    canonical = (rng.normal(size=(200, 4)) * [2.0, 1.0, 0.8, 1.0]).astype(np.float32)
    canonical[:3, :3] = [[0.0, 0.0, 0.0], [-0.0, 1e-45, -1e-30], [9.9e5, -9.9e5, 1.0]]
    boxes = np.array(
        [
            [31.7, -12.3, -0.9, 4.0, 1.7, 1.5, 0.0],
            [-1e5, 1e5, 2.0, 4.0, 1.7, 1.5, np.pi],
            [0.0, 0.0, 0.0, 1.0, 1.0, 1.0, -2.9],
            [1e-3, 5.0, -1.7, 1.0, 1.0, 1.0, 1e-12],
        ]
    )
    for box in boxes:
        for dim in (3, 4, 6):
            want = naive_place(canonical, box, dim)
            np.testing.assert_array_equal(placed_object(canonical, box, dim), want)
    assert placed_object(canonical[:0], boxes[0], 4).shape == (0, 4)
    # placed_objects: one database object after another into one array
    sizes = [0, 50, 150]
    db = GroundTruthDatabase.from_arrays(
        canonical, np.cumsum([0, *sizes]), ["Car"] * 3, boxes[:3].copy()
    )
    rows, at = np.array([2, 0, 1, 2]), boxes[[0, 1, 2, 3]]
    want = [naive_place(db.object_points(r), b, 5) for r, b in zip(rows, at, strict=True)]
    np.testing.assert_array_equal(placed_objects(db, rows, at, 5), np.concatenate(want))
    # GlobalScaling: x, y, z times the factor in float64, stored as float32; features kept
    points = np.concatenate([canonical, [[-1e6, 1e-45, -0.0, 7.0]]]).astype(np.float32)
    for scale in (0.95, 1.0, 1.05, 1 / 3):
        want = points.copy()
        want[:, :3] = (points[:, :3].astype(np.float64) * scale).astype(np.float32)
        out = GlobalScaling((scale, scale))(Frame(points.copy()), rng)
        np.testing.assert_array_equal(out.points, want)


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
        # owners: the last box holding each point (boxes overlap here), -1 for none
        last = np.where(
            reference.any(axis=1), len(boxes) - 1 - np.argmax(reference[:, ::-1], axis=1), -1
        )
        np.testing.assert_array_equal(query.owners(boxes, margin), last)
    assert query.inside_any(np.zeros((0, 7))).sum() == 0
    assert (query.owners(np.zeros((0, 7))) == -1).all()
    # own_counts: each point counted in its own box only, where asked
    owner = rng.integers(-1, len(boxes), len(points))
    where = rng.random(len(points)) < 0.7
    reference = points_in_boxes(points, boxes)
    expected = [int((reference[:, m] & (owner == m) & where).sum()) for m in range(len(boxes))]
    np.testing.assert_array_equal(query.own_counts(owner, boxes, where), expected)


# --------------------------------------------------------------------------------------------
# DR.CPO
# --------------------------------------------------------------------------------------------
MIN_POINTS = 5


@pytest.fixture(scope="module")
def synthetic_world():
    """A synthetic database of object surfaces, its index, and two ray-cast frames (camera FOV)."""
    from drcpo.datasets.kitti_coordinates import fov_mask
    from drcpo.datasets.kitti_writer import reference_calibration
    from drcpo.index import IndexConfig
    from drcpo.index_build import build_index
    from drcpo.synth import frame_rng, synthesize_frame

    db = synthetic_database(
        np.random.default_rng(11), {"Car": 120, "Pedestrian": 50, "Cyclist": 30}, 3, 400
    )
    index = build_index(db, IndexConfig(k=20))
    calib = reference_calibration()
    frames = []
    for i in range(2):
        made = synthesize_frame(frame_rng(3, i), calib=calib)
        points = np.asarray(made.sweep.points, dtype=np.float32)
        keep = fov_mask(points, calib)
        metadata = {"frame_id": f"synth{i}", "calib": calib, "fov_only": True}
        frames.append(Frame(points[keep], made.boxes, made.names, metadata))
    return db, index, frames


_KITTI_CACHE: dict = {}


@pytest.fixture
def kitti_world(kitti_sample, tmp_path_factory):
    """The database built from the real KITTI sample, its index, and its frames (camera FOV)."""
    if not _KITTI_CACHE:
        from drcpo.database.build import build_database
        from drcpo.datasets.kitti import KittiDataset
        from drcpo.datasets.kitti_coordinates import fov_mask
        from drcpo.index import IndexConfig
        from drcpo.index_build import build_index

        out = tmp_path_factory.mktemp("kitti") / "db"
        db = build_database(kitti_sample, "train", out)
        index = build_index(db, IndexConfig(k=20))
        index.save(out)
        dataset = KittiDataset(kitti_sample, "train")
        frames = []
        for frame_id in dataset.frame_ids:
            frame = dataset.frame(frame_id)
            keep = fov_mask(frame.points, frame.metadata["calib"], dataset.image_shape(frame_id))
            metadata = {**frame.metadata, "fov_only": True}
            frames.append(frame.replace(points=frame.points[keep], metadata=metadata))
        _KITTI_CACHE.update(db=db, index=index, frames=frames, path=out)
    return _KITTI_CACHE["db"], _KITTI_CACHE["index"], _KITTI_CACHE["frames"]


def row_set(points):
    return {row.tobytes() for row in np.ascontiguousarray(points)}


def check_drcpo_frame(transform: DRCPO, before: Frame, out: Frame) -> dict:
    """Assert the issue's invariants on one DR.CPO output; return a few counts."""
    config = transform.config
    stats = out.metadata["augment_stats"]
    added = sum(c["added"] for c in stats["objects"].get("drcpo", {}).values())
    dropped = sum(stats["labels_dropped"].values())
    kept_original = len(before.boxes) - dropped
    assert len(out.boxes) == kept_original + added == len(out.names)
    original, inserted = out.boxes[:kept_original], out.boxes[kept_original:]
    # Original boxes kept are unchanged, in order.
    before_rows = {row.tobytes(): i for i, row in enumerate(before.boxes)}
    kept_index = np.array([before_rows[row.tobytes()] for row in original], dtype=int)
    np.testing.assert_array_equal(out.names[:kept_original], before.names[kept_index])
    # No inserted box overlaps any other box in BEV.
    if added:
        overlap = bev_overlap_area(inserted, out.boxes)
        overlap[np.arange(added), kept_original + np.arange(added)] = 0.0
        assert overlap.max() == 0.0
    # Every box kept has at least 5 points, unless it already had fewer.
    counts_after = BoxQuery(out.points).counts(out.boxes)
    counts_before = BoxQuery(before.points).counts(before.boxes)
    assert (counts_after[kept_original:] >= MIN_POINTS).all()
    sparse_before = counts_before[kept_index] < MIN_POINTS
    assert ((counts_after[:kept_original] >= MIN_POINTS) | sparse_before).all()
    # Inserted boxes stand on the ground and hold few non-ground points of the frame.
    ground = frame_ground(before)
    if added:
        bottom = inserted[:, 2] - inserted[:, 5] / 2.0
        assert np.abs(bottom - ground.height_at(inserted[:, :2])).max() <= 0.3
    query = BoxQuery(before.points)
    tolerance = config.placement.ground_tolerance
    for box in inserted:
        members = before.points[query.inside(box)]
        non_ground = int((~ground.is_ground(members, tolerance)).sum()) if len(members) else 0
        assert non_ground <= config.placement.max_non_ground_points
    # Points: every output point is an input point, bit for bit, or lies in an inserted box
    # (its label holds every point the object brings).
    new_rows = row_set(out.points) - row_set(before.points)
    in_inserted = BoxQuery(out.points).inside_any(inserted)
    assert {row.tobytes() for row in out.points[in_inserted]} >= new_rows
    # Input points that are gone: in an inserted object's room (see DRCPO.room) or hidden
    # behind an inserted object kept (in the view window of its box,
    # beyond the box's nearest point).
    kept_rows = row_set(out.points)
    gone = np.array([row.tobytes() not in kept_rows for row in before.points], dtype=bool)
    if gone.any():
        cleared = BoxQuery(before.points).inside_any(inserted, margin=transform.room)
        _, viewpoint = transform.e_hpr_setting()
        grown = inserted.copy()
        grown[:, 3:6] += 0.2
        core = view_windows(before.points, grown, viewpoint, behind=True)
        assert (cleared | core)[gone].all()
    return {"added": added, "dropped": dropped, "gone": int(gone.sum())}


def test_drcpo_invariants_on_synthetic_world(synthetic_world):
    db, index, frames = synthetic_world
    transform = DRCPO(db, index)
    totals = {"added": 0, "gone": 0}
    for i, frame in enumerate(frames):
        out = transform(frame, np.random.default_rng(i))
        result = check_drcpo_frame(transform, frame, out)
        totals = {k: totals[k] + result[k] for k in totals}
        iterations = out.metadata["augment_stats"]["construction_iterations"]
        assert all(0 <= n <= 20 for values in iterations.values() for n in values)
    assert totals["added"] > 0


def test_drcpo_invariants_on_kitti_sample(kitti_world):
    db, index, frames = kitti_world
    transform = DRCPO(db, index)
    tried = 0
    for i, frame in enumerate(frames):
        out = transform(frame, np.random.default_rng(100 + i))
        check_drcpo_frame(transform, frame, out)
        tried += sum(c["tried"] for c in out.metadata["augment_stats"]["objects"]["drcpo"].values())
    assert tried > 0


def test_full_pipeline_on_kitti_sample(kitti_world):
    db, index, frames = kitti_world
    pipeline = build_pipeline("default", db, index)
    assert [type(t).__name__ for t in pipeline.transforms] == [
        "GroundTruthSampling",
        "DRCPO",
        "GlobalFlip",
        "GlobalRotation",
        "GlobalScaling",
    ]
    for i, frame in enumerate(frames[:3]):
        out = pipeline(frame.to_dict(), np.random.default_rng(i))
        assert isinstance(out, dict) and out["frame_id"] == frame.frame_id
        boxes = out["gt_boxes"]
        new = boxes[len(frame.boxes) :]
        overlap = bev_overlap_area(new, boxes)
        overlap[np.arange(len(new)), len(frame.boxes) + np.arange(len(new))] = 0.0
        assert overlap.max(initial=0.0) == 0.0
        assert next(iter(out["augment_stats"]["stages"])) == "gt_sampling"


def test_untouched_points_with_nothing_inserted(synthetic_world):
    db, index, frames = synthetic_world
    frame = frames[0]
    transform = DRCPO(db, index, {"sample": {}})
    out = transform(frame, np.random.default_rng(0))
    np.testing.assert_array_equal(out.points, frame.points)
    np.testing.assert_array_equal(out.boxes, frame.boxes)


def test_density_adjustment_fewer_points_farther_away(synthetic_world):
    """The same constructed object placed 5 to 70 m away keeps fewer points after s-HPR."""
    from scipy.stats import spearmanr

    db, index, _ = synthetic_world
    distances = np.linspace(5.0, 70.0, 14)
    counts = []
    for distance in distances:
        transform = DRCPO(
            db,
            index,
            {
                "sample": {"Car": 1},
                "placement": {"x_range": [distance - 3, distance + 3], "y_range": [-3.0, 3.0]},
                "external_occlusion": {"enabled": False},
                "self_occlusion": {"min_points": 0},
                "min_points_after": 0,
            },
        )
        # Same seed: same source object, heading, position in the area and construction.
        out = transform(Frame(np.zeros((0, 4), np.float32)), np.random.default_rng(42))
        stage = out.metadata["augment_stats"]["stages"]["drcpo.self_occlusion"]
        counts.append(stage["points_out"])
        assert (
            stage["points_in"]
            == out.metadata["augment_stats"]["stages"]["drcpo.construction"]["points_out"]
        )
    rho = spearmanr(distances, counts).statistic
    assert rho <= -0.8, (counts, rho)
    assert counts[0] > counts[-1]


def _run_seed(seed):
    transform, frame = _FORK_STATE["transform"], _FORK_STATE["frame"]
    out = transform(frame, np.random.default_rng(seed))
    return out.points, out.boxes, out.names


_FORK_STATE: dict = {}


def test_determinism_across_runs_and_a_forked_worker(synthetic_world):
    import multiprocessing

    db, index, frames = synthetic_world
    pipeline = Compose([GroundTruthSampling(db), DRCPO(db, index), GlobalFlip(), GlobalRotation()])
    _FORK_STATE.update(transform=pipeline, frame=frames[1])
    first = _run_seed(9)
    with multiprocessing.get_context("fork").Pool(1) as pool:
        in_worker = pool.apply(_run_seed, (9,))
    second = _run_seed(9)
    for a, b, c in zip(first, in_worker, second, strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)
    other = _run_seed(10)
    assert not np.array_equal(other[1], first[1])


def test_drcpo_dict_in_dict_out_and_features(synthetic_world):
    db, index, frames = synthetic_world
    frame = frames[0]
    wide = np.column_stack([frame.points, np.full((len(frame), 2), 7.0, np.float32)])
    data = {**frame.replace(points=wide).to_dict(), "extra": "kept"}
    out = DRCPO(db, index)(data, np.random.default_rng(1))
    assert isinstance(out, dict) and out["extra"] == "kept"
    assert out["points"].shape[1] == 6 and out["points"].dtype == np.float32
    inserted = ~np.isin(out["points"][:, 4], [7.0])
    assert inserted.any()
    assert (out["points"][inserted, 4:] == 0).all()  # database points carry no such feature


def test_drcpo_on_an_empty_frame(synthetic_world):
    db, index, _ = synthetic_world
    out = DRCPO(db, index)(Frame(np.zeros((0, 4), np.float32)), np.random.default_rng(0))
    assert len(out.boxes) > 0
    assert (BoxQuery(out.points).counts(out.boxes) >= MIN_POINTS).all()


def _reasons(out):
    found = {}
    for entry in out.metadata["augment_stats"]["objects"]["drcpo"].values():
        for reason, count in entry["rejected"].items():
            found[reason] = found.get(reason, 0) + count
    return found


def test_every_rejection_reason(synthetic_world):
    db, index, frames = synthetic_world
    empty = Frame(np.zeros((0, 4), np.float32))
    rng = np.random.default_rng
    tiny_area = DRCPO(db, index, {"placement": {"x_range": [0, 0.4], "y_range": [0, 0.4]}})
    assert set(_reasons(tiny_area(empty, rng(0)))) == {"out_of_range"}
    blocked = Frame(np.zeros((0, 4), np.float32), [[35.0, 0.0, -1.0, 80.0, 90.0, 2.0, 0.0]], ["X"])
    assert set(_reasons(DRCPO(db, index)(blocked, rng(0)))) == {"collision"}
    forest = np.random.default_rng(1).uniform([0, -40, -1.5], [70.4, 40, 2.0], (200_000, 3))
    forest = Frame(np.column_stack([forest, np.zeros(len(forest))]).astype(np.float32))
    reasons = _reasons(DRCPO(db, index)(forest, rng(0)))
    assert reasons.get("obstacle", 0) >= 20, reasons
    u, v = np.meshgrid(np.arange(-3.2, 3.2, 0.03), np.arange(-2.5, 1.0, 0.06), indexing="ij")
    wall = np.column_stack([np.full(u.size, 20.0), u.ravel(), v.ravel(), np.zeros(u.size)])
    # flat ground 2.5 m down, in front of the wall and behind it: boxes stand on it, hidden
    gx, gy = np.meshgrid(np.arange(2.0, 45.0, 0.5), np.arange(-3.0, 3.0, 0.5), indexing="ij")
    floor = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, -2.5), np.zeros(gx.size)])
    wall = np.concatenate([wall, floor])
    behind_wall = DRCPO(
        db,
        index,
        {
            "sample": {"Car": 1},
            "placement": {"x_range": [30, 40], "y_range": [-2.5, 2.5]},
        },
    )
    for seed in range(3):
        out = behind_wall(Frame(wall.astype(np.float32)), rng(seed))
        assert _reasons(out) == {"occluded": 1}
    sparse = DRCPO(db, index, {"self_occlusion": {"min_points": 100_000}})
    assert set(_reasons(sparse(empty, rng(0)))) == {"self_occlusion"}
    strict = DRCPO(db, index, {"min_points_after": 100_000})
    out = strict(frames[0], rng(0))
    assert "external_occlusion" in _reasons(out)
    assert len(out.boxes) <= len(frames[0].boxes)


def test_nothing_inserted_changes_nothing(synthetic_world):
    db, index, _ = synthetic_world
    rng = np.random.default_rng(5)
    wall = np.column_stack(
        [np.full(40_000, 10.0), rng.uniform(-8, 8, 40_000), rng.uniform(-1.7, 2.5, 40_000)]
    )
    ground = np.column_stack(
        [rng.uniform(2, 9.5, 5000), rng.uniform(-8, 8, 5000), np.full(5000, -1.73)]
    )
    car = np.array([20.0, 0.0, -0.95, *SIZES["Car"], 0.0])
    tiny = np.array([20.0, 5.0, -0.95, *SIZES["Pedestrian"], 0.0])
    car_points = from_canonical(surface_points(rng, SIZES["Car"], 200)[:, :3], car)
    tiny_points = from_canonical(surface_points(rng, SIZES["Pedestrian"], 3)[:, :3], tiny)
    xyz = np.concatenate([wall, ground, car_points, tiny_points])
    frame = Frame(
        np.column_stack([xyz, np.zeros(len(xyz))]).astype(np.float32),
        np.stack([car, tiny]),
        np.array(["Car", "Pedestrian"]),
    )
    transform = DRCPO(db, index, {"sample": {}})
    out = transform(frame, np.random.default_rng(0))
    # a car hidden behind a wall keeps its points and its label: e-HPR decides only what
    # inserted objects hide, and nothing was inserted
    assert out.metadata["augment_stats"]["labels_dropped"] == {}
    np.testing.assert_array_equal(out.points, frame.points)
    assert out.names.tolist() == ["Car", "Pedestrian"]
    # An original box that e-HPR or an inserted object's room leaves with fewer than
    # min_points_after points loses its label, unless it had fewer before (the tiny one's 3).
    points = np.concatenate([car[:3] + rng.uniform(-0.5, 0.5, (6, 3)), tiny[:3] + [[0, 0, 0]] * 3])
    sparse = Frame(
        np.column_stack([points, np.zeros(9)]).astype(np.float32), frame.boxes, frame.names
    )
    removed = np.zeros(9, dtype=bool)
    removed[[0, 1]] = True  # the car keeps 4 of its 6
    removed[6] = True  # the tiny one keeps 2 of its 3
    minimum = transform.config.min_points_after
    assert _sparse_originals(sparse, removed, minimum).tolist() == [True, False]
    removed[1] = False  # the car keeps 5
    assert _sparse_originals(sparse, removed, minimum).tolist() == [False, False]


def test_drcpo_config_round_trip_and_checks(synthetic_world):
    db, index, _ = synthetic_world
    transform = DRCPO(db, index, {"construction": {"margin": 0.0}, "sample": {"Car": 3}})
    config = transform.to_config()
    assert config["type"] == "DRCPO" and config["construction"]["margin"] == 0.0
    rebuilt = transform_from_config(config, database=db, index=index)
    assert rebuilt == transform and rebuilt.to_config() == config
    assert "sample={'Car': 3" in repr(transform)
    with pytest.raises(ConfigError, match="index"):
        transform_from_config(config, database=db)
    with pytest.raises(ConfigError, match=r"grids\.Car"):
        DRCPO(db, index, {"construction": {"grids": {"Car": [5, 2, 3]}}})
    with pytest.raises(ConfigError, match="mirror"):
        DRCPO(db, index, {"construction": {"mirror": ["Car"]}})
    with pytest.raises(ConfigError, match=r"drcpo\.construction\.coverage"):
        DRCPO(db, index, {"construction": {"coverage": 2}})


def test_build_pipeline_kinds(synthetic_world):
    db, index, _ = synthetic_world
    cda = build_pipeline({"pipeline": "cda"}, db, index)
    assert [type(t).__name__ for t in cda.transforms] == [
        "GroundTruthSampling",
        "GlobalFlip",
        "GlobalRotation",
        "GlobalScaling",
    ]
    drcpo = build_pipeline("second", db, index)
    assert drcpo[1].config.external_occlusion.viewpoint_z == 2.0  # SECOND's in the paper
    off = build_pipeline(
        {"gt_sampling": {"enabled": False}, "global_augmentation": {"enabled": False}}, db, index
    )
    assert [type(t).__name__ for t in off.transforms] == ["DRCPO"]
    with pytest.raises(ConfigError, match="database"):
        build_pipeline(None)
    with pytest.raises(ConfigError, match="pipeline"):
        build_pipeline(None, db, index, kind="magic")


# --------------------------------------------------------------------------------------------
# Offline generation (drcpo augment) and the benchmark's quick mode
# --------------------------------------------------------------------------------------------
def test_augment_cli_writes_kitti_layout_and_stats(kitti_world, kitti_sample, tmp_path):
    import json

    from typer.testing import CliRunner

    from drcpo.cli import app
    from drcpo.datasets.kitti import KittiDataset

    db_path = _KITTI_CACHE["path"]
    out = tmp_path / "augmented"
    args = ["augment", "--kitti", str(kitti_sample), "--db", str(db_path), "--out", str(out)]
    result = CliRunner().invoke(app, [*args, "--frames", "3", "--seed", "4"])
    assert result.exit_code == 0, result.output
    lines = (out / "stats.jsonl").read_text().splitlines()
    assert len(lines) == 3
    records = [json.loads(line) for line in lines]
    assert records[0]["frame_id"] == "000000" and "drcpo.external_occlusion" in records[0]["stages"]
    written = KittiDataset(out, "train")
    assert written.frame_ids == ["000000", "000001", "000002"]
    for record in records:
        frame = written.frame(record["frame_id"])
        assert len(frame) == record["points"]
        names, counts = np.unique(frame.names, return_counts=True)
        assert dict(zip(names.tolist(), counts.tolist(), strict=True)) == record["boxes"]
    # Same seed, same output; an existing output is refused, nothing half-written is left.
    again = CliRunner().invoke(
        app, [*args[:-1], str(tmp_path / "again"), "--frames", "3", "--seed", "4"]
    )
    assert again.exit_code == 0
    for name in ("000000", "000002"):
        first = (out / "training" / "velodyne" / f"{name}.bin").read_bytes()
        assert first == (tmp_path / "again" / "training" / "velodyne" / f"{name}.bin").read_bytes()
    refused = CliRunner().invoke(app, [*args, "--frames", "1"])
    assert refused.exit_code == 1 and "exists" in refused.output
    bad = CliRunner().invoke(app, [*args[:-1], str(tmp_path / "x"), "--config", "nope.yaml"])
    assert bad.exit_code == 1 and "nope.yaml" in bad.output
    assert not (tmp_path / "x").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_augment_kitti_leaves_no_output_when_a_frame_fails(kitti_world, kitti_sample, tmp_path):
    from drcpo.datasets.export import augment_kitti
    from drcpo.errors import DataError
    from drcpo.staging import staging_path

    class Failing(GlobalFlip):
        def apply(self, frame, rng, stats):
            if frame.frame_id == "000001":
                raise DataError("frame 000001: broken")
            return super().apply(frame, rng, stats)

    with pytest.raises(DataError, match="000001"):
        augment_kitti(kitti_sample, "train", Failing(), tmp_path / "out")
    # No output; only the staging directory a rerun resumes from (tests/test_export.py).
    assert list(tmp_path.iterdir()) == [staging_path(tmp_path / "out")]
    assert (staging_path(tmp_path / "out") / "frames" / "00000000.json").is_file()


def test_bench_augment_quick_mode(tmp_path, capsys):
    import importlib.util
    import json
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_augment.py"
    spec = importlib.util.spec_from_file_location("bench_augment", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    args = ["--quick", "--frames", "1", "--repeats", "1", "--work", str(tmp_path)]
    bench.main([*args, "--processes", "1"])
    last = capsys.readouterr().out.strip().splitlines()[-1]
    result = json.loads(last)
    assert {"cda_ms", "drcpo_ms", "ratio", "stages_ms"} <= set(result)
    assert result["ratio"] == pytest.approx(result["drcpo_ms"] / result["cda_ms"])
    assert "drcpo.external_occlusion" in result["stages_ms"]
    # the throughput run (forked processes) reports frames per second of both pipelines
    assert result["processes"] == 1
    assert result["cda_frames_per_s"] > 0 and result["drcpo_frames_per_s"] > 0
    with pytest.raises(SystemExit):
        bench.main([*args, "--processes", "-1"])

    def failing(frame, rng):
        raise RuntimeError("a transform that fails")

    with pytest.raises(SystemExit, match="failed"):  # at once, not after the barrier's timeout
        bench.frames_per_second(failing, [Frame(np.zeros((1, 4), np.float32))], 1, 2)


def test_view_windows_cover_the_boxes_and_nothing_opposite(rng):
    boxes = np.array(
        [[10.0, 3.0, -0.8, 4.0, 1.8, 1.5, 0.4], [-12.0, -0.5, -0.8, 4.0, 1.8, 1.5, 2.0]]
    )
    viewpoint = np.array([0.0, 0.0, 0.5])
    inside = np.concatenate(
        [from_canonical(rng.uniform(-0.5, 0.5, (300, 3)) * box[3:6], box) for box in boxes]
    )
    # Twice as far along the same rays: behind the boxes, in their windows.
    behind = viewpoint + 2.0 * (inside - viewpoint)
    nearer = viewpoint + 0.3 * (inside - viewpoint)
    across = inside * [1.0, -1.0, 1.0] + [0.0, 0.0, 30.0]  # mirrored and high above
    points = np.concatenate([inside, behind, nearer, across]).astype(np.float32)
    kind = np.repeat(np.arange(4), len(inside))
    hit = view_windows(points, boxes, viewpoint)
    assert hit[kind <= 2].all() and not hit[kind == 3].any()
    hit_behind = view_windows(points, boxes, viewpoint, behind=True)
    assert hit_behind[kind == 1].all() and not hit_behind[kind >= 2].any()
    # The second box's window crosses the azimuth seam at +-pi.
    assert hit[len(inside) // 2 : len(inside)].all()


def e_hpr_of(transform, points, owner, insertions):
    """DR.CPO's e-HPR step on points inserted into a frame of which nothing was cleared."""
    inserted = Inserted(points, owner, np.full(int((owner < 0).sum()), -1))
    setting, minimum = transform.e_hpr_setting(), transform.config.min_points_after
    return scoped_e_hpr(inserted, insertions, setting, minimum)


def test_inserted_scope_removes_what_inserted_objects_hide(synthetic_world, rng):
    db, index, _ = synthetic_world
    transform = DRCPO(db, index)
    # A wall 20 m ahead, a second layer right behind part of it (hidden before anything is
    # inserted), and a dense box inserted 10 m ahead in front of the wall's middle.
    y, z = np.meshgrid(np.linspace(-4, 4, 81), np.linspace(-1.5, 1.5, 31))
    wall = np.column_stack([np.full(y.size, 20.0), y.ravel(), z.ravel()])
    layer = wall[wall[:, 1] > 2.5] * 1.05
    box = np.array([10.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0])
    cube = rng.uniform(-0.5, 0.5, (4000, 3)) + box[:3]
    points = np.concatenate([wall, layer, cube])
    points = np.column_stack([points, np.zeros(len(points))]).astype(np.float32)
    owner = np.repeat([-1, 0], [len(wall) + len(layer), len(cube)])
    cube_object = Insertion(0, "Car", box, box, points[-4000:])
    keep, dropped = e_hpr_of(transform, points, owner, [cube_object])
    assert not dropped.any()  # the cube stays, with its visible face
    shadow = (np.abs(wall[:, 1]) < 0.8) & (np.abs(wall[:, 2]) < 0.8)
    assert not keep[: len(wall)][shadow].any()  # the wall behind the box is hidden now
    assert keep[: len(wall)][(np.abs(wall[:, 1]) > 1.5)].all()
    assert keep[len(wall) : len(wall) + len(layer)].all()  # hidden before: HPR's call, kept


def test_points_hidden_only_by_a_dropped_object_stay(synthetic_world, rng):
    db, index, _ = synthetic_world
    transform = DRCPO(db, index)
    # A wall 15 m ahead; object A (3 points, too few to keep) right in front of wall point P;
    # object B, dense, 25 m ahead beside the wall's edge: P lies in B's view window but in
    # front of B, so only A (dropped) could hide it, and P must stay.
    y, z = np.meshgrid(np.linspace(-3.0, 2.5, 56), np.linspace(-1.0, 1.0, 21))
    wall = np.column_stack([np.full(y.size, 15.0), y.ravel(), z.ravel()])
    p = np.flatnonzero((np.abs(wall[:, 1] - 2.5) < 1e-9) & (np.abs(wall[:, 2]) < 1e-9))[0]
    a_points = wall[p] * np.array([[10.0 / 15.0], [10.01 / 15.0], [10.02 / 15.0]])
    box_a = np.array([10.0, wall[p, 1] * 10.0 / 15.0, 0.0, 0.5, 0.5, 0.5, 0.0])
    box_b = np.array([25.0, 5.0, 0.0, 2.0, 4.0, 2.0, 0.0])
    cube = rng.uniform(-0.5, 0.5, (3000, 3)) * box_b[3:6] + box_b[:3]
    xyz = np.concatenate([wall, a_points, cube])
    points = np.column_stack([xyz, np.zeros(len(xyz))]).astype(np.float32)
    owner = np.repeat([-1, 0, 1], [len(wall), len(a_points), len(cube)])
    insertions = [
        Insertion(0, "Pedestrian", box_a, box_a, points[len(wall) : len(wall) + 3]),
        Insertion(1, "Car", box_b, box_b, points[len(wall) + 3 :]),
    ]
    keep, dropped = e_hpr_of(transform, points, owner, insertions)
    assert dropped.tolist() == [True, False]
    assert keep[p]  # hidden by A alone: A is gone, so P stays
    assert keep[: len(wall)].all()  # nothing of the wall lies behind B


@pytest.mark.parametrize("config", [{}, {"self_occlusion": {"min_points": 40}}])
def test_drcpo_frame_grid_paths_give_the_plain_answer(kitti_world, config, monkeypatch):
    # The frame's grid, prepared on a second thread while objects are built (with s-HPR
    # dropping some placed objects in the second case: fewer points cleared than prepared
    # for), must give the plain e-HPR passes' frame, point for point. (Without the grid,
    # placement's occluded test would take the z-buffer: it is off in both runs.)
    db, index, frames = kitti_world
    transform = DRCPO(db, index, {**config, "placement": {"occluded_fraction": None}})
    grid_path = [transform(frame, np.random.default_rng(7 + i)) for i, frame in enumerate(frames)]
    monkeypatch.setattr(DRCPO, "_frame_grid", lambda *args: None)
    for i, (frame, out) in enumerate(zip(frames, grid_path, strict=True)):
        plain = transform(frame, np.random.default_rng(7 + i))
        np.testing.assert_array_equal(out.points, plain.points)
        np.testing.assert_array_equal(out.boxes, plain.boxes)
        np.testing.assert_array_equal(out.names, plain.names)


def test_box_source_says_which_stage_added_each_box(synthetic_world):
    """metadata["box_source"]: "" for the frame's boxes, then "gt_sampling", then "drcpo"."""
    db, index, frames = synthetic_world
    pipeline = build_pipeline("default", db, index=index)
    out = pipeline(frames[0], np.random.default_rng(3))
    sources = out.metadata["box_source"]
    assert len(sources) == len(out.boxes)
    counts = {s: int(np.count_nonzero(sources == s)) for s in ("", "gt_sampling", "drcpo")}
    assert counts["gt_sampling"] > 0 and counts["drcpo"] > 0
    assert sum(counts.values()) == len(sources)
    stats = out.metadata["augment_stats"]["objects"]
    assert counts["drcpo"] == sum(c["added"] for c in stats["drcpo"].values())
    # each stage appends its boxes after the earlier ones
    assert list(sources) == sorted(sources, key=["", "gt_sampling", "drcpo"].index)
