import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drcpo import placement
from drcpo.collisions import bev_collisions
from drcpo.errors import ConfigError, DataError
from drcpo.frame import Frame
from drcpo.geometry import bev_corners, bev_overlap_area, box_members, points_in_boxes
from drcpo.ground import GroundConfig, GroundModel
from drcpo.occlusion.view_windows import surface_samples
from drcpo.placement import (
    REASONS,
    PlacementConfig,
    PlacementRounds,
    _Obstacles,
    frame_ground,
    place_objects,
    sample_poses,
)
from drcpo.poses import CentreCells, draw_poses, in_fov, observed_cells

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
    config = PlacementConfig(attempts=3)
    result = place_objects(frame, sizes(60), None, rng, config)
    assert len(result.accepted) >= 30
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

    crowded = {"x_range": (0, 30), "y_range": (-15, 15), "attempts": 4}
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


def place_with_verdicts(frame, dims, rng, config=None, occluded=None):
    """PlacementRounds driven to the end, ``occluded(boxes, placed)`` deciding each round."""
    rounds = PlacementRounds(frame, dims, None, rng, config)
    while (drawn := rounds.next_round()) is not None:
        rounds.settle(None if occluded is None else occluded(drawn.boxes, drawn.placed))
    return rounds.result()


def test_occluded_placements_are_tried_again(rng):
    frame = scene(rng, existing_boxes())
    calls = []

    def occluded(boxes, before):
        calls.append((boxes.copy(), before.copy()))
        return boxes[:, 0] < 35.0  # say the near half of the area is hidden

    config = PlacementConfig(attempts=6)
    result = place_with_verdicts(frame, sizes(20), rng, config, occluded)
    assert len(result.accepted) >= 10 and (result.boxes[:, 0] >= 35.0).all()
    np.testing.assert_array_equal(result.boxes[:, 3:6], sizes(20)[result.accepted])
    assert result.rejected["occluded"] > 0 and len(calls) > 1
    # Each call sees its candidates with their own sizes and every box placed before them.
    placed_so_far: set[tuple] = set()
    for boxes, before in calls:
        assert {tuple(b) for b in before} == placed_so_far
        placed_so_far |= {tuple(b) for b in boxes[boxes[:, 0] >= 35.0]}
    assert placed_so_far == {tuple(b) for b in result.boxes}
    left = result.reasons[result.reasons != ""]
    assert set(left) <= set(REASONS)
    # One try: those the test rejects stay rejected, for that reason.
    once = place_with_verdicts(frame, sizes(20), np.random.default_rng(3), occluded=occluded)
    assert (once.reasons == "occluded").sum() == once.rejected["occluded"] > 0


def test_rounds_draw_as_place_objects_whatever_the_verdicts():
    # The rounds are place_objects step by step: accepting everything gives its result, and
    # each round's boxes are the poses it drew that pass the geometric checks.
    frame = scene(np.random.default_rng(0), existing_boxes())
    config = PlacementConfig(attempts=4)
    plain = place_objects(frame, sizes(20), None, np.random.default_rng(5), config)
    rounds = place_with_verdicts(frame, sizes(20), np.random.default_rng(5), config)
    np.testing.assert_array_equal(rounds.boxes, plain.boxes)
    assert rounds.reasons.tolist() == plain.reasons.tolist()
    assert (rounds.rejected, rounds.attempts) == (plain.rejected, plain.attempts)
    # A rejected box is not placed: the next round draws its object again and does not count
    # it among the boxes placed before.
    first = PlacementRounds(frame, sizes(20), None, np.random.default_rng(5), config)
    drawn = first.next_round()
    assert len(drawn.boxes) and len(drawn.placed) == 0
    first.settle(np.ones(len(drawn.boxes), bool))
    assert first.result().rejected["occluded"] == len(drawn.boxes)
    assert len(first.next_round().placed) == 0
    first.settle()
    with pytest.raises(RuntimeError, match="next_round first"):
        first.settle()
    again = PlacementRounds(frame, sizes(20), None, np.random.default_rng(5), config)
    again.next_round()
    with pytest.raises(RuntimeError, match="settle the current round"):
        again.next_round()
    with pytest.raises(RuntimeError, match="settle the current round"):
        again.result()


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
        config = PlacementConfig(max_non_ground_points=limit, attempts=2)
        result = place_objects(frame, sizes(40), None, rng, config, ground)
        assert result.rejected["obstacle"] > 0
        assert len(result.accepted) > 0
        assert (nonground_counts(frame, ground, result.boxes) <= limit).all()


