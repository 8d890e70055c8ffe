import numpy as np
import pytest
from conftest import random_boxes
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import Polygon

from drcpo import geometry as g


def test_rotation_matrix_is_orthonormal_and_turns_x_towards_y():
    rot = g.rotation_matrix_z(np.pi / 2)
    np.testing.assert_allclose(rot @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    angles = np.linspace(-4, 4, 9)
    mats = g.rotation_matrix_z(angles)
    np.testing.assert_allclose(
        mats @ mats.transpose(0, 2, 1), np.broadcast_to(np.eye(3), mats.shape), atol=1e-12
    )


def test_wrap_angle_range():
    wrapped = g.wrap_angle(np.array([-np.pi, np.pi, 3 * np.pi, -7.0, 0.5]))
    assert (wrapped >= -np.pi).all() and (wrapped < np.pi).all()
    np.testing.assert_allclose(np.cos(wrapped), np.cos([-np.pi, np.pi, 3 * np.pi, -7.0, 0.5]))


def test_box_corners_match_dimensions_and_heading():
    box = np.array([[1.0, 2.0, 3.0, 4.0, 2.0, 1.0, np.pi / 2]])
    corners = g.box_corners(box)[0]
    # Length runs along +y after a quarter turn.
    assert np.ptp(corners[:, 1]) == pytest.approx(4.0)
    assert np.ptp(corners[:, 0]) == pytest.approx(2.0)
    assert np.ptp(corners[:, 2]) == pytest.approx(1.0)
    np.testing.assert_allclose(corners.mean(axis=0), [1, 2, 3], atol=1e-12)


def test_canonical_round_trip_keeps_features(rng):
    points = rng.normal(size=(50, 5)).astype(np.float32)
    box = np.array([3.0, -2.0, 0.5, 4, 2, 1.5, 2.3])
    canonical = g.to_canonical(points, box)
    np.testing.assert_array_equal(canonical[:, 3:], points[:, 3:])
    np.testing.assert_allclose(g.from_canonical(canonical, box), points, atol=1e-5)


def test_canonical_pose_puts_box_corners_on_axis_aligned_box():
    box = np.array([10.0, 5.0, -1.0, 4.0, 2.0, 1.5, 0.7])
    canonical = g.to_canonical(g.box_corners(box)[0], box)
    np.testing.assert_allclose(np.abs(canonical), [[2.0, 1.0, 0.75]] * 8, atol=1e-12)


def _points_in_boxes_halfspaces(points, boxes, margin=0.0):
    """Independent check: a point is inside iff it is on the inner side of all six face planes."""
    corners = g.box_corners(boxes)
    out = np.zeros((len(points), len(boxes)), dtype=bool)
    for m, c in enumerate(corners):
        centre = c.mean(axis=0)
        inside = np.ones(len(points), dtype=bool)
        for a, b in [(0, 1), (1, 2), (0, 4)]:
            axis = c[b] - c[a] if (a, b) != (0, 4) else c[4] - c[0]
            length = np.linalg.norm(axis)
            unit = axis / length
            proj = (points[:, :3] - centre) @ unit
            inside &= np.abs(proj) <= length / 2 + margin + 1e-9
        out[:, m] = inside
    return out


def test_points_in_boxes_matches_halfspace_test(rng):
    boxes = random_boxes(rng, 20)
    points = rng.uniform(-7, 7, (5000, 4))
    np.testing.assert_array_equal(
        g.points_in_boxes(points, boxes), _points_in_boxes_halfspaces(points, boxes)
    )
    np.testing.assert_array_equal(
        g.points_in_boxes(points, boxes, margin=0.1),
        _points_in_boxes_halfspaces(points, boxes, margin=0.1),
    )


def test_points_in_boxes_boundary_is_closed():
    box = np.array([[0.0, 0, 0, 2, 1, 1, 0]])
    on_faces = np.array([[1, 0.5, 0.5], [-1, -0.5, -0.5], [1, 0, 0], [0, 0, 0.5]])
    assert g.points_in_boxes(on_faces, box).all()
    assert not g.points_in_boxes(np.array([[1.0001, 0, 0]]), box).any()


def test_points_in_boxes_empty_inputs():
    assert g.points_in_boxes(np.zeros((0, 4)), np.zeros((3, 7))).shape == (0, 3)
    assert g.points_in_boxes(np.zeros((5, 4)), np.zeros((0, 7))).shape == (5, 0)


def _shapely_overlap(a, b):
    pa = [Polygon(c) for c in g.bev_corners(a)]
    pb = [Polygon(c) for c in g.bev_corners(b)]
    return np.array([[p.intersection(q).area for q in pb] for p in pa])


def test_bev_overlap_matches_shapely(rng):
    a, b = random_boxes(rng, 60, 3.0), random_boxes(rng, 40, 3.0)
    np.testing.assert_allclose(g.bev_overlap_area(a, b), _shapely_overlap(a, b), atol=1e-9)


def test_bev_overlap_degenerate_pairs():
    boxes = np.array(
        [
            [0, 0, 0, 2, 1, 1, 0],
            [0, 0, 0, 2, 1, 1, 0],  # identical
            [2, 0, 0, 2, 1, 1, 0],  # touching along an edge
            [1, 0, 0, 2, 1, 1, np.pi / 2],  # crossing at right angles
            [0, 0, 0, 2, 1, 1, np.pi],  # same footprint, turned around
        ]
    )
    np.testing.assert_allclose(g.bev_overlap_area(boxes), _shapely_overlap(boxes, boxes), atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(-3, 3), min_size=2, max_size=2),
    st.lists(st.floats(0.1, 5), min_size=4, max_size=4),
    st.floats(-7, 7),
    st.floats(-7, 7),
)
def test_bev_overlap_property(centre, dims, yaw_a, yaw_b):
    a = np.array([[0, 0, 0, dims[0], dims[1], 1, yaw_a]])
    b = np.array([[centre[0], centre[1], 0, dims[2], dims[3], 1, yaw_b]])
    ours = g.bev_overlap_area(a, b)[0, 0]
    assert ours == pytest.approx(_shapely_overlap(a, b)[0, 0], abs=1e-7)
    assert ours == pytest.approx(g.bev_overlap_area(b, a)[0, 0], abs=1e-9)


