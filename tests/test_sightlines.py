"""drcpo.occlusion.sightlines: which sight lines enter a box, against a naive segment clip in
each box's frame; and its use in the occlusion along rays (a surface element reaching past its
object's box hides nothing beside the box)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drcpo.errors import DataError
from drcpo.occlusion.sightlines import sight_lines_cross
from drcpo.sensor import Sensor
from drcpo.transforms.sensor_steps import sensor_occlusion


def naive_enters(point, origin, box, margin=0.0) -> bool:
    """Whether the segment origin -> point meets the box before the point: Liang-Barsky
    clipping of the segment, written out in the box's frame."""
    cos, sin = math.cos(box[6]), math.sin(box[6])

    def local(p):
        x, y, z = p[0] - box[0], p[1] - box[1], p[2] - box[2]
        return [x * cos + y * sin, -x * sin + y * cos, z]

    start, end = local(origin), local(point)
    low, high = 0.0, 1.0
    for axis in range(3):
        half = box[3 + axis] / 2.0 + margin
        step = end[axis] - start[axis]
        if step == 0.0:
            if abs(start[axis]) > half:
                return False
            continue
        t1, t2 = (-half - start[axis]) / step, (half - start[axis]) / step
        low, high = max(low, min(t1, t2)), min(high, max(t1, t2))
    return low <= high and low < 1.0


def random_scene(rng: np.random.Generator, points: int = 300, boxes: int = 6):
    xyz = rng.uniform([-30, -30, -2], [30, 30, 2], (points, 3))
    centres = rng.uniform([-20, -20, -1], [20, 20, 1], (boxes, 3))
    sizes = rng.uniform(0.5, 5.0, (boxes, 3))
    headings = rng.uniform(-math.pi, math.pi, (boxes, 1))
    return np.column_stack([xyz, rng.random(points)]), np.hstack([centres, sizes, headings])


@pytest.mark.parametrize("margin", [0.0, 0.3])
def test_sight_lines_match_the_naive_clip(margin: float) -> None:
    rng = np.random.default_rng(4)
    points, boxes = random_scene(rng)
    origin = np.array([0.3, -0.2, 1.7])
    own = rng.integers(-1, len(boxes), len(points))
    got = sight_lines_cross(points, origin, boxes, own, margin)
    expected = [
        any(naive_enters(p, origin, b, margin) for m, b in enumerate(boxes) if m != own[i])
        for i, p in enumerate(points)
    ]
    assert got.dtype == bool and 0 < got.sum() < len(points)
    np.testing.assert_array_equal(got, expected)


def test_the_prefilter_never_passes_over_a_box_the_segment_enters() -> None:
    """Boxes whose bounding circle holds the origin, points straight above it, and segments
    that end at or graze a box (tangent, corner, just short of its near face) against the
    naive clip: the cheap cone and distance tests only pass over boxes the clip misses."""
    origin = np.array([0.0, 0.0, 1.7])
    around = np.array([[0.5, 0.2, 0.0, 3.0, 2.0, 2.0, 0.4], [-1.0, 0.0, 0.0, 4.0, 4.0, 1.0, 0.0]])
    # a square turned 45 degrees: its corners touch its bounding circle's tangents and near side
    far = np.array(
        [[10.0, 0.0, 0.0, 2.0, 2.0, 4.0, math.pi / 4], [0.0, -8.0, 1.0, 1.0, 6.0, 2.0, 1.1]]
    )
    boxes = np.concatenate([around, far])
    rng = np.random.default_rng(8)
    corner = np.array([10.0, math.sqrt(2.0), 0.5])  # its corner on a tangent
    points = np.concatenate([
        np.array([[0.0, 0.0, 5.0], [0.0, 0.0, -3.0], corner, [8.6, 0.0, 0.5], [8.58, 0.0, 0.5]]),
        corner * np.array([[1.0, 1.0 - 1e-9, 1.0], [1.0, 1.0 + 1e-9, 1.0], [2.0, 2.0 - 1e-6, 1.0]]),
        np.column_stack([np.full(80, 20.0), np.linspace(-3.0, 3.0, 80), np.zeros(80)]),
        rng.uniform([-15, -15, -2], [15, 15, 4], (400, 3)),
    ])  # fmt: skip
    got = sight_lines_cross(points, origin, boxes)
    expected = [any(naive_enters(p, origin, b) for b in boxes) for p in points]
    assert 0 < got.sum() < len(points)
    np.testing.assert_array_equal(got, expected)


