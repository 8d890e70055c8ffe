"""drcpo.occlusion.render: objects rendered through the sensor (surface elements, first hits,
range noise, dropout) against a plain loop over rays and points, and the render's physics:
scan lines, self-occlusion, density falling with distance, box silhouettes close to the truth."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from drcpo.errors import DataError
from drcpo.occlusion.render import (
    RADIUS_RANGE,
    radius_cap,
    render_object,
    surfel_radii,
)
from drcpo.sensor import Sensor, sensor_preset

EXACT = dataclasses.replace(sensor_preset("hdl64e"), range_noise=0.0, dropout=0.0)


def small_sensor(**changes: object) -> Sensor:
    """8 beams, 1 degree columns, beam origins a few cm apart, mounted off the origin."""
    fields = dict(
        elevations=np.radians(np.linspace(4.0, -10.0, 8)),
        offsets=np.linspace(0.03, -0.03, 8),
        azimuth_step=math.radians(1.0),
        phase=math.radians(0.3),
        mount=(0.2, -0.1, 0.5),
        range_noise=0.0,
        dropout=0.0,
    )
    fields.update(changes)
    return Sensor(**fields)


def box_surface(rng: np.random.Generator, count: int, centre, dims, yaw: float) -> np.ndarray:
    """``(count, 4)`` points uniform on a box's six faces (x, y, z, face index)."""
    dims = np.asarray(dims, dtype=np.float64)
    areas = np.array([dims[1] * dims[2], dims[0] * dims[2], dims[0] * dims[1]])
    axis = rng.choice(3, count, p=areas / areas.sum())
    sign = rng.choice([-1.0, 1.0], count)
    local = rng.uniform(-0.5, 0.5, (count, 3)) * dims
    local[np.arange(count), axis] = sign * dims[axis] / 2.0
    cos, sin = math.cos(yaw), math.sin(yaw)
    world = np.column_stack(
        [cos * local[:, 0] - sin * local[:, 1], sin * local[:, 0] + cos * local[:, 1], local[:, 2]]
    )
    face = axis * 2 + (sign > 0)
    return np.column_stack([world + np.asarray(centre), face]).astype(np.float32)


def box_grid(rng: np.random.Generator, spacing: float, centre, dims, yaw: float) -> np.ndarray:
    """``(n, 4)`` points on a box's six faces on a jittered grid of ``spacing`` metres (x, y,
    z, face index), each moved by up to a tenth of the spacing: a densely sampled surface."""
    dims = np.asarray(dims, dtype=np.float64)
    faces = []
    for axis in range(3):
        u, v = (a for a in range(3) if a != axis)
        nu, nv = math.ceil(dims[u] / spacing), math.ceil(dims[v] / spacing)
        grid_u, grid_v = np.meshgrid(
            (np.arange(nu) + 0.5) / nu - 0.5, (np.arange(nv) + 0.5) / nv - 0.5
        )
        grid_u, grid_v = grid_u.ravel(), grid_v.ravel()
        for sign in (-1.0, 1.0):
            local = np.zeros((len(grid_u), 4))
            local[:, u] = (grid_u + rng.uniform(-0.1, 0.1, len(grid_u)) / nu) * dims[u]
            local[:, v] = (grid_v + rng.uniform(-0.1, 0.1, len(grid_u)) / nv) * dims[v]
            local[:, axis] = sign * dims[axis] / 2.0
            local[:, 3] = axis * 2 + (sign > 0)
            faces.append(local)
    local = np.concatenate(faces)
    cos, sin = math.cos(yaw), math.sin(yaw)
    world = np.column_stack(
        [cos * local[:, 0] - sin * local[:, 1], sin * local[:, 0] + cos * local[:, 1], local[:, 2]]
    )
    return np.column_stack([world + np.asarray(centre), local[:, 3]]).astype(np.float32)


def all_rays(sensor: Sensor) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    beam, column = np.meshgrid(
        np.arange(sensor.num_beams), np.arange(sensor.num_columns), indexing="ij"
    )
    beam, column = beam.ravel(), column.ravel()
    return beam, column, sensor.ray_origins(beam), sensor.ray_directions(beam, column)


