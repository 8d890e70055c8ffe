"""drcpo.occlusion.rays: the range image, the visible-ray count of boxes and occlusion along
rays, each against a plain loop (Sensor.cells, a slab test, a loop over points and elements)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from drcpo.errors import ConfigError, DataError
from drcpo.occlusion.rays import PlacedView, RangeImage, RayOcclusion, ray_occlusion
from drcpo.occlusion.render import point_cells, render_object, surfel_radii
from drcpo.sensor import Sensor, sensor_preset

HDL64E = sensor_preset("hdl64e")


def small_sensor() -> Sensor:
    """8 beams, 1 degree columns, beam origins a few cm apart, mounted off the origin."""
    return Sensor(
        elevations=np.radians(np.linspace(4.0, -10.0, 8)),
        offsets=np.linspace(0.03, -0.03, 8),
        azimuth_step=math.radians(1.0),
        phase=math.radians(0.3),
        mount=(0.2, -0.1, 0.5),
        range_noise=0.0,
        dropout=0.0,
    )


def scene(rng: np.random.Generator, count: int, sensor: Sensor) -> np.ndarray:
    """Ground and scattered clutter around the sensor, ``(count, 4)``."""
    radius = np.sqrt(rng.uniform(4.0, 900.0, count))
    angle = rng.uniform(-math.pi, math.pi, count)
    z = np.where(rng.random(count) < 0.6, -1.7, rng.uniform(-1.7, 1.5, count))
    return np.column_stack(
        [radius * np.cos(angle), radius * np.sin(angle), z, rng.random(count)]
    ).astype(np.float32)


def reference_image(points: np.ndarray, sensor: Sensor) -> np.ndarray:
    ranges = np.full((sensor.num_beams, sensor.num_columns), np.inf)
    beam, column, _ = sensor.cells(points)
    for i in range(len(points)):
        if beam[i] < 0:
            continue
        origin = sensor.ray_origins(beam[i : i + 1])[0]
        distance = np.linalg.norm(points[i, :3].astype(np.float64) - origin)
        ranges[beam[i], column[i]] = min(ranges[beam[i], column[i]], distance)
    return ranges


def slab(origin, direction, box) -> tuple[float, float]:
    cos, sin = math.cos(box[6]), math.sin(box[6])
    rel = origin - box[:3]
    lo = np.array([cos * rel[0] + sin * rel[1], -sin * rel[0] + cos * rel[1], rel[2]])
    ld = np.array(
        [
            cos * direction[0] + sin * direction[1],
            -sin * direction[0] + cos * direction[1],
            direction[2],
        ]
    )
    enter, leave = 0.0, math.inf
    for axis in range(3):
        half = box[3 + axis] / 2
        if ld[axis] == 0:
            if abs(lo[axis]) > half:
                return 1.0, 0.0
            continue
        t1, t2 = (-half - lo[axis]) / ld[axis], (half - lo[axis]) / ld[axis]
        enter, leave = max(enter, min(t1, t2)), min(leave, max(t1, t2))
    return enter, leave


def reference_visible(image: RangeImage, boxes, occluders, tolerance) -> list[int]:
    sensor = image.sensor
    counts = []
    for box in boxes:
        count = 0
        for b in range(sensor.num_beams):
            origin = sensor.ray_origins(np.array([b]))[0]
            for c in range(sensor.num_columns):
                direction = sensor.ray_directions(np.array([b]), np.array([c]))[0]
                enter, leave = slab(origin, direction, box)
                if enter > leave or enter > sensor.max_range:
                    continue
                if image.ranges[b, c] < enter - tolerance:
                    continue
                blocked = False
                for other in occluders:
                    near, far = slab(origin, direction, other)
                    blocked |= near <= far and near < enter - tolerance
                count += not blocked
        counts.append(count)
    return counts


def reference_occlusion(points, owner, sensor, radii, tolerance) -> np.ndarray:
    """A loop over the points: own ray against every element of the other objects, own cell
    against every other point."""
    xyz = points[:, :3].astype(np.float64)
    beam, column, _ = sensor.cells(points)
    origin = np.where((beam >= 0)[:, None], sensor.ray_origins(np.maximum(beam, 0)), sensor.mount)
    distance = np.linalg.norm(xyz - origin, axis=1)
    removed = np.zeros(len(points), bool)
    inserted = np.flatnonzero(owner >= 0)
    for i in range(len(points)):
        if xyz[i, 0] == sensor.mount[0] and xyz[i, 1] == sensor.mount[1]:
            continue
        if owner[i] >= 0 and beam[i] >= 0:
            same = (beam == beam[i]) & (column == column[i]) & (owner != owner[i])
            if (distance[same] < distance[i] - tolerance).any():
                removed[i] = True
                continue
        u = (xyz[i] - origin[i]) / distance[i]
        for j in inserted:
            if owner[j] == owner[i]:
                continue
            v = xyz[j] - origin[i]
            t = v @ u
            if 0 < t < distance[i] - tolerance and v @ v - t * t <= radii[j] ** 2:
                removed[i] = True
                break
    return removed


# ----------------------------------------------------------------------------------------------
# RangeImage
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("sensor", [HDL64E, small_sensor()], ids=["hdl64e", "small"])
def test_range_image_matches_the_cells(sensor: Sensor) -> None:
    points = scene(np.random.default_rng(0), 20000, sensor)
    image = RangeImage.build(points, sensor)
    np.testing.assert_allclose(image.ranges, reference_image(points, sensor), rtol=1e-12)
    assert np.isfinite(image.ranges).sum() > 1000


@pytest.mark.parametrize("seed", range(3))
def test_visible_rays_match_the_slab_test(seed: int) -> None:
    rng = np.random.default_rng(seed)
    sensor = small_sensor()
    image = RangeImage.build(scene(rng, 3000, sensor), sensor)
    boxes = []
    for _ in range(4):
        angle, distance = rng.uniform(-math.pi, math.pi), rng.uniform(3, 20)
        boxes.append(
            [
                distance * math.cos(angle),
                distance * math.sin(angle),
                rng.uniform(-1, 0.5),
                rng.uniform(0.5, 4),
                rng.uniform(0.5, 2),
                rng.uniform(0.5, 2),
                rng.uniform(-math.pi, math.pi),
            ]
        )
    boxes.append([0.0, 0.0, 0.5, 3.0, 2.0, 1.0, 0.3])  # around the sensor
    boxes = np.array(boxes)
    occluders = boxes[:2] * np.array([0.6, 0.6, 1, 1, 1, 1, 1])  # nearer, in the same direction
    for occ in (None, occluders):
        got = image.visible_rays(boxes, occ, tolerance=0.1)
        expected = reference_visible(image, boxes, [] if occ is None else occ, 0.1)
        assert got.tolist() == expected
    assert image.visible_rays(boxes).sum() > image.visible_rays(boxes, occluders).sum()


def test_visible_rays_see_through_empty_space_only() -> None:
    """A box behind a wall gets no rays; the same box in front of it gets them all."""
    sensor = HDL64E
    y, z = np.meshgrid(np.linspace(-6, 6, 400), np.linspace(-1.7, 2.0, 120))
    wall = np.column_stack([np.full(y.size, 15.0), y.ravel(), z.ravel()])
    image = RangeImage.build(wall, sensor)
    behind = np.array([[20.0, 0.0, -0.9, 4.0, 1.8, 1.5, 0.0]])
    front = np.array([[10.0, 0.0, -0.9, 4.0, 1.8, 1.5, 0.0]])
    assert image.visible_rays(behind)[0] == 0
    empty = RangeImage.build(np.zeros((0, 4), np.float32), sensor)
    assert image.visible_rays(front)[0] == empty.visible_rays(front)[0] > 500
    tall = front + np.array([0, 0, 1.0, 0, 0, 2.0, 0])  # up to 1.1 m above the sensor
    assert empty.visible_rays(behind, occluders=tall)[0] == 0
    assert 0 < empty.visible_rays(behind, occluders=front)[0] < empty.visible_rays(behind)[0]


def reference_in_turn(image, boxes, need, placed, placed_need) -> list[bool]:
    """Box by box: hidden by the boxes accepted before it, or hiding one of them, each counted
    against all of them."""
    accepted, needs, hidden = list(placed), list(placed_need), []
    for box, n in zip(boxes, need, strict=True):
        occluders = np.array(accepted).reshape(-1, 7)
        seen = image.visible_rays(box[None], occluders if len(accepted) else None)[0]
        if seen < n:
            hidden.append(True)
            continue
        if accepted:
            left = image.visible_rays(occluders, np.concatenate([occluders, box[None]]))
            if (left < np.array(needs)).any():
                hidden.append(True)
                continue
        accepted.append(box)
        needs.append(n)
        hidden.append(False)
    return hidden


@pytest.mark.parametrize("seed", range(4))
def test_placed_view_matches_box_by_box(seed: int) -> None:
    """Boxes in rows along a few directions, some behind others, in two rounds as placement
    draws them: the first come is kept, as the plain count of every box against all the
    boxes accepted says; a view started from the placed boxes answers the same."""
    rng = np.random.default_rng(seed)
    sensor = small_sensor() if seed % 2 else HDL64E
    image = RangeImage.build(scene(rng, 3000, sensor), sensor)
    boxes = []
    for _ in range(14):
        angle = rng.choice([-2.0, 0.3, 0.35, 1.5]) + rng.normal(0, 0.05)
        distance = rng.uniform(3, 25)
        boxes.append(
            [
                distance * math.cos(angle),
                distance * math.sin(angle),
                rng.uniform(-1, 0.5),
                rng.uniform(0.5, 4),
                rng.uniform(0.5, 2),
                rng.uniform(0.5, 2),
                rng.uniform(-math.pi, math.pi),
            ]
        )
    boxes = np.array(boxes)
    crossing = RangeImage(sensor, np.full(image.ranges.shape, np.inf)).visible_rays(boxes)
    need = np.maximum(3, np.ceil(0.4 * crossing)).astype(np.int64)
    view = PlacedView(image, 3, 0.6)
    placed, placed_need = boxes[:0], need[:0]
    for part in (slice(0, 7), slice(7, None)):
        fresh = PlacedView(image, 3, 0.6, placed=placed)
        assert view.holds(placed[::-1]) and fresh.holds(placed)
        got = view.admit(boxes[part])
        expected = reference_in_turn(image, boxes[part], need[part], placed, placed_need)
        assert got.tolist() == expected
        assert fresh.admit(boxes[part]).tolist() == expected
        assert 0 < got.sum() < len(got)  # some hidden, some kept
        placed = np.concatenate([placed, boxes[part][~got]])
        placed_need = np.concatenate([placed_need, need[part][~got]])
        np.testing.assert_array_equal(view.boxes, placed)
        np.testing.assert_array_equal(view.need, placed_need)
        # each accepted box's rays left: its count against all the others
        np.testing.assert_array_equal(view.left, image.visible_rays(placed, placed))
    assert not view.holds(placed[1:])
    assert view.admit(boxes[:0]).shape == (0,)
    with pytest.raises(ConfigError, match="max_hidden"):
        PlacedView(image, 3, 1.5)
    with pytest.raises(ConfigError, match="min_rays"):
        PlacedView(image, 2.5, 0.5)


def test_placed_view_passes_over_a_group_once_one_is_taken() -> None:
    """Poses of one object (a group) are alternatives: the first accepted is taken, the
    group's later ones are neither rejected nor taken and hide nothing."""
    sensor = HDL64E
    image = RangeImage.build(np.zeros((0, 4), np.float32), sensor)
    near = [8.0, 0.0, -0.9, 4.0, 1.8, 1.5, 0.0]
    behind = [16.0, 0.0, -0.9, 4.0, 1.8, 1.5, 0.0]  # in the near box's shadow
    aside = [8.0, 6.0, -0.9, 4.0, 1.8, 1.5, 0.0]
    boxes = np.array([near, aside, behind])
    alone = PlacedView(image, 12, 0.7).admit(boxes)
    assert alone.tolist() == [False, False, True]  # the near box hides the one behind it
    view = PlacedView(image, 12, 0.7)
    got = view.admit(boxes, groups=np.array([0, 0, 1]))  # near and aside: one object's poses
    assert got.tolist() == [False, False, True]
    np.testing.assert_array_equal(view.boxes, boxes[:1])  # aside passed over, not taken
    view = PlacedView(image, 12, 0.7)
    got = view.admit(np.array([near, behind, aside]), groups=np.array([0, 1, 1]))
    assert got.tolist() == [False, True, False]  # behind hidden: its second pose is tried
    np.testing.assert_array_equal(view.boxes, np.array([near, aside]))
    # a box conflicting with one taken before (say their footprints overlap) is passed over
    view = PlacedView(image, 12, 0.7)
    conflicts = np.zeros((3, 3), bool)
    conflicts[1, 0] = conflicts[0, 1] = True
    assert view.admit(boxes, conflicts=conflicts).tolist() == [False, False, True]
    np.testing.assert_array_equal(view.boxes, boxes[:1])
    with pytest.raises(DataError, match="groups"):
        view.admit(boxes, groups=np.array([0, 1]))
    with pytest.raises(DataError, match="conflicts"):
        view.admit(boxes, conflicts=np.zeros((3, 2), bool))