def test_obstacle_counts_match_brute_force(rng):
    frame = scene(rng, extra=[wall(rng, 10, 50, -20, 20, n=20000)])
    ground = GroundModel.from_points(frame.points)
    boxes = sample_poses(sizes(50), rng)
    boxes[:, 2] = ground.height_at(boxes[:, :2]) + boxes[:, 5] / 2
    obstacles = _Obstacles(frame.points, ground, AREA.ground_tolerance)
    expected = nonground_counts(frame, ground, boxes)
    np.testing.assert_array_equal(obstacles.count(boxes), expected)
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

    hidden = place_with_verdicts(frame, sizes(4), rng, occluded=lambda b, _: np.ones(len(b), bool))
    assert hidden.reasons.tolist() == ["occluded"] * 4 and len(hidden.accepted) == 0
    with pytest.raises(ValueError, match="1 occluded verdicts for 4 boxes"):
        place_with_verdicts(frame, sizes(4), rng, occluded=lambda b, _: np.ones(1, bool))


def test_retries_place_more_objects_and_count_attempts(rng):
    frame = scene(rng)
    config = PlacementConfig(x_range=(0, 15), y_range=(-8, 8))
    once = place_objects(frame, sizes(30), None, np.random.default_rng(3), config)
    tries = PlacementConfig(x_range=(0, 15), y_range=(-8, 8), attempts=6)
    more = place_objects(frame, sizes(30), None, np.random.default_rng(3), tries)
    assert len(more.accepted) > len(once.accepted)
    for result in (once, more):
        assert result.attempts == len(result.accepted) + sum(result.rejected.values())
        assert (result.reasons[result.accepted] == "").all()
        assert np.all(np.diff(result.accepted) > 0)
    assert once.attempts == 30


def test_source_height_mode_keeps_the_source_z(rng):
    frame = scene(rng)
    source = np.column_stack([np.zeros((9, 2)), np.linspace(-3, 1, 9), sizes(9), np.zeros(9)])
    config = PlacementConfig(height="source", max_non_ground_points=10**6)
    result = place_objects(frame, sizes(9), source, rng, config)
    assert len(result.accepted) > 0
    np.testing.assert_array_equal(result.boxes[:, 2], source[result.accepted, 2])
    with pytest.raises(DataError, match="source boxes"):
        place_objects(frame, sizes(9), None, rng, config)


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
    assert nothing.boxes.shape == (0, 7) and nothing.attempts == 0


def test_bad_input_is_rejected(rng):
    frame = scene(rng)
    with pytest.raises(DataError, match=r"dims\[1\]"):
        place_objects(frame, [[1.0, 1.0, 1.0], [1.0, -1.0, 1.0]], None, rng)
    with pytest.raises(DataError, match="shape"):
        place_objects(frame, [1.0, 1.0, 1.0], None, rng)
    with pytest.raises(ConfigError, match="placement.x_range"):
        PlacementConfig(x_range=(5, 5))
    with pytest.raises(ConfigError, match="placement.height"):
        PlacementConfig(height="air")
    with pytest.raises(ConfigError, match="placement.attempts"):
        PlacementConfig(attempts=0)
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


OBSERVED = {"height": "observed", "max_non_ground_points": 0}


def footprint_samples(boxes):
    """Corners and centre of each footprint, ``(K, 5, 2)``."""
    return np.concatenate([bev_corners(boxes), boxes[:, None, :2]], axis=1)


def observed_reference_counts(points, ground, boxes, tolerance=0.2):
    """Points per box above the observed ground at them (else above the box bottom)."""
    inside = points_in_boxes(points, boxes)
    heights, seen = ground.observed_height_at(points[:, :2])
    out = []
    for j, box in enumerate(boxes):
        reference = np.where(seen, heights, box[2] - box[5] / 2)
        out.append(int((inside[:, j] & (points[:, 2] > reference + tolerance)).sum()))
    return np.array(out)


def test_observed_boxes_stand_on_the_median_of_their_footprint_ground(rng):
    frame = scene(rng)
    ground = GroundModel.from_points(frame.points)
    config = PlacementConfig(attempts=3, **OBSERVED)
    result = place_objects(frame, sizes(30), None, rng, config, ground)
    assert len(result.accepted) >= 20
    samples = footprint_samples(result.boxes).reshape(-1, 2)
    heights, seen = ground.observed_height_at(samples, config.ground_gap)
    assert seen.all()
    bottom = result.boxes[:, 2] - result.boxes[:, 5] / 2
    np.testing.assert_allclose(bottom, np.median(heights.reshape(-1, 5), axis=1), atol=1e-12)
    assert np.abs(bottom - uneven(result.boxes[:, :2])).max() < 0.15
    # Ground returns lie inside the boxes (a box reaches down to the ground), yet with
    # max_non_ground_points 0 they are no obstacle.
    inside = points_in_boxes(frame.points, result.boxes).sum(axis=0)
    assert (inside > 0).mean() > 0.5
    np.testing.assert_array_equal(observed_reference_counts(frame.points, ground, result.boxes), 0)