def test_bev_iou_of_box_with_itself_is_one(rng):
    boxes = random_boxes(rng, 10)
    np.testing.assert_allclose(np.diag(g.bev_iou(boxes)), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.diag(g.boxes_iou3d(boxes)), 1.0, atol=1e-9)


def test_iou3d_matches_shapely_times_height(rng):
    a, b = random_boxes(rng, 15, 2.0), random_boxes(rng, 15, 2.0)
    inter_h = np.clip(
        np.minimum(a[:, None, 2] + a[:, None, 5] / 2, b[None, :, 2] + b[None, :, 5] / 2)
        - np.maximum(a[:, None, 2] - a[:, None, 5] / 2, b[None, :, 2] - b[None, :, 5] / 2),
        0,
        None,
    )
    inter = _shapely_overlap(a, b) * inter_h
    union = a[:, 3:6].prod(1)[:, None] + b[:, 3:6].prod(1)[None] - inter
    np.testing.assert_allclose(g.boxes_iou3d(a, b), inter / union, atol=1e-9)


def test_canonical_iou3d_is_iou3d_of_centred_boxes(rng):
    dims_a, dims_b = rng.uniform(0.2, 4, (30, 3)), rng.uniform(0.2, 4, (30, 3))
    a = np.column_stack([np.zeros((30, 3)), dims_a, np.zeros(30)])
    b = np.column_stack([np.zeros((30, 3)), dims_b, np.zeros(30)])
    np.testing.assert_allclose(
        g.canonical_iou3d(dims_a[:, None], dims_b[None]), g.boxes_iou3d(a, b), atol=1e-9
    )


