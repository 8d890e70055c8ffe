import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drcpo.collisions import bev_collisions
from drcpo.errors import ConfigError, DataError
from drcpo.frame import Frame
from drcpo.geometry import bev_corners, bev_overlap_area, box_members, points_in_boxes
from drcpo.ground import GroundModel
from drcpo.occlusion.view_windows import surface_samples
from drcpo.placement import (
    REASONS,
    PlacementConfig,
    _non_ground_counts,
    place_objects,
    sample_poses,
)
from drcpo.poses import in_fov

AREA = PlacementConfig()
SIZES = np.array([[3.9, 1.6, 1.5], [0.8, 0.6, 1.7], [1.8, 0.6, 1.7]])


def uneven(xy):
    return (
        -1.7
        + 0.03 * xy[:, 0]
        - 0.02 * xy[:, 1]
        + 0.25 * np.sin(xy[:, 0] / 5.0) * np.cos(xy[:, 1] / 6.0)
    )


def ground_cloud(rng, n=30000, extent=((-5, 75), (-45, 45)), surface=uneven):
    xy = np.column_stack([rng.uniform(*extent[0], n), rng.uniform(*extent[1], n)])
    return np.column_stack([xy, surface(xy) + rng.normal(0, 0.02, n), rng.uniform(0, 1, n)])


def wall(rng, x0, x1, y0, y1, height=3.0, n=4000, surface=uneven):
    """A block of non-ground points (a building, bushes) standing on the ground."""
    xy = np.column_stack([rng.uniform(x0, x1, n), rng.uniform(y0, y1, n)])
    z = surface(xy) + rng.uniform(0.1, height, n)
    return np.column_stack([xy, z, rng.uniform(0, 1, n)])


def scene(rng, boxes=None, extra=()):
    points = np.concatenate([ground_cloud(rng), *extra]).astype(np.float32)
    boxes = np.zeros((0, 7)) if boxes is None else np.asarray(boxes, dtype=np.float64)
    return Frame(points, boxes, np.array(["Car"] * len(boxes)))


def existing_boxes():
    xy = np.array([[10, 0], [20, 5], [30, -8], [15, -15], [45, 12], [60, -30], [8, 25], [50, 0]])
    out = np.column_stack([xy, uneven(xy.astype(float)) + 0.75, np.tile([3.9, 1.6, 1.5], (8, 1))])
    return np.column_stack([out, np.linspace(-3, 3, 8)])