def test_no_ground_where_the_frame_saw_none(rng):
    ground_xyz = ground_cloud(rng, n=60000)
    hole = (np.abs(ground_xyz[:, 0] - 30) < 10) & (np.abs(ground_xyz[:, 1]) < 10)
    frame = Frame(ground_xyz[~hole].astype(np.float32))
    ground = GroundModel.from_points(frame.points)
    over_hole = {"x_range": (21.0, 39.0), "y_range": (-9.0, 9.0)}
    observed = PlacementConfig(ground_gap=0.0, **over_hole, **OBSERVED)
    result = place_objects(frame, sizes(12), None, rng, observed, ground)
    assert result.rejected["no_ground"] == 12 and len(result.accepted) == 0
    assert set(result.reasons) == {"no_ground"}
    # The default mode places them on heights borrowed from the hole's rim.
    assert len(place_objects(frame, sizes(12), None, rng, PlacementConfig(**over_hole)).accepted)
    # From the hole's middle, the ground beyond it (14 m on) is farther than the gap
    # bridged between scan rings (0.3 of the range, 8 to 10 m).
    middle = PlacementConfig(x_range=(26.0, 34.0), y_range=(-4.0, 4.0), **OBSERVED)
    assert set(place_objects(frame, sizes(12), None, rng, middle, ground).reasons) == {"no_ground"}
    # Across the rim, only footprints whose five samples all saw ground are placed.
    rim = PlacementConfig(
        x_range=(10.0, 50.0), y_range=(-20.0, 20.0), attempts=4, ground_gap=0.0, **OBSERVED
    )
    result = place_objects(frame, sizes(40), None, rng, rim, ground)
    assert result.rejected["no_ground"] > 0 and len(result.accepted) > 0
    samples = footprint_samples(result.boxes)
    assert ~((np.abs(samples[..., 0] - 30) < 9.5) & (np.abs(samples[..., 1]) < 9.5)).any()


def ramp(xy):
    return -1.7 + 0.35 * (xy[:, 0] - 30)


def test_slope_rejects_footprints_on_steep_ground(rng):
    frame = Frame(ground_cloud(rng, n=60000, surface=ramp).astype(np.float32))
    ground = GroundModel.from_points(frame.points, config=GroundConfig(max_slope=0.5))
    # 0.35 rise per metre: at least 0.56 m over a car's 4.2 m diagonal, 0.21 m over a
    # cyclist's 1.9 m (along its 0.6 m width), more than the default limit of 0.1 allows.
    area = {"x_range": (5.0, 60.0), "y_range": (-20.0, 20.0), "attempts": 3}
    steep = place_objects(frame, sizes(20), None, rng, PlacementConfig(**area, **OBSERVED), ground)
    assert steep.rejected["slope"] > 0 and len(steep.accepted) == 0
    assert set(steep.reasons) <= {"slope", "no_ground"}
    lenient = PlacementConfig(max_slope=0.5, **area, **OBSERVED)
    placed = place_objects(frame, sizes(20), None, rng, lenient, ground)
    assert len(placed.accepted) > 10 and placed.rejected["slope"] == 0
    # Each placed footprint's heights spread by at most max_slope x its diagonal.
    heights, _ = ground.observed_height_at(footprint_samples(placed.boxes).reshape(-1, 2))
    spread = np.ptp(heights.reshape(-1, 5), axis=1)
    diagonal = np.hypot(placed.boxes[:, 3], placed.boxes[:, 4])
    assert (spread <= 0.5 * diagonal).all() and (spread > 0.1 * diagonal).all()