# ----------------------------------------------------------------------------------------------
# ray_occlusion
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(3))
def test_ray_occlusion_matches_the_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    sensor = small_sensor()
    frame = scene(rng, 1500, sensor)
    parts, owners = [frame], [np.full(len(frame), -1)]
    for k in range(3):
        angle, distance = rng.uniform(-math.pi, math.pi), rng.uniform(4, 12)
        centre = (distance * math.cos(angle), distance * math.sin(angle), -0.9)
        local = rng.uniform(-0.5, 0.5, (300, 3)) * (3.0, 1.6, 1.4)
        parts.append(
            np.column_stack([local + np.array(centre), rng.random(300)]).astype(np.float32)
        )
        owners.append(np.full(300, k))
    points, owner = np.concatenate(parts), np.concatenate(owners)
    radii = rng.uniform(0.05, 0.3, len(points))
    removed = ray_occlusion(points, owner, sensor, radii=radii, tolerance=0.1)
    expected = reference_occlusion(points, owner, sensor, radii, 0.1)
    np.testing.assert_array_equal(removed, expected)
    assert removed[owner == -1].sum() > 10 and removed[owner >= 0].sum() > 10
    # radii given per inserted point only: the same
    again = ray_occlusion(points, owner, sensor, radii=radii[owner >= 0], tolerance=0.1)
    np.testing.assert_array_equal(again, removed)


