"""drcpo.occlusion.silhouettes: the holes in inserted objects' rows and columns of returns,
against plain loops over objects, beams and columns; and ``external_occlusion.fill_holes`` in
the occlusion along rays (a point behind a hole of a solid object goes; the outline does not
grow)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drcpo.errors import DataError
from drcpo.occlusion.render import point_cells
from drcpo.occlusion.silhouettes import _line_gaps, silhouette_gaps
from drcpo.sensor import Sensor
from drcpo.transforms.sensor_steps import sensor_occlusion, with_silhouette_gaps


def small_sensor(phase_deg: float = 0.3) -> Sensor:
    """8 beams 2 degrees apart, 1 degree columns, beam origins a few cm apart."""
    return Sensor(
        elevations=np.radians(np.linspace(4.0, -10.0, 8)),
        offsets=np.linspace(0.03, -0.03, 8),
        azimuth_step=math.radians(1.0),
        phase=math.radians(phase_deg),
        mount=(0.2, -0.1, 0.5),
        range_noise=0.0,
        dropout=0.0,
    )


def on_ray(sensor: Sensor, beam: int, column: int, distance: float) -> np.ndarray:
    """The point of cell (beam, column) at ``distance`` from the beam's origin."""
    b, c = np.array([beam]), np.array([column])
    return (sensor.ray_origins(b) + distance * sensor.ray_directions(b, c))[0]


def reference_gaps(points: np.ndarray, owner: np.ndarray, sensor: Sensor) -> dict:
    """(object, beam, column) -> rounded x, y, z of every gap, by loops over objects, beams
    and columns (a cell both a row's and a column's gap: the row's)."""
    beam, column, _ = sensor.cells(points)
    columns = sensor.num_columns
    found: dict = {}
    distance = np.full(len(points), np.nan)
    inside = beam >= 0
    distance[inside] = np.linalg.norm(
        points[inside, :3].astype(np.float64) - sensor.ray_origins(beam[inside]), axis=1
    )
    column_gaps = {}
    for k in np.unique(owner[owner >= 0]):
        for b in np.unique(beam[(owner == k) & inside]):
            mine = (owner == k) & (beam == b)
            held = set(column[mine].tolist())
            mean = distance[mine].mean()
            # the shortest arc holding every column: the complement of the widest empty arc
            ordered = sorted(held)
            gaps = [(ordered[(i + 1) % len(ordered)] - c) % columns for i, c in enumerate(ordered)]
            if len(ordered) == 1:
                span = ordered
            else:
                widest = int(np.argmax(gaps))
                start = ordered[(widest + 1) % len(ordered)]
                length = (ordered[widest] - start) % columns + 1
                span = [(start + s) % columns for s in range(length)]
            for c in span:
                if c not in held:
                    found[(int(k), int(b), c)] = np.round(on_ray(sensor, int(b), c, mean), 6)
        for c in np.unique(column[(owner == k) & inside]):
            mine = (owner == k) & (column == c) & inside
            held = set(beam[mine].tolist())
            mean = distance[mine].mean()
            for b in range(min(held), max(held) + 1):
                if b not in held:
                    column_gaps[(int(k), b, int(c))] = np.round(on_ray(sensor, b, int(c), mean), 6)
    for key, xyz in column_gaps.items():
        found.setdefault(key, xyz)
    return {key: tuple(xyz.tolist()) for key, xyz in found.items()}


def as_dict(points: np.ndarray, owner: np.ndarray, sensor: Sensor) -> dict:
    beam, column, _ = sensor.cells(points)
    keys = [(int(k), int(b), int(c)) for k, b, c in zip(owner, beam, column, strict=True)]
    assert len(set(keys)) == len(keys)  # each cell once
    return {key: tuple(np.round(p, 6).tolist()) for key, p in zip(keys, points, strict=True)}