def test_box_holding_moves_out_only_the_faces_points_lie_beyond(rng):
    box = np.array([10.0, -4.0, -0.8, 4.0, 1.8, 1.5, 0.7])
    canonical = rng.uniform(-0.5, 0.5, (300, 3)) * box[3:6]
    inside = g.from_canonical(canonical, box)
    np.testing.assert_array_equal(g.box_holding(box, inside), box)
    np.testing.assert_array_equal(g.box_holding(box, np.zeros((0, 4))), box)
    # Two points 4 cm beyond the front face and 2 cm above the top.
    canonical = np.vstack([canonical, [[2.04, 0.1, 0.0], [-1.0, 0.3, 0.77]]])
    points = g.from_canonical(canonical, box).astype(np.float32)
    held = g.box_holding(box, points, pad=1e-4)
    assert g.points_in_boxes(points, held[None]).all()
    assert held[6] == box[6]
    growth = np.array([0.04 + 1e-4, 0.0, 0.02 + 1e-4])
    np.testing.assert_allclose(held[3:6], box[3:6] + growth, atol=1e-5)
    # The back, sides and bottom stay where they were.
    local = g.to_canonical(g.box_corners(held[None])[0], box)[:, :3]
    np.testing.assert_allclose(local.min(axis=0), -box[3:6] / 2, atol=1e-9)
    np.testing.assert_allclose(local.max(axis=0), box[3:6] / 2 + growth, atol=1e-5)


# --------------------------------------------------------------------------------------------
# The points-in-box rule (in_box) and every caller of it, on adversarial inputs
# --------------------------------------------------------------------------------------------
def naive_in_box(point, box, margin):
    """The rule in plain Python floats, with numpy's cos and sin of the heading."""
    cos, sin = float(np.cos(box[6:7])[0]), float(np.sin(box[6:7])[0])
    ox, oy, oz = (float(point[a]) - float(box[a]) for a in range(3))
    local_x, local_y = ox * cos + oy * sin, -ox * sin + oy * cos
    half = [float(box[3 + a]) / 2.0 + margin for a in range(3)]
    return abs(local_x) <= half[0] and abs(local_y) <= half[1] and abs(oz) <= half[2]


def naive_mask(points, boxes, margin):
    return np.array([[naive_in_box(p, b, margin) for b in boxes] for p in points], bool)


MARGINS = (0.0, 0.2, -0.2, 1e-4)


def adversarial_boxes(rng):
    """Rotated and axis-aligned boxes (quarter turns), overlapping, near the origin and far."""
    headings = [0.0, np.pi / 2, np.pi, -np.pi / 2, 0.3, -2.1, 1e-9]
    boxes = []
    for centre in ([0.0, 0.0, 0.0], [1e6, -1e6, 3.0], [1e12, 1e12, -1e3]):
        for h in headings:
            size = rng.choice([0.5, 1.0, 2.0, 4.0], 3)
            boxes.append([*(np.asarray(centre) + rng.uniform(-1, 1, 3)), *size, h])
    boxes.append(boxes[0])  # a duplicate: a point in two boxes
    boxes.append([0.0, 0.0, 0.0, 2.0, 1.0, 1.0, 0.0])  # exactly representable faces
    return np.array(boxes)