def test_observed_obstacles_are_measured_from_the_ground_under_them(rng):
    blocks = [wall(rng, 10, 30, -20, 20, height=2.0, n=20000), wall(rng, 40, 45, 0, 8, n=2000)]
    frame = scene(rng, extra=blocks)
    ground = GroundModel.from_points(frame.points)
    boxes = sample_poses(sizes(200), rng)
    boxes[:, 2] = ground.height_at(boxes[:, :2]) + boxes[:, 5] / 2 + rng.uniform(-0.3, 0.3, 200)
    obstacles = _Obstacles(frame.points, ground, 0.2, observed=True)
    for _ in range(4):  # unindexed, then indexed: the same counts
        counts = obstacles.count(boxes)
        np.testing.assert_array_equal(
            counts, observed_reference_counts(frame.points, ground, boxes)
        )
    assert obstacles._index is not None and counts.max() > 10 and (counts == 0).sum() > 20
    config = PlacementConfig(attempts=4, **OBSERVED)
    result = place_objects(frame, sizes(40), None, rng, config, ground)
    assert result.rejected["obstacle"] > 0 and len(result.accepted) > 10
    np.testing.assert_array_equal(observed_reference_counts(frame.points, ground, result.boxes), 0)


def test_indexed_members_are_box_members(rng):
    points = ground_cloud(rng, n=20000).astype(np.float32)
    points[:50, :2] = np.nan  # never inside
    boxes = sample_poses(sizes(300), rng, PlacementConfig(x_range=(-20, 90), y_range=(-60, 60)))
    boxes[:, 2] = rng.uniform(-2.5, -1.0, 300)
    boxes[:3, :2] = [[500.0, 0.0], [0.0, -500.0], [-300.0, 300.0]]  # beyond the frame
    obstacles = _Obstacles(points, GroundModel.from_points(points), 0.2)
    expected = {tuple(pair) for pair in np.column_stack(box_members(points, boxes))}
    for _ in range(4):
        pairs = {tuple(pair) for pair in np.column_stack(obstacles.members(boxes))}
        assert pairs == expected
    assert obstacles._index is not None and len(expected) > 300
    empty = _Obstacles(np.full((5, 4), np.nan, np.float32), GroundModel.flat(), 0.2)
    for _ in range(4):
        assert len(empty.members(boxes)[0]) == 0


def test_many_rounds_give_the_same_placements_indexed_or_not(rng, monkeypatch):
    frame = scene(rng, existing_boxes(), extra=[wall(rng, 10, 30, -20, 20, n=20000)])
    config = PlacementConfig(attempts=8, x_range=(0, 35), y_range=(-25, 25))
    indexed = place_objects(frame, sizes(40), None, np.random.default_rng(4), config)
    monkeypatch.setattr(placement, "_INDEX_AFTER", 10**9)
    plain = place_objects(frame, sizes(40), None, np.random.default_rng(4), config)
    np.testing.assert_array_equal(indexed.boxes, plain.boxes)
    assert indexed.rejected == plain.rejected and indexed.rejected["obstacle"] > 0


def test_max_attempts_per_frame_caps_the_poses(rng):
    frame = scene(rng)

    def run(cap, seed=3, attempts=6, hide=True):
        config = PlacementConfig(attempts=attempts, max_attempts_per_frame=cap)
        rounds = PlacementRounds(frame, sizes(30), None, np.random.default_rng(seed), config)
        drawn = []
        while (round_ := rounds.next_round()) is not None:
            drawn.append(len(round_.boxes))
            rounds.settle(np.ones(len(round_.boxes), bool) if hide else None)
        return rounds.result(), drawn

    capped, drawn = run(100)  # rounds of 30, 30, 30 and 10 poses
    assert capped.attempts == 100 and len(drawn) == 4 and drawn[-1] <= 10
    assert capped.attempts == len(capped.accepted) + sum(capped.rejected.values())
    # A cap below the objects asked: those never tried end as "budget", one per object.
    starved, _ = run(12)
    assert starved.attempts == 12 and starved.rejected["budget"] == 18
    assert starved.reasons[12:].tolist() == ["budget"] * 18
    assert (starved.reasons[:12] != "budget").all()
    assert starved.attempts == sum(starved.rejected.values()) - 18
    # A cap never reached draws exactly what no cap draws.
    free, _ = run(None, hide=False)
    roomy, _ = run(10_000, hide=False)
    np.testing.assert_array_equal(free.boxes, roomy.boxes)
    assert free.rejected == roomy.rejected and free.rejected["budget"] == 0
    # Same seed, same capped output.
    again, _ = run(100)
    assert again.reasons.tolist() == capped.reasons.tolist()