def reference_render(points: np.ndarray, radii: np.ndarray, sensor: Sensor) -> dict:
    """{(beam, column): (depth, source)}: for every ray, the nearest point within its radius
    of the ray (in front of the origin), by a loop over rays and points."""
    xyz = points[:, :3].astype(np.float64)
    hits = {}
    for b, c, origin, direction in zip(*all_rays(sensor), strict=True):
        best = (math.inf, -1)
        for i in range(len(xyz)):
            v = xyz[i] - origin
            t = float(v @ direction)
            if t > 0 and float(v @ v) - t * t <= radii[i] ** 2 and t < best[0]:
                best = (t, i)
        if best[1] >= 0:
            hits[(int(b), int(c))] = best
    return hits


def slab_hits(sensor: Sensor, centre, dims, yaw: float) -> set[tuple[int, int]]:
    """The rays that cross a box, by the slab test."""
    beam, column, origin, direction = all_rays(sensor)
    cos, sin = math.cos(yaw), math.sin(yaw)
    rel = origin - np.asarray(centre)
    lo = np.column_stack([cos * rel[:, 0] + sin * rel[:, 1], -sin * rel[:, 0] + cos * rel[:, 1]])
    ld = np.column_stack(
        [
            cos * direction[:, 0] + sin * direction[:, 1],
            -sin * direction[:, 0] + cos * direction[:, 1],
        ]
    )
    lo, ld = np.column_stack([lo, rel[:, 2]]), np.column_stack([ld, direction[:, 2]])
    half = np.asarray(dims) / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - lo) / ld, (half - lo) / ld
    enter = np.nanmax(np.minimum(t1, t2), axis=1)
    leave = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (enter <= leave) & (leave > 0)
    return set(zip(beam[hit].tolist(), column[hit].tolist(), strict=True))


def cells_of(sensor: Sensor, returns: np.ndarray) -> list[tuple[int, int]]:
    beam, column, _ = sensor.cells(returns)
    return list(zip(beam.tolist(), column.tolist(), strict=True))


# ----------------------------------------------------------------------------------------------
# Against the plain loop
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(4))
def test_render_matches_the_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    sensor = small_sensor()
    angle = rng.uniform(-math.pi, math.pi)  # any azimuth, the seam at +-pi included
    centre = (6 * math.cos(angle), 6 * math.sin(angle), 0.0)
    points = box_surface(rng, 60, centre, (1.5, 1.0, 1.2), rng.uniform(0, math.pi))
    radii = rng.uniform(0.05, 0.3, len(points))
    returns, source = render_object(points, sensor, rng, radii)
    expected = reference_render(points, radii, sensor)
    assert len(expected) > 10
    got = dict(zip(cells_of(sensor, returns), source.tolist(), strict=True))
    assert got == {cell: i for cell, (_, i) in expected.items()}
    for row, cell in zip(returns, cells_of(sensor, returns), strict=True):
        origin = sensor.ray_origins(np.array([cell[0]]))[0]
        depth = np.linalg.norm(row[:3].astype(np.float64) - origin)
        assert depth == pytest.approx(expected[cell][0], abs=1e-4)
    np.testing.assert_array_equal(returns[:, 3], points[source, 3])  # features of the hit


def test_render_across_column_zero() -> None:
    """Points straight ahead of the sensor whose ray windows start before column 0, at
    different negative columns: every window still lands in one frame of columns (the first
    negative start once counted as unset, and a later point moved the frame from under the
    earlier points' windows: their hits went to other columns, or past the rays' end)."""
    sensor = small_sensor(phase=0.0)
    points = np.array(
        [[8.0, 0.0, 0.2, 1.0], [8.0, 0.05, -0.2, 2.0], [8.0, 0.9, 0.0, 3.0]],
        dtype=np.float32,
    )
    radii = np.array([0.3, 0.1, 0.2])  # windows starting at columns -2, -1 and 4
    returns, source = render_object(points, sensor, np.random.default_rng(0), radii)
    expected = reference_render(points, radii, sensor)
    assert len(expected) >= 3
    got = dict(zip(cells_of(sensor, returns), source.tolist(), strict=True))
    assert got == {cell: i for cell, (_, i) in expected.items()}