def test_ray_occlusion_matches_the_reference_across_the_column_seam() -> None:
    """Objects whose elements reach past the last column into column 0 (straight ahead, the
    small sensor's seam at -0.2 degrees) and one all around the mount hide as the reference
    says."""
    rng = np.random.default_rng(7)
    sensor = small_sensor()
    frame = scene(rng, 1500, sensor)
    # the frame's points ahead: what the seam's objects may hide
    ahead = np.column_stack(
        [rng.uniform(12.0, 25.0, 400), rng.uniform(-1.5, 1.5, 400), rng.uniform(-1.7, 1.0, 400)]
    )
    parts = [frame, np.column_stack([ahead, rng.random(400)]).astype(np.float32)]
    owners = [np.full(len(frame) + 400, -1)]
    for k, (x, y, spread) in enumerate([(8.0, -0.03, 0.6), (5.0, 0.4, 1.2), (0.0, 0.0, 0.3)]):
        local = rng.uniform(-spread, spread, (300, 3)) * (1.0, 1.0, 0.8) + (x, y, -0.4)
        parts.append(np.column_stack([local, rng.random(300)]).astype(np.float32))
        owners.append(np.full(300, k))
    points, owner = np.concatenate(parts), np.concatenate(owners)
    radii = rng.uniform(0.05, 0.3, len(points))
    removed = ray_occlusion(points, owner, sensor, radii=radii, tolerance=0.1)
    np.testing.assert_array_equal(removed, reference_occlusion(points, owner, sensor, radii, 0.1))
    beam, column, _ = point_cells(points[owner == 0], sensor)
    assert {0, sensor.num_columns - 1} <= set(column[beam >= 0].tolist())
    assert removed[owner == -1].sum() > 20