def test_several_poses_per_round_are_tried_in_turn(rng):
    """poses_per_round = 3: an object's poses come in turn (first poses of every object, then
    the second ones, ...); the first one the caller accepts is placed and its later ones are
    unused (not attempts); the same attempts per object in a third of the rounds."""
    frame = scene(rng, existing_boxes())
    config = PlacementConfig(attempts=6, poses_per_round=3, x_range=(0, 40), y_range=(-20, 20))
    rounds = PlacementRounds(frame, sizes(25), None, np.random.default_rng(8), config)
    verdicts = np.random.default_rng(9)
    count, placed_from = 0, {}
    while (drawn := rounds.next_round()) is not None:
        count += 1
        objects = drawn.objects
        assert len(objects) == len(drawn.boxes)
        # blocks of increasing object numbers: first poses, then second ones, ...
        starts = np.flatnonzero(np.diff(objects) <= 0) + 1
        for block in np.split(objects, starts):
            assert (np.diff(block) > 0).all()
        hidden = verdicts.random(len(objects)) < 0.5
        taken = {}
        for i, obj in enumerate(objects.tolist()):  # the caller's rule: first accepted wins
            if obj in taken or drawn.conflicts[i, list(taken.values())].any():
                hidden[i] = False  # passed over: neither (a conflict: placement rejects it)
            elif not hidden[i]:
                taken[obj] = i
        for obj, i in taken.items():
            placed_from[obj] = drawn.boxes[i]
        rounds.settle(hidden)
    result = rounds.result()
    assert count == 2  # 6 attempts, 3 per round
    assert sorted(placed_from) == result.accepted.tolist()
    for k, obj in enumerate(result.accepted):
        np.testing.assert_array_equal(result.boxes[k], placed_from[int(obj)])
    assert result.attempts == len(result.accepted) + sum(result.rejected.values())
    assert result.rejected["occluded"] > 0 and len(result.accepted) > 5
    assert result.rejected["collision"] > 0  # conflicts among the round's poses, once taken
    assert not bev_collisions(result.boxes, result.boxes)[
        ~np.eye(len(result.boxes), dtype=bool)
    ].any()
    assert not bev_collisions(result.boxes, frame.boxes).any()
    # one pose per round is the default, and draws as before
    one = PlacementConfig(attempts=6, x_range=(0, 40), y_range=(-20, 20))
    same = dataclasses.replace(one, poses_per_round=1)
    a = place_objects(frame, sizes(25), None, np.random.default_rng(8), one)
    b = place_objects(frame, sizes(25), None, np.random.default_rng(8), same)
    np.testing.assert_array_equal(a.boxes, b.boxes)
    with pytest.raises(ConfigError, match="placement.poses_per_round"):
        PlacementConfig(poses_per_round=0)


def test_new_keys_are_checked():
    assert REASONS[:4] == ("out_of_range", "collision", "obstacle", "occluded")
    assert PlacementConfig(height="observed").height == "observed"
    for key, value in (
        ("max_slope", -0.1),
        ("ground_gap", 1.5),
        ("max_attempts_per_frame", 0),
        ("max_attempts_per_frame", 2.5),
    ):
        with pytest.raises(ConfigError, match=f"placement.{key}"):
            PlacementConfig(**{key: value})
    assert PlacementConfig(max_attempts_per_frame=None).max_attempts_per_frame is None
    defaults = PlacementConfig()
    assert (defaults.max_attempts_per_frame, defaults.height) == (None, "ground")


def test_frame_ground_leaves_out_the_points_in_excluded_boxes(rng):
    cloud = ground_cloud(rng, n=40000)
    # An object pasted from another frame, its bottom 0.6 m below this frame's ground.
    pasted_xy = np.column_stack([rng.uniform(20, 24, 3000), rng.uniform(-1, 1, 3000)])
    pasted = np.column_stack(
        [pasted_xy, uneven(pasted_xy) - 0.6 + rng.uniform(0, 1.5, 3000), np.ones(3000)]
    )
    frame = Frame(np.concatenate([cloud, pasted]).astype(np.float32))
    box = np.array(
        [[22.0, 0.0, float(uneven(np.array([[22.0, 0.0]]))[0]) + 0.15, 4.2, 2.2, 1.6, 0]]
    )
    under = np.array([[21.0, 0.0], [22.5, 0.5], [23.0, -0.5]])
    plain = frame_ground(frame)
    assert (plain.height_at(under) - uneven(under) < -0.4).all()  # it rides on the pasted one
    cleaned = frame_ground(frame, exclude=box)
    assert np.abs(cleaned.height_at(under) - uneven(under)).max() < 0.1
    outside = ~points_in_boxes(frame.points, box)[:, 0]
    reference = GroundModel.from_points(frame.points[outside])
    np.testing.assert_array_equal(cleaned.heights, reference.heights)
    for nothing in (None, np.zeros((0, 7))):
        np.testing.assert_array_equal(frame_ground(frame, exclude=nothing).heights, plain.heights)
    with pytest.raises(DataError, match=r"exclude boxes must have shape \(M, 7\)"):
        frame_ground(frame, exclude=np.zeros((2, 6)))
    with pytest.raises(DataError, match="non-finite"):
        frame_ground(frame, exclude=np.full((1, 7), np.nan))