def test_render_around_the_sensor_and_wide_elements() -> None:
    """Points all around the sensor (the window spans every column) and elements larger than
    a column's width."""
    rng = np.random.default_rng(7)
    sensor = small_sensor()
    angle = rng.uniform(-math.pi, math.pi, 40)
    points = np.column_stack(
        [3 * np.cos(angle), 3 * np.sin(angle), rng.uniform(-0.5, 0.8, 40), np.arange(40)]
    ).astype(np.float32)
    radii = rng.uniform(0.02, 0.4, 40)
    returns, source = render_object(points, sensor, rng, radii)
    expected = reference_render(points, radii, sensor)
    got = dict(zip(cells_of(sensor, returns), source.tolist(), strict=True))
    assert got == {cell: i for cell, (_, i) in expected.items()}


def test_returns_lie_on_their_rays() -> None:
    rng = np.random.default_rng(3)
    sensor = dataclasses.replace(EXACT, offsets=np.linspace(0.05, -0.05, 64), mount=(0.1, 0, 0.2))
    points = box_surface(rng, 3000, (12.0, -4.0, -0.9), (4.0, 1.7, 1.5), 0.7)
    returns, _ = render_object(points, sensor, rng)
    beam, column, _ = sensor.cells(returns)
    assert (beam >= 0).all()
    assert len(set(zip(beam.tolist(), column.tolist(), strict=True))) == len(returns)
    origin = sensor.ray_origins(beam)
    offset = returns[:, :3].astype(np.float64) - origin
    direction = sensor.ray_directions(beam, column)
    along = np.einsum("ij,ij->i", offset, direction)
    off_ray = np.linalg.norm(offset - along[:, None] * direction, axis=1)
    assert off_ray.max() < 1e-5 * along.max()  # float32 rounding only


# ----------------------------------------------------------------------------------------------
# Noise, dropout, determinism
# ----------------------------------------------------------------------------------------------
def test_same_seed_same_output_and_noise_statistics() -> None:
    sensor = dataclasses.replace(EXACT, range_noise=0.05, dropout=0.2)
    points = box_surface(np.random.default_rng(0), 4000, (8.0, 2.0, -0.9), (4, 1.7, 1.5), 0.2)
    radii = surfel_radii(points)
    first = render_object(points, sensor, np.random.default_rng(11), radii)
    again = render_object(points, sensor, np.random.default_rng(11), radii)
    other = render_object(points, sensor, np.random.default_rng(12), radii)
    np.testing.assert_array_equal(first[0], again[0])
    np.testing.assert_array_equal(first[1], again[1])
    assert not np.array_equal(first[0], other[0])
    exact, _ = render_object(points, EXACT, np.random.default_rng(11), radii)
    # dropout: about 20 % of the returns lost
    assert len(first[0]) / len(exact) == pytest.approx(0.8, abs=0.03)
    # noise: along the ray, N(0, 0.05)
    cells = {cell: row for cell, row in zip(cells_of(EXACT, exact), exact, strict=True)}
    noisy = dict(zip(cells_of(sensor, first[0]), first[0], strict=True))
    assert set(noisy) <= set(cells)
    error = [np.linalg.norm(noisy[c][:3]) - np.linalg.norm(cells[c][:3]) for c in noisy]
    assert np.mean(error) == pytest.approx(0.0, abs=0.005)
    assert np.std(error) == pytest.approx(0.05, rel=0.1)


def test_returns_out_of_range_are_lost() -> None:
    sensor = dataclasses.replace(EXACT, min_range=9.0, max_range=10.5)
    points = box_surface(np.random.default_rng(1), 3000, (10.0, 0.0, -0.5), (3, 3, 1.0), 0.0)
    returns, _ = render_object(points, sensor, np.random.default_rng(0))
    distance = np.linalg.norm(returns[:, :3], axis=1)
    assert len(returns) > 100
    assert distance.min() >= 9.0 - 1e-4 and distance.max() <= 10.5 + 1e-4
    full, _ = render_object(points, EXACT, np.random.default_rng(0))
    assert len(full) > len(returns)