def adversarial_points(boxes, rng):
    """``float64 (N, 4)``: per box, its corners, edge midpoints and face centres (computed as
    the rule computes the frame, so they land on or a rounding off the faces), the same grown
    and shrunk by each margin and nudged by one float step either way; plus NaN and inf."""
    unit = np.array(np.meshgrid([-0.5, 0.0, 0.5], [-0.5, 0.0, 0.5], [-0.5, 0.0, 0.5])).T
    unit = unit.reshape(-1, 3)
    out = []
    for box in boxes:
        cos, sin = np.cos(box[6:7])[0], np.sin(box[6:7])[0]
        for margin in MARGINS:
            local = unit * box[3:6] + np.sign(unit) * margin
            world = np.column_stack(
                [
                    cos * local[:, 0] - sin * local[:, 1] + box[0],
                    sin * local[:, 0] + cos * local[:, 1] + box[1],
                    local[:, 2] + box[2],
                ]
            )
            out += [world, np.nextafter(world, np.inf), np.nextafter(world, -np.inf)]
    xyz = np.concatenate([*out, rng.uniform(-3, 3, (200, 3))])
    xyz = np.concatenate([xyz, [[np.nan, 0, 0], [0, np.inf, 0], [0, 0, -np.inf]]])
    return np.column_stack([xyz, rng.random(len(xyz))])


@pytest.fixture(scope="module")
def adversarial():
    rng = np.random.default_rng(13)
    boxes = adversarial_boxes(rng)
    return adversarial_points(boxes, rng), boxes


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("margin", MARGINS)
def test_points_in_boxes_and_box_members_follow_the_naive_rule(adversarial, dtype, margin):
    points, boxes = adversarial
    points = points.astype(dtype)
    want = naive_mask(points, boxes, margin)
    assert want.sum() > 100 and (~want).sum() > 100
    np.testing.assert_array_equal(g.points_in_boxes(points, boxes, margin), want)
    point, box = g.box_members(points, boxes, margin)
    np.testing.assert_array_equal(point, np.nonzero(want)[0])  # by point, then box
    np.testing.assert_array_equal(box, np.nonzero(want)[1])
    for m, single in enumerate(boxes):
        rows = np.arange(len(points))[::-1]  # any order, kept
        np.testing.assert_array_equal(
            g.rows_in_box(points, rows, single, margin), rows[want[rows, m]]
        )


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_box_query_follows_the_naive_rule(adversarial, dtype):
    from drcpo.transforms.insertion import BoxQuery

    points, boxes = adversarial
    points = points.astype(dtype)
    query = BoxQuery(points)
    rng = np.random.default_rng(5)
    owner = rng.integers(-1, len(boxes), len(points))
    where = rng.random(len(points)) < 0.7
    for margin in MARGINS:
        want = naive_mask(points, boxes, margin)
        for m, box in enumerate(boxes):
            np.testing.assert_array_equal(query.inside(box, margin), np.flatnonzero(want[:, m]))
        np.testing.assert_array_equal(query.inside_any(boxes, margin), want.any(axis=1))
        np.testing.assert_array_equal(query.counts(boxes, margin), want.sum(axis=0))
        last = np.where(want.any(axis=1), len(boxes) - 1 - np.argmax(want[:, ::-1], axis=1), -1)
        np.testing.assert_array_equal(query.owners(boxes, margin), last)
    want = naive_mask(points, boxes, 0.0)
    own = [int((want[:, m] & (owner == m) & where).sum()) for m in range(len(boxes))]
    np.testing.assert_array_equal(query.own_counts(owner, boxes, where), own)


def test_placement_obstacle_counts_follow_the_naive_rule(adversarial):
    from drcpo.ground import GroundModel
    from drcpo.placement import _non_ground_counts

    points, boxes = adversarial
    finite = np.isfinite(points[:, :3]).all(axis=1)
    # A ground far below every point: no point is ground, each counts in each box holding it.
    ground = GroundModel.flat(-1e15)
    counts = _non_ground_counts(points[finite].astype(np.float32), boxes, ground, 0.0)
    want = naive_mask(points[finite].astype(np.float32), boxes, 0.0).sum(axis=0)
    np.testing.assert_array_equal(counts, want)