def test_observed_placement_on_real_kitti_frames(kitti_sample):
    from drcpo.datasets.kitti import KittiDataset

    rng = np.random.default_rng(0)
    config = PlacementConfig(attempts=10, fov_only=True, **OBSERVED)
    touching = placed = 0
    for frame in KittiDataset(kitti_sample, "train"):
        ground = frame_ground(frame)
        result = place_objects(frame, sizes(30), None, rng, config, ground)
        # Frame 000000 is a street closed by buildings 20 m ahead: little ground to stand on.
        assert len(result.accepted) >= 3, (frame.frame_id, result.rejected)
        placed += len(result.accepted)
        counts = observed_reference_counts(frame.points, ground, result.boxes)
        np.testing.assert_array_equal(counts, 0, err_msg=frame.frame_id)
        touching += int((points_in_boxes(frame.points, result.boxes).sum(axis=0) > 0).sum())
        # The bottom lies on the frame's own ground returns under the footprint.
        columns = result.boxes.copy()
        columns[:, 5] = 1.0
        columns[:, 2] = result.boxes[:, 2] - result.boxes[:, 5] / 2
        inside = points_in_boxes(frame.points, columns)
        for j in np.flatnonzero(inside.sum(axis=0) >= 5):
            gap = np.median(frame.points[inside[:, j], 2]) - columns[j, 2]
            assert abs(gap) < 0.15, (frame.frame_id, j, gap)
    # Ground returns under a box are no obstacle: boxes holding some are placed.
    assert touching >= 30 and placed >= 80


# --------------------------------------------------------------------------------------------
# height "observed": centres drawn where the frame observed ground (drcpo.poses)
# --------------------------------------------------------------------------------------------
def toy_ground(rng, shape=(30, 20), share=0.3, origin=(0.0, -10.0), size=1.0):
    """A grid ground whose ground cells are a random ``share`` of its cells."""
    cells = rng.uniform(0, 1, shape) < share
    heights = np.full(shape, -1.7)
    return GroundModel(
        np.array([0.0, 0.0, -1.7]), np.asarray(origin), size, heights, cells, "points"
    )


def reference_cells(ground, x_range, y_range, half_angle=None):
    """Lower corners of the ground cells whose centre lies in the area (and view), by loops."""
    found = []
    nx, ny = ground.ground_cells.shape
    for i in range(nx):
        for j in range(ny):
            cx = ground.origin[0] + (i + 0.5) * ground.cell_size
            cy = ground.origin[1] + (j + 0.5) * ground.cell_size
            inside = x_range[0] <= cx <= x_range[1] and y_range[0] <= cy <= y_range[1]
            if half_angle is not None:
                inside = inside and abs(math.atan2(cy, cx)) <= half_angle
            if inside and ground.ground_cells[i, j]:
                found.append((cx - ground.cell_size / 2, cy - ground.cell_size / 2))
    return np.array(found).reshape(-1, 2)


def cell_of(ground, xy):
    """``(i, j)`` of the grid cell holding each position (naive floor)."""
    return [
        (math.floor((x - ground.origin[0]) / ground.cell_size),
         math.floor((y - ground.origin[1]) / ground.cell_size))
        for x, y in xy
    ]  # fmt: skip


@pytest.mark.parametrize("half_angle", [None, 0.5])
def test_observed_cells_are_the_ground_cells_in_the_area(rng, half_angle):
    ground = toy_ground(rng, origin=(2.0, -10.0))
    x_range, y_range = (5.0, 25.0), (-6.5, 8.0)
    cells = observed_cells(ground, x_range, y_range, half_angle)
    expected = reference_cells(ground, x_range, y_range, half_angle)
    assert 10 < len(expected) < ground.ground_cells.sum()
    np.testing.assert_array_equal(cells.corners, expected)
    assert cells.size == ground.cell_size
    # No grid (a plane or the flat fallback): nowhere observed.
    assert len(observed_cells(GroundModel.flat(), x_range, y_range).corners) == 0