def test_silhouette_gaps_match_a_loop_over_objects_beams_and_columns() -> None:
    sensor = small_sensor()
    rng = np.random.default_rng(3)
    points, owner = [], []
    for k, (centre, spread) in enumerate([(20, 6), (-60, 5), (0, 4)]):  # the last across column 0
        for _ in range(40):
            b, c = int(rng.integers(0, 8)), int(centre + rng.integers(-spread, spread + 1))
            points.append(on_ray(sensor, b, c % sensor.num_columns, rng.uniform(8.0, 12.0)))
            owner.append(k)
    frame = np.column_stack([rng.uniform(-30, 30, (50, 2)), np.full(50, -1.2)])
    points = np.concatenate([frame, np.array(points)])
    owner = np.concatenate([np.full(50, -1), owner])
    gaps, gap_owner = silhouette_gaps(points, owner, sensor)
    expected = reference_gaps(points, owner, sensor)
    assert len(gaps) == len(expected) > 10
    got = as_dict(gaps, gap_owner, sensor)
    assert got.keys() == expected.keys()
    for key, xyz in expected.items():
        np.testing.assert_allclose(got[key], xyz, atol=2e-6)
    # the cells given instead of found: the same gaps, bit for bit
    again, again_owner = silhouette_gaps(points, owner, sensor, point_cells(points, sensor))
    np.testing.assert_array_equal(again, gaps)
    np.testing.assert_array_equal(again_owner, gap_owner)
    with pytest.raises(DataError, match="cells"):
        silhouette_gaps(points, owner, sensor, tuple(a[1:] for a in point_cells(points, sensor)))


def test_no_inserted_points_no_gaps() -> None:
    gaps, gap_owner = silhouette_gaps(np.zeros((5, 4)) + 3.0, np.full(5, -1), small_sensor())
    assert gaps.shape == (0, 3) and gap_owner.shape == (0,)


def holed_wall(sensor: Sensor) -> tuple[np.ndarray, np.ndarray]:
    """A frame point at 20 m on cell (3, 40) and another on (3, 50); an inserted wall at 10 m
    on beams 2-4, columns 36-44, without a return in cell (3, 40): a hole."""
    wall = [
        on_ray(sensor, b, c, 10.0) for b in (2, 3, 4) for c in range(36, 45) if (b, c) != (3, 40)
    ]
    frame = [on_ray(sensor, 3, 40, 20.0), on_ray(sensor, 3, 50, 20.0)]
    points = np.column_stack([np.array(frame + wall), np.zeros(len(frame) + len(wall))])
    owner = np.concatenate([np.full(2, -1), np.zeros(len(wall), dtype=np.int64)])
    return points.astype(np.float32), owner


@pytest.mark.parametrize("fill", [False, True])
def test_fill_holes_hides_the_point_behind_a_hole_and_nothing_beside(fill: bool) -> None:
    sensor = small_sensor()
    points, owner = holed_wall(sensor)
    keep, dropped = sensor_occlusion(
        points,
        owner,
        np.full(2, -1),
        sensor,
        lambda kept: np.zeros(1, dtype=bool),
        lambda kept: np.zeros(0, dtype=np.int64),
        1,
        fill_holes=fill,
    )
    assert keep.shape == (len(points),) and not dropped.any()
    assert keep[0] == (not fill)  # behind the hole: seen through it only without the fill
    assert keep[1]  # beside the wall: never hidden
    assert keep[2:].all()  # the wall's own returns


def test_with_silhouette_gaps_appends_gaps_that_are_never_returns() -> None:
    sensor = small_sensor()
    points, owner = holed_wall(sensor)
    filled, filled_owner, radii = with_silhouette_gaps(points, owner, sensor)
    assert len(filled) == len(points) + 1 and filled.dtype == points.dtype
    np.testing.assert_array_equal(filled[: len(points)], points)
    np.testing.assert_allclose(filled[-1, :3], on_ray(sensor, 3, 40, 10.0), atol=1e-5)
    assert filled_owner[-1] == 0 and filled[-1, 3] == 0.0
    # the gap's element: half an azimuth step across at its distance
    reach = np.linalg.norm(filled[-1, :3] - np.asarray(sensor.mount))
    assert radii[-1] == pytest.approx(reach * sensor.azimuth_step / 2, rel=1e-5)
    assert len(radii) == int((filled_owner >= 0).sum())