@pytest.mark.parametrize("seed", range(3))
def test_without_objects_matches_the_reference_on_the_rest(seed: int) -> None:
    """RayOcclusion.without: the verdict of the points left once some objects are taken out
    equals the plain loop run on those points alone; the taken-out objects' points go."""
    rng = np.random.default_rng(10 + seed)
    sensor = small_sensor()
    frame = scene(rng, 1500, sensor)
    parts, owners = [frame], [np.full(len(frame), -1)]
    for k in range(4):
        # two pairs of objects in a row, so that taking the nearer out uncovers the farther
        if k % 2 == 0:
            angle, distance = rng.uniform(-math.pi, math.pi), rng.uniform(4, 12)
        else:
            distance += 5.0
        centre = (distance * math.cos(angle), distance * math.sin(angle), -0.9)
        local = rng.uniform(-0.5, 0.5, (250, 3)) * (3.0, 1.6, 1.4)
        parts.append(
            np.column_stack([local + np.array(centre), rng.random(250)]).astype(np.float32)
        )
        owners.append(np.full(250, k))
    points, owner = np.concatenate(parts), np.concatenate(owners)
    radii = rng.uniform(0.05, 0.3, len(points))
    rays = RayOcclusion(points, owner, sensor, radii=radii, tolerance=0.1)
    np.testing.assert_array_equal(
        rays.removed, reference_occlusion(points, owner, sensor, radii, 0.1)
    )
    for gone in ([0], [0, 2], [1, 3], np.array([True, False, False, True])):
        out = np.zeros(4, bool)
        out[gone] = True
        live = ~out[np.maximum(owner, 0)] | (owner < 0)
        expected = np.ones(len(points), bool)
        kept_owner = np.unique(owner[live], return_inverse=True)[1] - 1  # -1 stays first
        expected[live] = reference_occlusion(points[live], kept_owner, sensor, radii[live], 0.1)
        got = rays.without(np.asarray(gone))
        np.testing.assert_array_equal(got, expected)
        np.testing.assert_array_equal(
            got[live], ray_occlusion(points[live], kept_owner, sensor, radii[live], 0.1)
        )
        assert not (got & ~rays.removed & live).any()  # kept with them, kept without
    # what the nearer objects hid of the farther ones comes back
    assert (rays.removed[owner == 1] & ~rays.without([0])[owner == 1]).any()
    np.testing.assert_array_equal(rays.without([]), rays.removed)
    with pytest.raises(DataError, match="objects"):
        rays.without([4])
    with pytest.raises(DataError, match="objects"):
        rays.without(np.ones(3, bool))