def test_observed_cells_bridge_scan_rings_as_observed_height_at_does():
    # Two rings on the ground, 4 m apart at 14 m: the cells between them are observed with a
    # gap of 0.3 of the range, not with 0.
    shape = (30, 20)
    ground_cells = np.zeros(shape, dtype=bool)
    ground_cells[[12, 16], :] = True
    ground = GroundModel(
        np.array([0.0, 0.0, -1.7]), np.array([0.0, -10.0]), 1.0, np.full(shape, -1.7),
        ground_cells, "points",
    )  # fmt: skip
    area = ((0.0, 30.0), (-10.0, 10.0))
    strict = observed_cells(ground, *area)
    np.testing.assert_array_equal(strict.corners, reference_cells(ground, *area))
    bridged = observed_cells(ground, *area, max_gap=0.3)
    centres = np.array([[x + 0.5, y + 0.5] for x in range(30) for y in range(-10, 10)])
    expected = centres[[ground.observed_height_at(c[None], 0.3)[1][0] for c in centres]] - 0.5
    np.testing.assert_array_equal(bridged.corners, expected)
    between = (bridged.corners[:, 0] > 12) & (bridged.corners[:, 0] < 16)
    assert between.sum() >= 20 and len(bridged.corners) > len(strict.corners)


def test_centres_lie_on_observed_ground_cells_inside_the_area_and_view(rng):
    ground = toy_ground(rng, shape=(60, 60), origin=(0.0, -30.0))
    x_range, y_range, half = (0.0, 60.0), (-30.0, 30.0), 0.6
    cells = observed_cells(ground, x_range, y_range, half)
    boxes = draw_poses(sizes(3000), rng, x_range, y_range, half, cells)
    drawn = np.isfinite(boxes[:, 0])
    assert drawn.mean() > 0.95
    for i, j in cell_of(ground, boxes[drawn, :2]):
        assert ground.ground_cells[i, j]
    corners = bev_corners(boxes[drawn])
    assert (corners[..., 0] >= x_range[0]).all() and (corners[..., 0] <= x_range[1]).all()
    assert (corners[..., 1] >= y_range[0]).all() and (corners[..., 1] <= y_range[1]).all()
    assert in_fov(boxes[drawn], half).all()
    # A footprint too large for the area cannot fit anywhere.
    huge = draw_poses(np.array([[100.0, 100.0, 1.0]]), rng, x_range, y_range, None, cells)
    assert np.isnan(huge[0, :2]).all()


def test_centres_are_uniform_over_the_observed_cells(rng):
    from scipy import stats

    ground = toy_ground(rng, shape=(12, 10), share=0.35, origin=(0.0, -5.0))
    cells = observed_cells(ground, (0.0, 12.0), (-5.0, 5.0))
    count = 40000
    tiny = np.full((count, 3), 0.01)
    boxes = draw_poses(tiny, np.random.default_rng(7), (0.0, 12.0), (-5.0, 5.0), None, cells)
    index = {tuple(c): k for k, c in enumerate(cell_of(ground, cells.corners + 0.5))}
    per_cell = np.zeros(len(cells.corners))
    inside_x, inside_y = [], []
    for (x, y), key in zip(boxes[:, :2], cell_of(ground, boxes[:, :2]), strict=True):
        per_cell[index[key]] += 1  # a KeyError: a centre off the observed cells
        inside_x.append(x - math.floor(x))
        inside_y.append(y - math.floor(y))
    assert stats.chisquare(per_cell).pvalue > 1e-3
    # Inside a cell, uniform too (the edge cells lose only the 0.005 m the box's half needs).
    for share in (inside_x, inside_y):
        assert stats.chisquare(np.histogram(share, bins=10, range=(0, 1))[0]).pvalue > 1e-3
    # The whole-area draw (the other modes') lands on ground cells by their share only.
    whole = draw_poses(tiny[:2000], np.random.default_rng(7), (0.0, 12.0), (-5.0, 5.0))
    hits = [ground.ground_cells[i, j] for i, j in cell_of(ground, whole[:, :2])]
    share = ground.ground_cells.mean()
    assert abs(np.mean(hits) - share) < 4 * math.sqrt(share * (1 - share) / 2000) < 0.05