# --------------------------------------------------------------------------------------------
# The box-frame kernels against naive references: box_holding's extents, rotate_points_z
# --------------------------------------------------------------------------------------------
def naive_box_holding(box, points, pad):
    """box_holding spelled out in plain Python floats: each point in the box's frame (as
    naive_in_box computes it), the lowest and highest coordinate per axis; unchanged when
    those lie within the box, else every face moved out to the farthest point within ``pad``
    of it or beyond it, plus ``pad``, and the new centre taken back to the world frame."""
    cos, sin = float(np.cos(box[6:7])[0]), float(np.sin(box[6:7])[0])
    local = []
    for p in points:
        ox, oy = float(p[0]) - float(box[0]), float(p[1]) - float(box[1])
        local.append((ox * cos + oy * sin, -ox * sin + oy * cos, float(p[2]) - float(box[2])))
    half = [float(box[3 + a]) / 2.0 for a in range(3)]
    lowest = [min(q[a] for q in local) for a in range(3)]
    highest = [max(q[a] for q in local) for a in range(3)]
    if all(lowest[a] >= -half[a] and highest[a] <= half[a] for a in range(3)):
        return np.asarray(box, dtype=np.float64)
    low = [min(-half[a], lowest[a] - pad) for a in range(3)]
    high = [max(half[a], highest[a] + pad) for a in range(3)]
    shift = [(low[a] + high[a]) / 2.0 for a in range(3)]
    return np.array(
        [
            box[0] + (shift[0] * cos - shift[1] * sin),
            box[1] + (shift[0] * sin + shift[1] * cos),
            box[2] + shift[2],
            *(high[a] - low[a] for a in range(3)),
            box[6],
        ]
    )


def test_box_holding_follows_the_naive_extents(adversarial):
    points, boxes = adversarial
    points = points[np.isfinite(points[:, :3]).all(axis=1)]
    rng = np.random.default_rng(21)
    for dtype in (np.float64, np.float32):
        for box in boxes[:14]:  # near the origin and at 1e6 m: the extents are exact there
            for pad in (1e-4, 0.0, 0.5):
                # all the points (grows), its own face points (unchanged), one point, a few
                for chosen in (points, points[:40], points[rng.integers(0, len(points), 1)]):
                    chosen = chosen.astype(dtype)
                    np.testing.assert_array_equal(
                        g.box_holding(box, chosen, pad), naive_box_holding(box, chosen, pad)
                    )
        inside = g.from_canonical(rng.uniform(-0.5, 0.5, (50, 3)) * boxes[0, 3:6], boxes[0])
        np.testing.assert_array_equal(g.box_holding(boxes[0], inside.astype(dtype)), boxes[0])
    np.testing.assert_array_equal(g.box_holding(boxes[3], np.zeros((0, 3))), boxes[3])


def test_rotate_points_z_follows_the_naive_rotation():
    # Every row's x, y rotated in Python floats with numpy's cos and sin of the angle,
    # stored in the points' dtype; z and the features untouched.
    rng = np.random.default_rng(22)
    points = np.concatenate(
        [
            rng.normal(0, 30, (300, 5)),
            [[0.0, 0.0, 1.0, 2.0, 3.0], [1e12, -1e12, 0.0, 0.0, 0.0], [np.nan, 1.0, 0.0, 0, 0]],
            [[np.inf, 0.0, 0.0, 0.0, 0.0], [-0.0, 5e-324, 0.0, 0.0, 0.0]],
        ]
    )
    for angle in (0.0, np.pi, -np.pi / 2, 0.7, 1e-9, 40.0):
        cos, sin = float(np.cos(np.float64(angle))), float(np.sin(np.float64(angle)))
        for dtype in (np.float64, np.float32):
            cloud = points.astype(dtype)
            want = cloud.copy()
            for i, (x, y) in enumerate(cloud[:, :2].astype(np.float64).tolist()):
                want[i, 0], want[i, 1] = cos * x - sin * y, sin * x + cos * y
            got = g.rotate_points_z(cloud, angle)
            assert got.dtype == dtype
            np.testing.assert_array_equal(got, want)
            assert g.rotate_points_z(cloud[:0], angle).shape == (0, 5)