# ----------------------------------------------------------------------------------------------
# Physics
# ----------------------------------------------------------------------------------------------
def test_back_faces_give_no_returns() -> None:
    """A densely sampled box seen from the front: no return comes from the faces turned away
    from the sensor, but for elements within two radii of an edge they share with a visible
    face (those stick out past it)."""
    rng = np.random.default_rng(5)
    dims, centre = np.array([4.0, 1.8, 1.5]), np.array([10.0, 0.0, -0.98])
    points = box_grid(rng, 0.05, centre, dims, 0.0)
    _, source = render_object(points, EXACT, rng)
    face = points[source, 3].astype(int)
    # faces 2 * axis + (sign > 0): the sensor sees the near end (-x) and the top (+z)
    assert np.isin(face, [0, 5]).mean() > 0.9
    local = points[source, :3] - centre
    margin = 2 * surfel_radii(points).max()
    back = np.isin(face, [1, 4])  # the far end and the bottom
    inner = (np.abs(local[:, 1]) < dims[1] / 2 - margin) & (local[:, 2] < dims[2] / 2 - margin)
    assert back.sum() > 0  # the far end's rim shows above the top
    assert not (back & inner & (face == 1)).any()
    # the bottom: near the edges it shares with the sides and the near end, the neighbouring
    # faces' points make the radii smaller, so a ray rarely slips through
    assert (face == 4).sum() <= 0.005 * len(face)


@pytest.mark.parametrize("distance", [10.0, 40.0])
def test_dense_box_gives_the_true_ray_count(distance: float) -> None:
    """The choice of the radii: a densely sampled box gives nearly the rays that truly hit it
    (no holes between the points, the silhouette grown little)."""
    rng = np.random.default_rng(int(distance))
    dims, yaw = (4.0, 1.7, 1.5), 0.4
    centre = (distance * math.cos(0.3), distance * math.sin(0.3), -0.98)
    points = box_grid(rng, 0.05, centre, dims, yaw)
    returns, _ = render_object(points, EXACT, rng)
    truth = slab_hits(EXACT, centre, dims, yaw)
    got = set(cells_of(EXACT, returns))
    assert len(got) == len(returns)
    assert len(truth - got) <= 0.02 * len(truth)  # holes
    assert len(got - truth) <= 0.15 * len(truth)  # silhouette growth
    assert len(returns) / len(truth) == pytest.approx(1.0, abs=0.15)


def test_density_falls_as_the_inverse_square_of_distance() -> None:
    rng = np.random.default_rng(9)
    counts = []
    for distance in (8.0, 16.0, 32.0):
        points = box_surface(rng, 8000, (distance, 0.0, -0.98), (4.0, 1.7, 1.5), 0.5)
        counts.append(len(render_object(points, EXACT, rng)[0]))
    ratios = np.array(counts[:-1]) / np.array(counts[1:])
    np.testing.assert_allclose(ratios, 4.0, rtol=0.15)


def test_scan_lines() -> None:
    """Every return lies on a beam's elevation (seen from the beam's origin)."""
    rng = np.random.default_rng(2)
    points = box_surface(rng, 3000, (15.0, 5.0, -0.98), (4.0, 1.7, 1.5), 1.0)
    returns, _ = render_object(points, EXACT, rng)
    elevation = np.degrees(np.arctan2(returns[:, 2], np.hypot(returns[:, 0], returns[:, 1])))
    gap = np.abs(elevation[:, None] - np.degrees(EXACT.elevations)[None]).min(axis=1)
    assert gap.max() < 1e-4


# ----------------------------------------------------------------------------------------------
# Radii
# ----------------------------------------------------------------------------------------------
def test_radii_follow_the_spacing_and_are_clipped() -> None:
    rng = np.random.default_rng(4)
    sparse = box_surface(rng, 300, (0, 0, 0), (4.0, 1.7, 1.5), 0.0)
    dense = box_surface(rng, 30000, (0, 0, 0), (4.0, 1.7, 1.5), 0.0)
    assert np.median(surfel_radii(dense)) < np.median(surfel_radii(sparse)) / 4
    far_apart = np.array([[0, 0, 0], [5, 0, 0], [0, 5, 0]], dtype=np.float32)
    np.testing.assert_allclose(surfel_radii(far_apart), 0.15)  # the upper clip
    same = np.zeros((5000, 3), dtype=np.float32)
    np.testing.assert_allclose(surfel_radii(same), 0.01)  # the lower clip
    # a wide object (the voxel grid's sparse path) agrees with a compact one
    apart = np.concatenate([dense, dense + np.array([300.0, 0, 0, 0], dtype=np.float32)])
    np.testing.assert_allclose(surfel_radii(apart)[: len(dense)], surfel_radii(dense))