def test_observed_placement_draws_on_observed_ground_only(rng, monkeypatch):
    # A street: ground only on a 12 m wide strip, buildings on either side.
    ground_xyz = ground_cloud(rng, n=60000)
    street = np.abs(ground_xyz[:, 1]) < 6
    houses = [wall(rng, 0, 70, 8, 40), wall(rng, 0, 70, -40, -8)]
    frame = Frame(np.concatenate([ground_xyz[street], *houses]).astype(np.float32))
    ground = GroundModel.from_points(frame.points)
    config = PlacementConfig(attempts=20, ground_gap=0.0, **OBSERVED)
    drawn = []
    draw = placement.draw_poses

    def spy(*args):
        drawn.append(draw(*args))
        return drawn[-1]

    monkeypatch.setattr(placement, "draw_poses", spy)
    result = place_objects(frame, sizes(30), None, np.random.default_rng(3), config, ground)
    centres = np.concatenate(drawn)[:, :2]
    centres = centres[np.isfinite(centres[:, 0])]
    assert len(centres) == result.attempts - result.rejected["out_of_range"]
    assert ground.observed_height_at(centres)[1].all()
    # Drawn over the whole area instead (no cells), most poses miss the street.
    monkeypatch.setattr(placement, "observed_cells", lambda *args: None)
    whole = place_objects(frame, sizes(30), None, np.random.default_rng(3), config, ground)
    assert whole.rejected["no_ground"] > 2 * result.rejected["no_ground"]
    assert whole.attempts / max(len(whole.accepted), 1) > 2 * result.attempts / len(result.accepted)
    assert len(result.accepted) >= len(whole.accepted)


def test_rounds_take_the_centre_cells_of_an_earlier_pass(rng, monkeypatch):
    """Rounds given the :attr:`PlacementRounds.cells` of an earlier pass on the same ground
    and area place as those finding them again, without finding them; given cells are what
    the centres are drawn over."""
    frame = scene(rng, existing_boxes(), [wall(rng, 20, 40, 5, 30)])
    ground = GroundModel.from_points(frame.points)
    config = PlacementConfig(attempts=5, fov_only=True, **OBSERVED)

    def run(cells=None):
        rounds = PlacementRounds(frame, sizes(20), None, np.random.default_rng(4), config,
                                 ground, cells)  # fmt: skip
        while rounds.next_round() is not None:
            rounds.settle()
        return rounds

    first = run()
    assert len(first.cells.corners) > 10
    monkeypatch.setattr(placement, "observed_cells", None)  # (not called again)
    again = run(first.cells)
    assert again.cells is first.cells
    np.testing.assert_array_equal(again.result().boxes, first.result().boxes)
    assert again.result().rejected == first.result().rejected
    nowhere = run(CentreCells(np.zeros((0, 2)), first.cells.size)).result()
    assert len(nowhere.accepted) == 0 and set(nowhere.reasons) == {"no_ground"}


def test_observed_placement_without_observed_ground_rejects_no_ground(rng):
    frame = scene(rng)
    config = PlacementConfig(attempts=3, **OBSERVED)
    result = place_objects(frame, sizes(6), None, rng, config, GroundModel.flat())
    assert result.rejected["no_ground"] == 18 and set(result.reasons) == {"no_ground"}


def test_observed_placement_is_deterministic_and_seeded(rng):
    frame = scene(rng, existing_boxes(), [wall(rng, 20, 40, 5, 30)])
    ground = GroundModel.from_points(frame.points)
    config = PlacementConfig(attempts=5, fov_only=True, clearance=0.3, **OBSERVED)
    runs = [
        place_objects(frame, sizes(24), None, np.random.default_rng(s), config, ground)
        for s in (5, 5, 6)
    ]
    np.testing.assert_array_equal(runs[0].boxes, runs[1].boxes)
    assert runs[0].rejected == runs[1].rejected
    assert not np.array_equal(runs[0].boxes, runs[2].boxes)
    assert in_fov(runs[0].boxes, config.fov_half_angle).all()


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


@pytest.mark.parametrize("height", ["ground", "source"])
def test_other_height_modes_keep_the_whole_area_draw(rng, height):
    dims = sizes(50)
    expected = reference_area_draw(dims, 9, AREA.x_range, AREA.y_range)
    np.testing.assert_array_equal(sample_poses(dims, np.random.default_rng(9)), expected)
    # PlacementRounds draws its first round so in these modes (the frame has room for all).
    config = PlacementConfig(height=height)
    frame = Frame(ground_cloud(rng, n=2000).astype(np.float32))
    source = np.column_stack([np.zeros((len(dims), 2)), np.full(len(dims), -0.9), dims])
    source = np.column_stack([source, np.zeros(len(dims))])
    rounds = PlacementRounds(frame, dims, source, np.random.default_rng(9), config)
    assert rounds.cells is None
    drawn = rounds.next_round()
    tried = rounds._open[1]
    np.testing.assert_array_equal(tried[:, :2], expected[:, :2])
    assert len(drawn.boxes) > 0
    assert PlacementConfig().height == "ground"