def test_rendered_object_hides_what_is_behind_it() -> None:
    """A car rendered at 10 m in front of a wall: the wall behind it goes, the wall beside it
    stays, the car stays; behind the wall, the car would go."""
    sensor = dataclasses.replace(HDL64E, range_noise=0.0, dropout=0.0)
    rng = np.random.default_rng(1)
    y, z = np.meshgrid(np.linspace(-8, 8, 800), np.linspace(-1.7, 1.0, 150))
    wall = np.column_stack([np.full(y.size, 20.0), y.ravel(), z.ravel(), np.zeros(y.size)])
    local = rng.uniform(-0.5, 0.5, (4000, 3)) * (4.0, 1.8, 1.5)
    side = rng.integers(0, 3, 4000)
    local[np.arange(4000), side] = (
        np.sign(local[np.arange(4000), side]) * np.array([2.0, 0.9, 0.75])[side]
    )
    car_points = np.column_stack([local + np.array([10.0, 0.0, -0.98]), np.ones(4000)]).astype(
        np.float32
    )
    car, _ = render_object(car_points, sensor, rng)
    points = np.concatenate([wall.astype(np.float32), car])
    owner = np.concatenate([np.full(len(wall), -1), np.zeros(len(car), np.int64)])
    removed = ray_occlusion(points, owner, sensor)
    assert not removed[owner == 0].any()
    shadow = (np.abs(wall[:, 1]) < 0.8 * 2 * 0.9) & (wall[:, 2] < -0.4) & (wall[:, 2] > -1.6)
    shadow &= np.abs(wall[:, 1]) < 1.2
    assert removed[: len(wall)][shadow].mean() > 0.95
    assert not removed[: len(wall)][np.abs(wall[:, 1]) > 3.0].any()
    behind = car.copy()
    behind[:, 0] += 20.0  # now beyond the wall
    points = np.concatenate([wall.astype(np.float32), behind])
    removed = ray_occlusion(points, owner, sensor)
    assert removed[owner == 0].mean() > 0.9
    assert not removed[owner == -1].any()