def test_a_point_in_front_of_or_inside_a_box() -> None:
    box = np.array([[10.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.3]])
    points = np.array([[5.0, 0.0, 0.0], [10.0, 0.0, 0.0], [15.0, 0.0, 0.0], [15.0, 5.0, 0.0]])
    got = sight_lines_cross(points, np.zeros(3), box)
    np.testing.assert_array_equal(got, [False, True, True, False])
    # its own box aside, nothing is entered
    assert not sight_lines_cross(points, np.zeros(3), box, np.zeros(4, dtype=np.int64)).any()
    assert sight_lines_cross(np.zeros((0, 4)), np.zeros(3), box).shape == (0,)


@pytest.mark.parametrize(
    ("points", "origin", "boxes", "own", "margin", "field"),
    [
        (np.zeros((3, 2)), np.zeros(3), np.zeros((1, 7)), None, 0.0, "points"),
        (np.full((1, 3), np.nan), np.zeros(3), np.zeros((1, 7)), None, 0.0, "NaN"),
        (np.zeros((1, 3)), np.zeros(2), np.zeros((1, 7)), None, 0.0, "origin"),
        (np.zeros((1, 3)), np.zeros(3), -np.ones((1, 7)), None, 0.0, "boxes"),
        (np.zeros((2, 3)), np.zeros(3), np.zeros((1, 7)), np.zeros(3), 0.0, "own"),
        (np.zeros((1, 3)), np.zeros(3), np.zeros((1, 7)), None, -1.0, "margin"),
    ],
)
def test_bad_input_names_the_field(points, origin, boxes, own, margin, field) -> None:
    with pytest.raises(DataError, match=field):
        sight_lines_cross(points, origin, boxes, own, margin)


def wide_sensor() -> Sensor:
    """8 beams 2 degrees apart, 1 degree columns, at the origin."""
    return Sensor(
        elevations=np.radians(np.linspace(4.0, -10.0, 8)),
        offsets=np.zeros(8),
        azimuth_step=math.radians(1.0),
        phase=0.0,
        mount=(0.0, 0.0, 0.0),
        range_noise=0.0,
        dropout=0.0,
    )


def on_ray(sensor: Sensor, beam: int, column: int, distance: float) -> np.ndarray:
    b, c = np.array([beam]), np.array([column])
    return (sensor.ray_origins(b) + distance * sensor.ray_directions(b, c))[0]


def box_on_arc(distance: float, first_deg: float, last_deg: float, depth: float) -> np.ndarray:
    """A box at ``distance`` spanning the azimuths ``first_deg`` to ``last_deg``, facing the
    origin, beam 3's height at 10 m in its middle, 1 m high."""
    middle = math.radians((first_deg + last_deg) / 2.0)
    half_width = distance * math.tan(math.radians((last_deg - first_deg) / 2.0))
    x, y = distance * math.cos(middle), distance * math.sin(middle)
    return np.array([x, y, -0.35 * distance / 10.0, depth, 2 * half_width, 1.0, middle])