def test_reference_radii() -> None:
    """The voxel rule against a plain count over the 27 neighbouring voxels."""
    rng = np.random.default_rng(8)
    points = box_surface(rng, 400, (1.0, 2.0, 3.0), (1.2, 0.8, 0.6), 0.3)[:, :3]
    voxel = 0.15
    key = np.floor(points.astype(np.float64) / voxel - points.min(axis=0) / voxel).astype(int)
    expected = []
    for k in key:
        count = int((np.abs(key - k).max(axis=1) <= 1).sum())
        expected.append(min(max(0.9 * 3 * voxel / math.sqrt(count), 0.01), 0.15))
    np.testing.assert_allclose(surfel_radii(points), expected)


def test_max_radius_clips_the_radii() -> None:
    """The upper clip against the plain radii clipped again by hand."""
    rng = np.random.default_rng(9)
    points = box_surface(rng, 1000, (4.0, 1.0, 0.0), (0.8, 0.6, 1.7), 0.2)
    plain = surfel_radii(points)
    assert plain.max() > 0.07 > plain.min()  # the clip bites on some, not all
    np.testing.assert_array_equal(surfel_radii(points, 0.07), np.minimum(plain, 0.07))
    np.testing.assert_array_equal(surfel_radii(points, 1.0), plain)
    np.testing.assert_array_equal(surfel_radii(points, 0.005), np.full(len(points), 0.005))


def test_radius_cap_is_a_share_of_the_narrower_side() -> None:
    assert radius_cap(np.array([0.8, 0.6, 1.7]), None) is None
    for dims, share in [((0.8, 0.6, 1.7), 0.12), ((1.76, 0.5, 1.7), 0.2), ((0.4, 0.9, 1.0), 0.1)]:
        expected = min(share * min(dims[0], dims[1]), RADIUS_RANGE[1])
        assert radius_cap(np.array(dims), share) == pytest.approx(expected)
    assert radius_cap(np.array([3.9, 1.6, 1.56]), 0.12) == RADIUS_RANGE[1]  # a car: unclipped
    with pytest.raises(DataError, match="dims"):
        radius_cap(np.array([0.8, 0.0, 1.7]), 0.12)
    with pytest.raises(DataError, match="dims"):
        radius_cap(np.array([0.8, 0.6]), 0.12)


def test_render_with_max_radius_is_render_with_those_radii() -> None:
    points = box_surface(np.random.default_rng(10), 600, (8.0, 2.0, -0.8), (0.8, 0.6, 1.7), 0.4)
    capped, source = render_object(points, EXACT, np.random.default_rng(3), max_radius=0.06)
    given, given_source = render_object(
        points, EXACT, np.random.default_rng(3), surfel_radii(points, 0.06)
    )
    np.testing.assert_array_equal(capped, given)
    np.testing.assert_array_equal(source, given_source)
    wide, _ = render_object(points, EXACT, np.random.default_rng(3))
    assert 0 < len(capped) < len(wide)  # smaller elements: fewer rays hit a thin object


# ----------------------------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------------------------
def test_bad_input_is_a_data_error() -> None:
    rng = np.random.default_rng(0)
    points = box_surface(rng, 50, (5, 0, 0), (1, 1, 1), 0.0)
    with pytest.raises(DataError, match="shape"):
        render_object(points[:, :2], EXACT, rng)
    bad = points.copy()
    bad[3, 1] = np.nan
    with pytest.raises(DataError, match="row 3"):
        render_object(bad, EXACT, rng)
    with pytest.raises(DataError, match="radii"):
        render_object(points, EXACT, rng, np.ones(3))
    with pytest.raises(DataError, match="radii"):
        render_object(points, EXACT, rng, np.full(len(points), -1.0))
    with pytest.raises(DataError, match="shape"):
        surfel_radii(np.zeros(5))
    for bad_cap in (0.0, -0.1, float("nan"), float("inf")):
        with pytest.raises(DataError, match="max_radius"):
            surfel_radii(points, bad_cap)
    empty, source = render_object(np.zeros((0, 5), np.float32), EXACT, rng)
    assert empty.shape == (0, 5) and source.shape == (0,)