def test_objects_hide_each_other() -> None:
    sensor = dataclasses.replace(HDL64E, range_noise=0.0, dropout=0.0)
    rng = np.random.default_rng(2)
    cube = rng.uniform(-0.5, 0.5, (3000, 3)) * 1.5
    near, _ = render_object(
        np.column_stack([cube + np.array([8.0, 0.0, -1.0]), np.ones(3000)]).astype(np.float32),
        sensor,
        rng,
    )
    far, _ = render_object(  # smaller, lower: within the near one's shadow
        np.column_stack([cube / 1.5 + np.array([16.0, 0.0, -1.2]), np.ones(3000)]).astype(
            np.float32
        ),
        sensor,
        rng,
    )
    points = np.concatenate([near, far])
    owner = np.concatenate([np.zeros(len(near), np.int64), np.ones(len(far), np.int64)])
    removed = ray_occlusion(points, owner, sensor, radii=np.full(len(points), 0.05))
    assert not removed[owner == 0].any()
    assert removed[owner == 1].mean() > 0.95
    assert surfel_radii(near).shape == (len(near),)


def test_default_radii_are_each_objects_own() -> None:
    """Without radii, each object's points get surfel_radii of that object alone, whatever
    the order of the points."""
    rng = np.random.default_rng(4)
    frame = scene(rng, 2000, HDL64E)
    objects = [
        rng.uniform(-0.5, 0.5, (n, 3)) * size + centre
        for n, size, centre in (
            (800, 1.5, (8.0, 2.0, -1.0)),
            (300, 0.6, (8.5, 2.5, -1.2)),
            (1500, 2.0, (12.0, 2.5, -0.8)),
        )
    ]
    points = np.concatenate([frame[:, :3], *objects]).astype(np.float32)
    owner = np.concatenate(
        [np.full(len(frame), -1), *(np.full(len(o), k) for k, o in enumerate(objects))]
    )
    shuffle = rng.permutation(len(points))
    points, owner = points[shuffle], owner[shuffle]
    radii = np.zeros(len(points))
    for k in range(len(objects)):
        radii[owner == k] = surfel_radii(points[owner == k])
    np.testing.assert_array_equal(
        ray_occlusion(points, owner, HDL64E), ray_occlusion(points, owner, HDL64E, radii=radii)
    )
    assert ray_occlusion(points, owner, HDL64E)[owner == 1].any()


def test_no_inserted_points_removes_nothing() -> None:
    points = scene(np.random.default_rng(0), 500, HDL64E)
    assert not ray_occlusion(points, np.full(500, -1), HDL64E).any()


def test_cells_given_or_found_alike() -> None:
    """``cells`` (the points' cells found before) gives the verdicts found without it, and
    is what the verdict uses (the distances halved, the frame's points come before the
    object's surface); a wrong length is refused."""
    rng = np.random.default_rng(21)
    sensor = small_sensor()
    frame = scene(rng, 1500, sensor)
    local = rng.uniform(-0.5, 0.5, (300, 3)) * (3.0, 1.6, 1.4) + (6.0, 1.0, -0.9)
    inserted = np.column_stack([local, rng.random(300)]).astype(np.float32)
    points = np.concatenate([frame, inserted])
    owner = np.concatenate([np.full(len(frame), -1), np.zeros(300, np.int64)])
    radii = rng.uniform(0.05, 0.3, len(points))
    found = RayOcclusion(points, owner, sensor, radii=radii)
    beam, column, distance = point_cells(points, sensor)
    given = RayOcclusion(points, owner, sensor, radii=radii, cells=(beam, column, distance))
    np.testing.assert_array_equal(given.removed, found.removed)
    assert found.removed[owner == -1].sum() > 10
    nearer = RayOcclusion(points, owner, sensor, radii=radii, cells=(beam, column, distance / 2))
    assert nearer.removed[owner == -1].sum() < found.removed[owner == -1].sum()
    with pytest.raises(DataError, match="cells' column"):
        RayOcclusion(points, owner, sensor, cells=(beam, column[:-1], distance))