def sparse_wall(sensor: Sensor) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """A sparse wall at 10 m (returns 3 columns apart: its elements, 15 cm across, reach past
    its last column), its box (ending 0.3 degree past it) and a point at 20 m 0.7 degree
    beside it, in the reach of its last column's elements but not behind the box."""
    wall = [on_ray(sensor, b, c, 10.0) for b in (2, 3, 4) for c in (30, 33, 36, 39)]
    turn = math.radians(0.7)  # column 39's ray turned about the z axis
    x, y, z = on_ray(sensor, 3, 39, 20.0)
    beside = np.array([x * math.cos(turn) - y * math.sin(turn),
                       x * math.sin(turn) + y * math.cos(turn), z])  # fmt: skip
    return wall, box_on_arc(10.0, 29.7, 39.3, 0.2), beside


def occlusion_keeps(points, owner, objects, sensor, boxes) -> np.ndarray:
    kept, _ = sensor_occlusion(
        np.column_stack([points, np.zeros(len(points))]).astype(np.float32),
        np.asarray(owner),
        np.full(int(np.count_nonzero(np.asarray(owner) < 0)), -1),
        sensor,
        lambda kept: np.zeros(objects, dtype=bool),
        lambda kept: np.zeros(0, dtype=np.int64),
        1,
        boxes=boxes,
    )
    return kept


def test_elements_past_the_box_hide_nothing_beside_it() -> None:
    """A frame point beside the sparse wall's box is hidden by an element without the boxes,
    kept with them; one straight behind the wall goes either way."""
    sensor = wide_sensor()
    wall, box, beside = sparse_wall(sensor)
    points = np.array([on_ray(sensor, 3, 33, 20.0), beside, *wall])
    owner = [-1, -1] + [0] * len(wall)
    without = occlusion_keeps(points, owner, 1, sensor, None)
    within = occlusion_keeps(points, owner, 1, sensor, box[None])
    assert not without[0] and not within[0]  # straight behind the wall
    assert not without[1]  # beside it: an element reaches it ...
    assert within[1]  # ... but past the box, which holds the wall
    assert within[2:].all() and without[2:].all()


def test_an_inserted_return_beside_a_box_stays_unless_its_cell_has_a_nearer_one() -> None:
    """Object 1's returns at 20 m: one beside the sparse wall's box (kept with the boxes, an
    element hides it without them), one in the cell of a frame point at 15 m (hidden either
    way: the cell rule, whatever the boxes)."""
    sensor = wide_sensor()
    wall, wall_box, beside = sparse_wall(sensor)
    points = np.array([on_ray(sensor, 3, 45, 15.0), *wall, beside, on_ray(sensor, 3, 45, 20.0)])
    owner = [-1] + [0] * len(wall) + [1, 1]
    boxes = np.stack([wall_box, box_on_arc(20.0, 39.0, 46.0, 0.4)])
    without = occlusion_keeps(points, owner, 2, sensor, None)
    within = occlusion_keeps(points, owner, 2, sensor, boxes)
    assert not without[-2] and within[-2]
    assert not without[-1] and not within[-1]
    assert without[:-2].all() and within[:-2].all()


def test_frame_cells_given_or_found_alike() -> None:
    """``frame_cells`` (the frame's cells found before) gives the verdicts found without it;
    cells of another frame are refused."""
    from drcpo.occlusion.render import point_cells

    sensor = wide_sensor()
    wall, box, beside = sparse_wall(sensor)
    points = np.array([on_ray(sensor, 3, 33, 20.0), beside, *wall])
    xyz = np.column_stack([points, np.zeros(len(points))]).astype(np.float32)
    owner = np.array([-1, -1] + [0] * len(wall))

    def keep(frame_cells):
        kept, _ = sensor_occlusion(
            xyz, owner, np.full(2, -1), sensor,
            lambda kept: np.zeros(1, dtype=bool), lambda kept: np.zeros(0, dtype=np.int64),
            1, fill_holes=True, boxes=box[None], frame_cells=frame_cells,
        )  # fmt: skip
        return kept

    np.testing.assert_array_equal(keep(point_cells(xyz[:2], sensor)), keep(None))
    with pytest.raises(DataError, match="frame_cells"):
        keep(point_cells(xyz[:3], sensor))