@pytest.mark.parametrize("seed", range(6))
def test_line_gaps_match_the_vectorised_reference(seed: int) -> None:
    """One pass over the sorted cells gives the lines' gaps, positions and means the
    vectorised rule gives, bit for bit: repeated cells, lines of one cell, ties between the
    widest empty arcs, arcs that wrap around the circle."""
    rng = np.random.default_rng(seed)
    period = int(rng.choice([8, 40, 2000]))
    count = int(rng.integers(1, 400))
    line = rng.integers(0, 12, count)
    position = rng.integers(0, period, count)
    position[: count // 3] = rng.integers(0, 3, count // 3)  # crowded: repeats and ties
    distance = rng.uniform(1.0, 60.0, count)
    got = _line_gaps(line, position, period, distance)
    want = reference_line_gaps(line, position, period, distance)
    for mine, theirs in zip(got, want, strict=True):
        np.testing.assert_array_equal(mine, theirs)
    assert len(got[0]) > 0


def test_line_gaps_of_one_line_leave_the_widest_arc_outside() -> None:
    # held 0, 1, 4 and 9 of 12: empty arcs 2-3 (2), 5-8 (4) and 10-11 (2): the widest,
    # 5-8, is outside; 2, 3, 10 and 11 are gaps, at the line's mean distance
    line, position, mean = _line_gaps(
        np.zeros(5, np.int64), np.array([9, 0, 4, 1, 4]), 12, np.array([1.0, 2, 3, 4, 5])
    )
    np.testing.assert_array_equal(position, [10, 11, 2, 3])
    np.testing.assert_array_equal(line, [0, 0, 0, 0])
    np.testing.assert_array_equal(mean, [3.0] * 4)


def reference_line_gaps(
    line: np.ndarray, position: np.ndarray, period: int, distance: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The vectorised rule the kernel replaced (argsort, bincount, reduceat): of the cells
    ``(line, position)`` on a circle of ``period``, every empty arc between two held positions
    of a line but the widest; each gap's line, position and its line's mean ``distance``."""
    code = line * period + position
    order = np.argsort(code, kind="stable")
    code, distance = code[order], distance[order]
    line = code // period
    index = np.cumsum(np.r_[True, line[1:] != line[:-1]]) - 1
    mean = np.bincount(index, distance) / np.bincount(index)
    new_cell = np.r_[True, code[1:] != code[:-1]]
    held_line, held = index[new_cell], code[new_cell] % period
    first = np.flatnonzero(np.r_[True, held_line[1:] != held_line[:-1]])
    last = np.r_[first[1:] - 1, len(held_line) - 1]
    empty_before = np.empty(len(held_line), dtype=np.int64)
    empty_before[1:] = held[1:] - held[:-1] - 1
    empty_before[first] = held[first] + period - held[last] - 1
    # the widest empty arc of each line (its first, on a tie) lies outside the object
    widest = np.maximum.reduceat(empty_before, first)
    candidates = np.flatnonzero(empty_before == widest[held_line])
    outside = candidates[np.r_[True, held_line[candidates][1:] != held_line[candidates][:-1]]]
    empty_before[outside] = 0
    cell_of = np.repeat(np.arange(len(held_line)), empty_before)
    step = np.arange(len(cell_of)) - np.repeat(np.cumsum(empty_before) - empty_before, empty_before)
    gap_position = (held[cell_of] - empty_before[cell_of] + step) % period
    gap_line = held_line[cell_of]
    return line[new_cell][cell_of], gap_position, mean[gap_line]