# ----------------------------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------------------------
def test_bad_input() -> None:
    points = scene(np.random.default_rng(0), 50, HDL64E)
    owner = np.full(50, -1)
    owner[:10] = 0
    with pytest.raises(DataError, match="shape"):
        RangeImage.build(points[:, :2], HDL64E)
    with pytest.raises(DataError, match="shape"):
        ray_occlusion(points, owner[:5], HDL64E)
    with pytest.raises(DataError, match="-1"):
        ray_occlusion(points, np.full(50, -2), HDL64E)
    with pytest.raises(DataError, match="integers"):
        ray_occlusion(points, owner.astype(float), HDL64E)
    with pytest.raises(DataError, match="radii"):
        ray_occlusion(points, owner, HDL64E, radii=np.ones(7))
    for row in (3, 20):  # an inserted point, an original one
        bad = points.copy()
        bad[row, 2] = np.nan
        with pytest.raises(DataError, match=f"row {row}"):
            ray_occlusion(bad, owner, HDL64E)
        with pytest.raises(DataError, match=f"row {row}"):
            RangeImage.build(bad, HDL64E)
    image = RangeImage.build(points, HDL64E)
    with pytest.raises(DataError, match="boxes"):
        image.visible_rays(np.zeros((2, 6)))
    with pytest.raises(DataError, match="occluders"):
        image.visible_rays(np.ones((1, 7)), occluders=np.full((1, 7), np.nan))
    with pytest.raises(DataError, match="positive"):
        image.visible_rays(np.array([[5, 0, 0, 1, -1, 1, 0.0]]))
    with pytest.raises(ConfigError, match="tolerance"):
        image.visible_rays(np.ones((1, 7)), tolerance=-1.0)
    assert image.visible_rays(np.zeros((0, 7))).shape == (0,)


@pytest.mark.parametrize("seed", range(2))
def test_with_boxes_paints_each_rays_entry(seed: int) -> None:
    """:meth:`RangeImage.with_boxes`: every cell keeps the nearest of its return and the
    entries of its ray into the boxes (the slab test, ray by ray)."""
    rng = np.random.default_rng(seed)
    sensor = small_sensor()
    image = RangeImage.build(scene(rng, 3000, sensor), sensor)
    boxes = [[0.0, 0.0, 0.5, 3.0, 2.0, 1.0, 0.3]]  # around the sensor
    for _ in range(4):
        angle, distance = rng.uniform(-math.pi, math.pi), rng.uniform(3, 20)
        sizes = [rng.uniform(0.5, 4), rng.uniform(0.5, 2), rng.uniform(0.5, 2)]
        x, y = distance * math.cos(angle), distance * math.sin(angle)
        boxes.append([x, y, rng.uniform(-1, 0.5), *sizes, rng.uniform(-math.pi, math.pi)])
    boxes = np.array(boxes)
    expected = np.array(image.ranges)
    for b in range(sensor.num_beams):
        origin = sensor.ray_origins(np.array([b]))[0]
        for c in range(sensor.num_columns):
            direction = sensor.ray_directions(np.array([b]), np.array([c]))[0]
            for box in boxes:
                enter, leave = slab(origin, direction, box)
                if enter <= leave:
                    expected[b, c] = min(expected[b, c], enter)
    painted = image.with_boxes(boxes)
    np.testing.assert_allclose(painted.ranges, expected, rtol=1e-9, atol=1e-9)
    assert (painted.ranges < image.ranges).sum() > 100
    assert image.with_boxes(np.zeros((0, 7))) is image