def sizes(count):
    return np.tile(SIZES, (count // 3 + 1, 1))[:count]


def nonground_counts(frame, ground, boxes, tolerance=0.2):
    above = frame.points[~ground.is_ground(frame.points, tolerance)]
    return points_in_boxes(above, boxes).sum(axis=0)


def test_no_two_boxes_overlap_and_footprints_stay_in_the_area(rng):
    frame = scene(rng, existing_boxes())
    result = place_objects(frame, sizes(60), None, rng)
    assert len(result.accepted) >= 20
    everything = np.concatenate([frame.boxes, result.boxes])
    overlap = bev_overlap_area(everything)
    np.fill_diagonal(overlap, 0)
    assert (overlap == 0).all()
    corners = bev_corners(result.boxes)
    assert (corners[..., 0] >= 0 - 1e-9).all() and (corners[..., 0] <= 70.4 + 1e-9).all()
    assert (np.abs(corners[..., 1]) <= 40 + 1e-9).all()
    np.testing.assert_array_equal(result.boxes[:, 3:6], sizes(60)[result.accepted])
    assert ((result.boxes[:, 6] >= -np.pi) & (result.boxes[:, 6] < np.pi)).all()


def test_clearance_keeps_room_around_each_placed_footprint(rng):
    frame = scene(rng, existing_boxes())

    def rooms_overlap(result):
        room = result.boxes.copy()
        room[:, 3:5] += 0.6
        overlap = bev_overlap_area(room, np.concatenate([room, frame.boxes]))
        overlap[:, : len(room)][np.diag_indices(len(room))] = 0
        return (overlap > 0).any()

    crowded = {"x_range": (0, 30), "y_range": (-15, 15)}
    result = place_objects(frame, sizes(60), None, rng, PlacementConfig(clearance=0.3, **crowded))
    assert len(result.accepted) >= 10
    np.testing.assert_array_equal(result.boxes[:, 3:6], sizes(60)[result.accepted])
    assert not rooms_overlap(result)
    room = result.boxes.copy()
    room[:, 3:5] += 0.6
    corners = bev_corners(room)
    assert (corners[..., 0] >= -1e-9).all() and (corners[..., 0] <= 30 + 1e-9).all()
    # Without clearance, boxes come closer than that to one another.
    tight = place_objects(
        frame, sizes(60), None, np.random.default_rng(0), PlacementConfig(**crowded)
    )
    assert rooms_overlap(tight)
    with pytest.raises(ConfigError, match="placement.clearance"):
        PlacementConfig(clearance=-0.1)


def test_surface_samples_lie_on_the_faces_seen_from_the_viewpoint():
    boxes = np.array([[10.0, 0.0, -1.0, 4.0, 2.0, 1.5, 0.0], [0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.4]])
    # Level with the first box's centre, the viewpoint sees its back face (x = 8) only; it
    # lies inside the second box, which shows it nothing.
    samples, offsets = surface_samples(boxes, np.array([0.0, 0.0, -1.0]))
    assert offsets.tolist() == [0, 20, 20]
    np.testing.assert_allclose(samples[:, 0], 8.0)
    assert np.ptp(samples[:, 1]) == pytest.approx(2.0)
    assert np.ptp(samples[:, 2]) == pytest.approx(1.5)
    assert len(np.unique(samples, axis=0)) == 20
    above, offsets = surface_samples(boxes[:1], np.zeros(3))  # above the top: back and top
    assert offsets.tolist() == [0, 40] and np.isclose(above[:, 2], -0.25).sum() == 20 + 5


def test_boxes_stand_on_sloped_uneven_ground(rng):
    frame = scene(rng)
    ground = GroundModel.from_points(frame.points)
    result = place_objects(frame, sizes(30), None, rng, None, ground)
    assert len(result.accepted) >= 20
    bottom = result.boxes[:, 2] - result.boxes[:, 5] / 2
    np.testing.assert_allclose(bottom, ground.height_at(result.boxes[:, :2]), atol=1e-9)
    assert np.abs(bottom - uneven(result.boxes[:, :2])).max() < 0.3
    # Built internally from the frame's own points when no model is given.
    again = place_objects(frame, sizes(30), None, np.random.default_rng(1))
    bottom = again.boxes[:, 2] - again.boxes[:, 5] / 2
    assert np.abs(bottom - uneven(again.boxes[:, :2])).max() < 0.3


def test_no_box_holds_more_than_the_allowed_nonground_points(rng):
    blocks = [wall(rng, 5, 35, -40, -5, n=20000), wall(rng, 40, 70, 10, 40, height=1.0, n=8000)]
    frame = scene(rng, extra=blocks)
    ground = GroundModel.from_points(frame.points)
    for limit in (0, 10):
        config = PlacementConfig(max_non_ground_points=limit)
        result = place_objects(frame, sizes(40), None, rng, config, ground)
        assert result.rejected["obstacle"] > 0
        assert len(result.accepted) > 0
        assert (nonground_counts(frame, ground, result.boxes) <= limit).all()


def test_obstacle_counts_match_brute_force(rng):
    frame = scene(rng, extra=[wall(rng, 10, 50, -20, 20, n=20000)])
    ground = GroundModel.from_points(frame.points)
    boxes = sample_poses(sizes(50), rng)
    boxes[:, 2] = ground.height_at(boxes[:, :2]) + boxes[:, 5] / 2
    counts = _non_ground_counts(frame.points, boxes, ground, AREA.ground_tolerance)
    expected = nonground_counts(frame, ground, boxes)
    np.testing.assert_array_equal(counts, expected)
    assert expected.max() > 10


def test_every_rejection_reason(rng):
    frame = scene(rng)
    too_big = place_objects(frame, [[120.0, 2.0, 2.0], [2.0, 150.0, 2.0]], None, rng)
    assert too_big.rejected == dict.fromkeys(REASONS, 0) | {"out_of_range": 2}
    assert too_big.reasons.tolist() == ["out_of_range", "out_of_range"]
    assert len(too_big.accepted) == 0 and too_big.boxes.shape == (0, 7)

    blocker = np.array([[35.2, 0.0, -1.0, 70.4, 80.0, 2.0, 0.0]])
    blocked = place_objects(scene(rng, blocker), sizes(5), None, rng)
    assert blocked.rejected["collision"] == 5 and len(blocked.accepted) == 0

    crowded = place_objects(frame, sizes(40), None, rng, PlacementConfig(x_range=(0, 12)))
    assert crowded.rejected["collision"] > 0
    assert set(crowded.reasons.tolist()) <= {"", "collision", "obstacle"}

    forest = scene(rng, extra=[wall(rng, -2, 22, -12, 12, height=2.0, n=40000)])
    small = PlacementConfig(x_range=(0, 20), y_range=(-10, 10))
    dense = place_objects(forest, sizes(6), None, rng, small)
    assert dense.rejected["obstacle"] == 6 and len(dense.accepted) == 0
    assert set(dense.rejected) == set(REASONS)

    placed = place_objects(frame, sizes(4), None, rng)
    hidden = placed.reject(np.ones(len(placed.accepted), bool), "occluded")
    assert hidden.reasons.tolist() == ["occluded"] * 4 and len(hidden.accepted) == 0
    with pytest.raises(ValueError, match="1 verdicts for 4 placed boxes"):
        placed.reject(np.ones(1, bool), "occluded")
    with pytest.raises(ValueError, match="unknown reason 'hidden'"):
        placed.reject(np.ones(4, bool), "hidden")


def test_a_caller_rejects_placed_boxes_without_touching_the_others(rng):
    # DR.CPO's "occluded" test: the result with some placed boxes rejected, the rest as they were.
    frame = scene(rng, existing_boxes())
    placed = place_objects(frame, sizes(20), None, np.random.default_rng(4))
    assert len(placed.accepted) >= 10 and set(placed.reasons) >= {""}
    mask = placed.boxes[:, 0] < 35.0
    out = placed.reject(mask, "occluded")
    np.testing.assert_array_equal(out.accepted, placed.accepted[~mask])
    np.testing.assert_array_equal(out.boxes, placed.boxes[~mask])
    # every reason whole (a reason never cut to the width of the ones before it)
    assert out.reasons[placed.accepted[mask]].tolist() == ["occluded"] * int(mask.sum())
    assert out.rejected["occluded"] == placed.rejected["occluded"] + mask.sum()
    assert (out.reasons[out.accepted] == "").all()
    assert len(out.accepted) + sum(out.rejected.values()) == 20
    assert placed.rejected["occluded"] == 0 and (placed.reasons[placed.accepted] == "").all()


def test_the_papers_ablations_place_objects_at_their_own_centre_and_turn_them_in_a_range(rng):
    count = 400
    source = np.column_stack(
        [rng.uniform(-10, 80, count), rng.uniform(-50, 50, count), np.full(count, -1.0),
         sizes(count), rng.uniform(-np.pi, np.pi, count)]
    )  # fmt: skip
    fixed = PlacementConfig(location="source", fov_only=True)
    boxes = sample_poses(sizes(count), rng, fixed, source=source)
    placed = np.isfinite(boxes[:, 0])
    np.testing.assert_array_equal(boxes[placed, :2], source[placed, :2])
    corners = bev_corners(boxes[placed])
    assert (corners[..., 0] >= 0.0).all() and (corners[..., 0] <= 70.4).all()
    assert (np.abs(corners[..., 1]) <= 40.0).all()
    assert (np.abs(np.arctan2(corners[..., 1], corners[..., 0])) <= fixed.fov_half_angle).all()
    # every row left out had a corner outside the area or the view
    left = sample_poses(sizes(count), rng, PlacementConfig(location="source"), source=source)
    outside = ~np.isfinite(left[:, 0])
    probe = left.copy()
    probe[:, :2] = source[:, :2]  # its own centre, the heading drawn
    far = bev_corners(probe[outside])
    assert ((far[..., 0] < 0) | (far[..., 0] > 70.4) | (np.abs(far[..., 1]) > 40)).any(1).all()
    for half_width in (np.pi / 4, np.pi / 2):
        turned = sample_poses(
            sizes(count), rng, PlacementConfig(heading_range=half_width), source=source
        )
        turn = np.angle(np.exp(1j * (turned[:, 6] - source[:, 6])))
        assert (np.abs(turn) <= half_width + 1e-9).all()
        assert np.abs(turn).max() > 0.9 * half_width  # the whole range is drawn
        assert (turned[:, 6] >= -np.pi).all() and (turned[:, 6] < np.pi).all()
    frame = scene(rng)
    result = place_objects(frame, sizes(count), source, rng, fixed)
    np.testing.assert_array_equal(result.boxes[:, :2], source[result.accepted, :2])
    with pytest.raises(DataError, match="own poses needs their boxes"):
        place_objects(frame, sizes(3), None, rng, fixed)


def test_field_of_view_only(rng):
    config = PlacementConfig(fov_only=True)
    boxes = sample_poses(sizes(300), rng, config)
    corners = bev_corners(boxes)
    azimuth = np.abs(np.arctan2(corners[..., 1], corners[..., 0]))
    assert (azimuth <= config.fov_half_angle + 1e-9).all()
    assert np.isfinite(boxes).all()
    narrow = sample_poses(sizes(3), rng, PlacementConfig(fov_only=True, fov_half_angle=1e-4))
    assert np.isnan(narrow[:, 0]).all()
    frame = scene(rng)
    placed = place_objects(frame, sizes(30), None, rng, config)
    corners = bev_corners(placed.boxes)
    assert (np.abs(np.arctan2(corners[..., 1], corners[..., 0])) <= config.fov_half_angle).all()


def test_sample_poses_cover_the_area_uniformly(rng):
    boxes = sample_poses(np.tile([[1.0, 1.0, 1.0]], (4000, 1)), rng)
    assert np.abs(boxes[:, 0].mean() - 35.2) < 1.0 and np.abs(boxes[:, 1].mean()) < 1.2
    assert boxes[:, 0].min() < 3 and boxes[:, 0].max() > 67
    assert np.abs(np.histogram(boxes[:, 6], bins=4, range=(-np.pi, np.pi))[0] - 1000).max() < 120
    np.testing.assert_array_equal(boxes[:, 2], 0.5)


def test_same_seed_same_placement(rng):
    frame = scene(rng, existing_boxes())
    a = place_objects(frame, sizes(20), None, np.random.default_rng(9))
    b = place_objects(frame, sizes(20), None, np.random.default_rng(9))
    np.testing.assert_array_equal(a.boxes, b.boxes)
    np.testing.assert_array_equal(a.accepted, b.accepted)
    assert a.rejected == b.rejected


def test_dict_frames_empty_frames_and_empty_samples(rng):
    frame = scene(rng, existing_boxes())
    as_dict = place_objects(frame.to_dict(), sizes(10), None, np.random.default_rng(2))
    as_frame = place_objects(frame, sizes(10), None, np.random.default_rng(2))
    np.testing.assert_array_equal(as_dict.boxes, as_frame.boxes)
    empty = place_objects(Frame(np.zeros((0, 4), np.float32)), sizes(4), None, rng)
    assert len(empty.accepted) == 4
    np.testing.assert_allclose(empty.boxes[:, 2] - empty.boxes[:, 5] / 2, -1.73)
    nothing = place_objects(frame, np.zeros((0, 3)), None, rng)
    assert nothing.boxes.shape == (0, 7) and len(nothing.reasons) == 0


def test_bad_input_is_rejected(rng):
    frame = scene(rng)
    with pytest.raises(DataError, match=r"dims\[1\]"):
        place_objects(frame, [[1.0, 1.0, 1.0], [1.0, -1.0, 1.0]], None, rng)
    with pytest.raises(DataError, match="shape"):
        place_objects(frame, [1.0, 1.0, 1.0], None, rng)
    with pytest.raises(ConfigError, match="placement.x_range"):
        PlacementConfig(x_range=(5, 5))
    with pytest.raises(ConfigError, match="placement.location"):
        PlacementConfig(location="air")
    with pytest.raises(ConfigError, match="placement.fov_half_angle"):
        PlacementConfig(fov_half_angle=4.0)
    with pytest.raises(ConfigError, match="placement.max_non_ground_points"):
        PlacementConfig(max_non_ground_points=-1)


def test_real_kitti_frames(kitti_sample):
    from drcpo.datasets.kitti import KittiDataset

    rng = np.random.default_rng(0)
    gaps = []
    for frame in KittiDataset(kitti_sample, "train"):
        ground = GroundModel.from_points(frame.points)
        result = place_objects(frame, sizes(30), None, rng, PlacementConfig(), ground)
        assert len(result.accepted) > 0, frame.frame_id
        everything = np.concatenate([frame.boxes, result.boxes])
        overlap = bev_overlap_area(everything)
        np.fill_diagonal(overlap, 0)
        assert (overlap == 0).all(), frame.frame_id
        assert (nonground_counts(frame, ground, result.boxes) <= 10).all(), frame.frame_id
        bottom = result.boxes[:, 2] - result.boxes[:, 5] / 2
        np.testing.assert_allclose(bottom, ground.height_at(result.boxes[:, :2]), atol=1e-9)
        # Where the frame shows the ground under a placed box, the box stands on it: the lowest
        # tenth of the points in its (slightly grown) footprint, up to its top, lies at its bottom.
        columns = result.boxes.copy()
        columns[:, 5] += 10.0
        columns[:, 2] -= 5.0
        inside = points_in_boxes(frame.points, columns, margin=0.3)
        for j in np.flatnonzero(inside.sum(axis=0) >= 10):
            gaps.append(np.percentile(frame.points[inside[:, j], 2], 10) - bottom[j])
    gaps = np.abs(gaps)
    assert len(gaps) >= 12
    assert np.mean(gaps < 0.3) >= 0.75, np.round(gaps, 2)


# --------------------------------------------------------------------------------------------
# Kernels against their numpy references
# --------------------------------------------------------------------------------------------
finite = st.floats(-20, 20, allow_nan=False)
sizes_ = st.floats(0.1, 8, allow_nan=False)
heading = st.floats(-math.pi, math.pi, allow_nan=False)


def overlap_depth(a, b):
    """Smallest overlap (metres) of the two footprints' projections on their edge normals."""
    depth = np.inf
    for box in (a, b):
        for angle in (box[6], box[6] + np.pi / 2):
            axis = np.array([np.cos(angle), np.sin(angle)])
            pa, pb = bev_corners(a)[0] @ axis, bev_corners(b)[0] @ axis
            depth = min(depth, min(pa.max(), pb.max()) - max(pa.min(), pb.min()))
    return depth


@settings(max_examples=300, deadline=None)
@given(
    st.tuples(finite, finite, sizes_, sizes_, heading),
    st.tuples(finite, finite, sizes_, sizes_, heading),
)
def test_collisions_agree_with_the_overlap_area(a, b):
    box_a = np.array([a[0], a[1], 0.0, a[2], a[3], 1.0, a[4]])
    box_b = np.array([b[0], b[1], 0.0, b[2], b[3], 1.0, b[4]])
    collide = bev_collisions(box_a, box_b)[0, 0]
    area = bev_overlap_area(box_a, box_b)[0, 0]
    # else a tie either way: bev_overlap_area's clip gives a 6e-8 m^2 sliver for boxes 6e-8 m
    # apart (a=(6, 0, 6, 1, 0), b=(-5.96e-8, 0, 6, 1, 0)), below any placement clearance
    if abs(overlap_depth(box_a, box_b)) > 1e-6:
        assert collide == (area > 0), (area, overlap_depth(box_a, box_b))
    assert bev_collisions(box_b, box_a)[0, 0] == collide
    assert bev_collisions(box_a, box_a)[0, 0]  # identical boxes collide


def test_touching_boxes_do_not_collide(rng):
    box = np.array([10.0, 5.0, 0.0, 4.0, 2.0, 1.5, 0.0])
    for shift in ([4.0, 0.0], [0.0, 2.0], [4.0, 2.0], [-4.0, -2.0]):  # edge or corner contact
        other = box.copy()
        other[:2] += shift
        assert not bev_collisions(box, other)[0, 0]
        assert bev_overlap_area(box, other)[0, 0] == 0
        other[:2] -= np.sign(shift) * 1e-6
        assert bev_collisions(box, other)[0, 0]
    many = np.column_stack(
        [rng.uniform(0, 30, (200, 2)), np.zeros(200), rng.uniform(0.5, 5, (200, 3))]
    )
    many = np.column_stack([many, rng.uniform(-np.pi, np.pi, 200)])
    np.testing.assert_array_equal(bev_collisions(many, many), bev_overlap_area(many) > 0)


def naive_first_come(boxes, objects):
    """Greedy in order: a box stays unless its footprint overlaps (overlap_depth > 0) one kept
    before it of another object."""
    kept = []
    for i, box in enumerate(boxes):
        clash = any(
            kept[j] and objects[j] != objects[i] and overlap_depth(boxes[j], box) > 0
            for j in range(i)
        )
        kept.append(not clash)
    return np.array(kept, dtype=bool)


def test_first_come_follows_the_naive_greedy(rng):
    from drcpo.collisions import first_come

    for count, spread in ((60, 30.0), (200, 20.0), (40, 4.0)):
        boxes = np.column_stack(
            [
                rng.uniform(0, spread, (count, 2)),
                np.zeros(count),
                rng.uniform(0.5, 5, (count, 3)),
                rng.uniform(-np.pi, np.pi, count),
            ]
        )
        objects = rng.integers(0, count // 3, count)  # some alternatives of one object
        want = naive_first_come(boxes, objects)
        assert 0 < want.sum() < count
        np.testing.assert_array_equal(first_come(boxes, objects), want)
    # A chain a-b-c of overlaps: b goes, so c (clear of a) stays; exact edge contact (d) and
    # a copy of a kept box of the same object (e) stay; a copy of another's (f) goes.
    chain = np.array(
        [
            [0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],
            [3.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],
            [6.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],
            [-4.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],
            [0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],
            [6.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],
        ]
    )
    owners = np.array([0, 1, 2, 3, 0, 4])
    want = naive_first_come(chain, owners)
    np.testing.assert_array_equal(want, [True, False, True, True, True, False])
    np.testing.assert_array_equal(first_come(chain, owners), want)
    assert first_come(np.zeros((0, 7)), np.zeros(0, np.int64)).shape == (0,)


def test_box_members_match_points_in_boxes(rng):
    points = np.column_stack(
        [rng.uniform(-5, 45, (20000, 2)), rng.uniform(-3, 2, 20000), rng.random(20000)]
    ).astype(np.float32)
    points[:20, 0] = np.nan
    boxes = sample_poses(sizes(90), rng, PlacementConfig(x_range=(0, 40), y_range=(-5, 45)))
    boxes[:, 2] = rng.uniform(-1.5, 0.5, len(boxes))
    # Points on faces and corners (the closed-box rule) and boxes sharing points.
    corners = bev_corners(boxes[:5])
    points[20:40, :2] = corners.reshape(-1, 2)
    points[20:40, 2] = np.repeat(boxes[:5, 2], 4)
    boxes[-1] = boxes[0]
    point, box = box_members(points, boxes)
    expected = points_in_boxes(points, boxes)
    assert expected.sum() > 500
    found = np.zeros_like(expected)
    found[point, box] = True
    np.testing.assert_array_equal(found, expected)
    assert len(point) == expected.sum()


def test_field_of_view_test_matches_the_corner_azimuths(rng):
    boxes = sample_poses(sizes(500), rng, PlacementConfig(x_range=(-20, 50)))
    boxes[::7, :2] = np.nan
    half = np.deg2rad(41.0)
    corners = bev_corners(np.nan_to_num(boxes))
    expected = (np.abs(np.arctan2(corners[..., 1], corners[..., 0])) <= half).all(axis=1)
    expected &= np.isfinite(boxes[:, 0])
    np.testing.assert_array_equal(in_fov(boxes, half), expected)


# --------------------------------------------------------------------------------------------
# The draw against a step-by-step reference
# --------------------------------------------------------------------------------------------
def reference_area_draw(dims, seed, x_range, y_range):
    """Today's whole-area draw, step by step: headings, then (u, v) per box (no view)."""
    rng = np.random.default_rng(seed)
    heading = rng.uniform(-np.pi, np.pi, len(dims))
    u = rng.uniform(0.0, 1.0, (len(dims), 2))
    out = np.empty((len(dims), 7))
    for k, (dx, dy, dz) in enumerate(dims):
        c, s = abs(np.cos(heading[k])), abs(np.sin(heading[k]))
        reach_x, reach_y = (c * dx + s * dy) / 2.0, (s * dx + c * dy) / 2.0
        low_x, high_x = x_range[0] + reach_x, x_range[1] - reach_x
        low_y, high_y = y_range[0] + reach_y, y_range[1] - reach_y
        x = low_x + u[k, 0] * (high_x - low_x)
        y = low_y + u[k, 1] * (high_y - low_y)
        out[k] = [x, y, dz / 2.0, dx, dy, dz, heading[k]]
    return out


def reference_fov_draw(dims, seed, x_range, y_range, half_angle):
    """The draw with a field of view, step by step: headings, then rounds of (u, v) for the
    rows still to draw; a row whose footprint fits but has a corner (as bev_corners computes
    it) at an azimuth beyond ``half_angle`` (libm's atan2) is drawn again, at most
    FOV_ROUNDS more times, then left NaN."""
    from drcpo.poses import FOV_ROUNDS

    rng = np.random.default_rng(seed)
    heading = rng.uniform(-np.pi, np.pi, len(dims))
    out = np.column_stack([np.zeros((len(dims), 2)), dims[:, 2] / 2.0, dims, heading])
    todo = list(range(len(dims)))
    for _ in range(FOV_ROUNDS + 1):
        if not todo:
            break
        u = rng.uniform(0.0, 1.0, (len(todo), 2))
        again = []
        for k, r in enumerate(todo):
            dx, dy = float(dims[r, 0]), float(dims[r, 1])
            cos, sin = float(np.cos(heading[r])), float(np.sin(heading[r]))
            reach_x = (abs(cos) * dx + abs(sin) * dy) / 2
            reach_y = (abs(sin) * dx + abs(cos) * dy) / 2
            low_x, high_x = x_range[0] + reach_x, x_range[1] - reach_x
            low_y, high_y = y_range[0] + reach_y, y_range[1] - reach_y
            if low_x > high_x or low_y > high_y:
                out[r, :2] = np.nan
                continue
            x, y = low_x + u[k, 0] * (high_x - low_x), low_y + u[k, 1] * (high_y - low_y)
            out[r, :2] = x, y
            corners = [
                ((cos * a * dx - sin * b * dy) + x, (sin * a * dx + cos * b * dy) + y)
                for a, b in ((0.5, 0.5), (-0.5, 0.5), (-0.5, -0.5), (0.5, -0.5))
            ]
            if not all(abs(math.atan2(cy, cx)) <= half_angle for cx, cy in corners):
                again.append(r)
        todo = again
    out[todo, :2] = np.nan
    return out, rng.bit_generator.state


def test_the_field_of_view_draw_follows_the_step_by_step_reference():
    from drcpo.poses import draw_poses

    dims = np.concatenate([sizes(60), [[90.0, 1.0, 1.0], [1.0, 200.0, 1.0]]])  # two never fit
    for area, half in (
        (((0.0, 70.4), (-40.0, 40.0)), np.deg2rad(41.0)),
        (((-20.0, 50.0), (-40.0, 40.0)), 0.3),  # most of the area is out of view
        (((0.0, 70.4), (-40.0, 40.0)), 1e-4),  # nothing fits a sliver: every row left NaN
        (((-5.0, 5.0), (-5.0, 5.0)), np.pi),  # every direction
    ):
        want, state = reference_fov_draw(dims, 4, *area, half)
        rng = np.random.default_rng(4)
        got = draw_poses(dims, rng, *area, half_angle=half)
        np.testing.assert_array_equal(got, want)
        assert rng.bit_generator.state == state
    assert np.isnan(want[-2:, :2]).all() and np.isfinite(want[:-2]).all()


def test_place_objects_puts_boxes_where_the_whole_area_draw_puts_them(rng):
    dims = sizes(50)
    expected = reference_area_draw(dims, 9, AREA.x_range, AREA.y_range)
    np.testing.assert_array_equal(sample_poses(dims, np.random.default_rng(9)), expected)
    # place_objects draws so (an empty frame: every box fits)
    frame = Frame(ground_cloud(rng, n=2000).astype(np.float32))
    placed = place_objects(frame, dims, None, np.random.default_rng(9))
    assert len(placed.accepted) > 0
    np.testing.assert_array_equal(placed.boxes[:, :2], expected[placed.accepted, :2])
