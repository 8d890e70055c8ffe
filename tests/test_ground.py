import math

import numpy as np
import pytest
from scipy import ndimage

from drcpo.datasets.kitti_coordinates import Calibration
from drcpo.errors import ConfigError, DataError
from drcpo.geometry import rotation_matrix_z
from drcpo.ground import (
    KITTI_SENSOR_HEIGHT,
    GroundConfig,
    GroundModel,
    # test seams: the numba kernels, each against a plain numpy/scipy reference
    _bin_lowest_points,
    _fill_heights,
    _ground_cells,
)
from drcpo.ground_plane import fit_plane, road_plane_to_lidar


def tilted(xy):
    return 0.04 * xy[:, 0] - 0.03 * xy[:, 1] - 1.7


def uneven(xy):
    return -1.7 + 0.03 * xy[:, 0] + 0.3 * np.sin(xy[:, 0] / 6.0) * np.cos(xy[:, 1] / 7.0)


def ground_points(rng, surface, n=40000, noise=0.02, extent=((0, 60), (-30, 30))):
    xy = np.column_stack([rng.uniform(*extent[0], n), rng.uniform(*extent[1], n)])
    return np.column_stack([xy, surface(xy) + rng.normal(0, noise, n)])


def clutter(rng, surface):
    """Points of a wall, a parked car's body (its ground hidden) and a tree canopy."""
    wall_xy = np.column_stack([np.full(3000, 45.0), rng.uniform(-20, 20, 3000)])
    wall = np.column_stack([wall_xy, surface(wall_xy) + rng.uniform(0.0, 4.0, 3000)])
    car_xy = np.column_stack([rng.uniform(18, 22, 3000), rng.uniform(4, 6, 3000)])
    car = np.column_stack([car_xy, surface(car_xy) + rng.uniform(0.5, 1.5, 3000)])
    tree_xy = np.column_stack([rng.uniform(30, 34, 2000), rng.uniform(-12, -8, 2000)])
    tree = np.column_stack([tree_xy, surface(tree_xy) + rng.uniform(3.0, 6.0, 2000)])
    return {"wall": wall, "car": car, "tree": tree}


def frame_with_clutter(rng, surface):
    parts = clutter(rng, surface)
    ground = ground_points(rng, surface)
    # The car and the tree hide the ground under them.
    hidden = ((ground[:, 0] > 17.5) & (ground[:, 0] < 22.5) & (abs(ground[:, 1] - 5) < 1.5)) | (
        (ground[:, 0] > 29.5) & (ground[:, 0] < 34.5) & (abs(ground[:, 1] + 10) < 2.5)
    )
    points = np.concatenate([ground[~hidden], *parts.values()])
    features = rng.uniform(0, 1, (len(points), 1))
    return np.column_stack([points, features]).astype(np.float32), ground[~hidden], parts


def query_grid(extent=((2, 58), (-28, 28)), step=2.0):
    xs = np.arange(extent[0][0], extent[0][1], step)
    ys = np.arange(extent[1][0], extent[1][1], step)
    return np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)


def test_recovers_a_tilted_plane_and_ignores_walls_objects_and_trees(rng):
    points, ground, parts = frame_with_clutter(rng, tilted)
    model = GroundModel.from_points(points, rng=np.random.default_rng(0))
    assert model.source == "points"
    np.testing.assert_allclose(model.plane[:2], [0.04, -0.03], atol=0.003)
    # Built on each cell's lowest point, the estimate sits about 1.5 noise sigmas low.
    assert -1.7 - 0.05 < model.plane[2] < -1.7
    xy = query_grid()
    assert np.abs(model.height_at(xy) - tilted(xy)).max() < 0.1
    # Under the car and the tree the ground is unseen; the estimate must not ride on them.
    under = np.array([[20.0, 5.0], [32.0, -10.0], [45.0, 0.0]])
    assert np.abs(model.height_at(under) - tilted(under)).max() < 0.15
    assert model.is_ground(ground).mean() > 0.99
    for name, cloud in parts.items():
        high = cloud[cloud[:, 2] > tilted(cloud[:, :2]) + 0.3]
        assert not model.is_ground(high).any(), name


def test_follows_uneven_ground_better_than_a_plane(rng):
    points, _, _ = frame_with_clutter(rng, uneven)
    model = GroundModel.from_points(points)
    xy = query_grid()
    local_error = np.abs(model.height_at(xy) - uneven(xy))
    plane_error = np.abs(model.plane_height_at(xy) - uneven(xy))
    assert local_error.max() < 0.12
    assert plane_error.max() > 0.25


def test_ignores_noise_far_below_the_ground(rng):
    points = ground_points(rng, tilted)
    noise_xy = rng.uniform([10, -10], [40, 10], (40, 2))
    noise = np.column_stack([noise_xy, tilted(noise_xy) - rng.uniform(2, 5, 40)])
    model = GroundModel.from_points(np.concatenate([points, noise]))
    xy = query_grid()
    assert np.abs(model.height_at(xy) - tilted(xy)).max() < 0.1


def test_outside_the_grid_continues_along_the_plane(rng):
    model = GroundModel.from_points(ground_points(rng, tilted))
    far = np.array([[80.0, 0.0], [-20.0, 45.0], [30.0, -50.0]])
    np.testing.assert_allclose(model.height_at(far), tilted(far), atol=0.1)


def test_sparse_far_ground_is_filled_from_neighbours(rng):
    near = ground_points(rng, uneven, n=20000, extent=((0, 30), (-15, 15)))
    far = ground_points(rng, uneven, n=300, extent=((30, 60), (-15, 15)))
    model = GroundModel.from_points(np.concatenate([near, far]))
    xy = query_grid(extent=((2, 58), (-14, 14)))
    assert np.abs(model.height_at(xy) - uneven(xy)).max() < 0.2
    assert not model.ground_cells.all()


def test_same_seed_same_model_and_default_seed_is_fixed(rng):
    points, _, _ = frame_with_clutter(rng, uneven)
    a = GroundModel.from_points(points, rng=np.random.default_rng(3))
    b = GroundModel.from_points(points, rng=np.random.default_rng(3))
    np.testing.assert_array_equal(a.heights, b.heights)
    np.testing.assert_array_equal(a.plane, b.plane)
    c, d = GroundModel.from_points(points), GroundModel.from_points(points)
    np.testing.assert_array_equal(c.heights, d.heights)


def test_empty_or_degenerate_frames_fall_back():
    empty = GroundModel.from_points(np.zeros((0, 4), np.float32))
    assert empty.source == "default"
    np.testing.assert_allclose(empty.height_at(np.array([[5.0, 1.0]])), [-KITTI_SENSOR_HEIGHT])
    nan = GroundModel.from_points(np.full((10, 4), np.nan, np.float32))
    assert nan.source == "default"
    two = GroundModel.from_points(np.array([[1.0, 0.0, -1.5], [2.0, 0.0, -1.5]]))
    assert np.isfinite(two.height_at(np.array([[1.5, 0.0]]))).all()
    assert GroundModel.flat(-2.0).is_ground(np.array([[0, 0, -1.85], [0, 0, -1.75]])).tolist() == [
        True,
        False,
    ]


def scipy_ground_cells(minima, config):
    """The slope-cone test as a scipy grey erosion of the whole grid (reference)."""
    radius = max(int(np.ceil(config.window / config.cell_size)), 1)
    offsets = np.arange(-radius, radius + 1) * config.cell_size
    distance = np.hypot(offsets[:, None], offsets[None, :])
    footprint = distance <= radius * config.cell_size + 1e-9
    finite = np.where(np.isfinite(minima), minima, 1e9)
    structure = np.where(footprint, -config.max_slope * distance, 0)
    cone = ndimage.grey_erosion(finite, footprint=footprint, structure=structure)
    return np.isfinite(minima) & (minima <= cone + config.tolerance)


def scipy_fill_heights(minima, ground, plane_z, config):
    """Heights filled from scipy's exact Euclidean feature transform (reference)."""
    distance, (ix, iy) = ndimage.distance_transform_edt(~ground, return_indices=True)
    borrowed = minima[ix, iy] - plane_z[ix, iy] + plane_z
    near = distance * config.cell_size <= config.fill_radius
    return np.where(ground, minima, np.where(near, borrowed, plane_z))


@pytest.mark.parametrize("shape", [(1, 1), (2, 7), (5, 3), (23, 31), (60, 45)])
def test_grid_steps_match_scipy_bit_for_bit(rng, shape):
    # Integer heights and sparse ground make exact ties (equidistant ground cells, cones
    # touching the tolerance) common; the borders reflect as scipy's "reflect" mode does.
    for _ in range(20):
        config = GroundConfig(
            window=float(rng.choice([1.0, 2.0, 4.0, 9.0])),
            max_slope=float(rng.choice([0.0, 0.5, 1.0])),
            tolerance=float(rng.choice([0.0, 0.5, 1.0])),
            fill_radius=float(rng.choice([0.0, 1.0, 2.5, 10.0])),
        )
        minima = rng.integers(-3, 4, shape).astype(float)
        minima[rng.random(shape) < rng.uniform(0.1, 0.9)] = np.inf
        # scipy reads past its line buffers (a different answer each time) when the window
        # reflects more than once, i.e. reaches beyond a whole side of the grid.
        if np.ceil(config.window / config.cell_size) < min(shape):
            ground = _ground_cells(minima, config)
            np.testing.assert_array_equal(ground, scipy_ground_cells(minima, config))
        sparse = rng.random(shape) < rng.uniform(0.02, 0.3)
        sparse.flat[rng.integers(0, sparse.size)] = True
        plane_z = rng.normal(0, 1, shape)
        heights = rng.normal(0, 1, shape)
        np.testing.assert_array_equal(
            _fill_heights(heights, sparse, plane_z, config),
            scipy_fill_heights(heights, sparse, plane_z, config),
        )


def test_lowest_points_per_cell_in_the_points_dtype(rng):
    for dtype in (np.float32, np.float64):
        xyz = rng.uniform(-3, 3, (500, 3)).astype(dtype)
        xyz[:5, 2] = xyz[:5, 2].min() - 1  # ties: the last of them is kept
        xyz[5, 2] = np.nan
        xyz[6, 0] = 1e3  # out of range
        origin, shape, lowest, occupied = _bin_lowest_points(xyz, 10.0, 0.5)
        keep = np.isfinite(xyz[:, 2]) & (np.abs(xyz[:, :2]) <= 10.0).all(axis=1)
        x, y, z = xyz[keep, 0], xyz[keep, 1], xyz[keep, 2]
        np.testing.assert_array_equal(origin, np.floor([x.min() / 0.5, y.min() / 0.5]) * 0.5)
        ix = ((x - dtype(origin[0])) * dtype(2.0)).astype(np.int32)
        iy = ((y - dtype(origin[1])) * dtype(2.0)).astype(np.int32)
        assert shape == (ix.max() + 1, iy.max() + 1)
        cells = ix * shape[1] + iy
        np.testing.assert_array_equal(occupied, np.unique(cells))
        for c, row in zip(occupied, lowest, strict=True):
            members = np.flatnonzero(cells == c)
            last = members[z[members] == z[members].min()][-1]
            np.testing.assert_array_equal(row, [x[last], y[last], z[last]])


def naive_ransac_plane(seeds, rng, config):
    """The RANSAC fit step by step: the same draws (the triples, then the scored subset);
    each triple's normal (p1 - p0) x (p2 - p0), kept when within max_tilt_deg of vertical and
    not degenerate; its inliers |n . p - n . p0| <= threshold * |n| (n . p summed x, y, z);
    the first hypothesis with the most inliers among the scored seeds; least squares on its
    inliers among all seeds (all seeds when no hypothesis or fewer than 3 inliers)."""

    def lstsq(xyz):
        design = np.column_stack([xyz[:, 0], xyz[:, 1], np.ones(len(xyz))])
        return np.linalg.lstsq(design, xyz[:, 2], rcond=None)[0]

    def distances(points, n):
        return points[:, 0] * n[0] + points[:, 1] * n[1] + points[:, 2] * n[2]

    if len(seeds) < 3:
        return None
    picks = rng.integers(0, len(seeds), size=(config.ransac_iterations, 3))
    scored = seeds[rng.choice(len(seeds), 1000, replace=False)] if len(seeds) > 1000 else seeds
    cos_tilt = float(np.cos(np.deg2rad(config.max_tilt_deg)))
    best, best_count = None, -1
    for a, b, c in seeds[picks]:
        n = [
            (b[1] - a[1]) * (c[2] - a[2]) - (b[2] - a[2]) * (c[1] - a[1]),
            (b[2] - a[2]) * (c[0] - a[0]) - (b[0] - a[0]) * (c[2] - a[2]),
            (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]),
        ]
        norm = math.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
        if not (abs(n[2]) >= cos_tilt * norm and norm > 1e-9):
            continue
        offset, limit = n[0] * a[0] + n[1] * a[1] + n[2] * a[2], config.ransac_threshold * norm
        count = int((np.abs(distances(scored, n) - offset) <= limit).sum())
        if count > best_count:  # the first of equals
            best, best_count = (n, offset, limit), count
    if best is None:
        return lstsq(seeds)
    n, offset, limit = best
    chosen = seeds[np.abs(distances(seeds, n) - offset) <= limit]
    return lstsq(chosen) if len(chosen) >= 3 else lstsq(seeds)


def test_ransac_plane_follows_the_naive_fit():
    rng = np.random.default_rng(41)
    xy = rng.uniform(-40, 40, (1500, 2))
    plane = 0.02 * xy[:, 0] - 0.01 * xy[:, 1] - 1.7
    noisy = np.column_stack([xy, plane + rng.normal(0, 0.05, len(xy))])
    noisy[::7, 2] += rng.uniform(0.5, 3.0, len(noisy[::7]))  # roofs and walls
    lattice = np.column_stack([np.indices((6, 6)).reshape(2, -1).T * 2.0, np.zeros(36)])
    lattice[::3, 2] = 0.5  # integer-ish heights: inlier counts tie between planes
    wall = np.column_stack([np.zeros(30), rng.uniform(-5, 5, 30), rng.uniform(-2, 2, 30)])
    copies = np.repeat(noisy[:5], 8, axis=0)  # repeated seeds: degenerate triples
    cases = {
        "noisy": noisy,  # more than 1000 seeds: scored on a subset
        "small": noisy[:200],
        "lattice": lattice,
        "copies": copies,
        "wall": wall,  # every hypothesis too steep: least squares on all seeds
        "three": noisy[:3],
        "two": noisy[:2],
    }
    for name, seeds in cases.items():
        for config in (GroundConfig(), GroundConfig(ransac_iterations=7, max_tilt_deg=5.0)):
            for seed in range(3):
                want = naive_ransac_plane(seeds, np.random.default_rng(seed), config)
                got = fit_plane(
                    seeds,
                    np.random.default_rng(seed),
                    config.ransac_iterations,
                    config.ransac_threshold,
                    config.max_tilt_deg,
                )
                if want is None:
                    assert got is None, name
                else:
                    np.testing.assert_array_equal(got, want, err_msg=name)


def naive_height_at(model, xy):
    """Bilinear interpolation between cell centres, one query at a time: the query's cell
    coordinates clamped to the grid, the four surrounding centres (fewer on a one-cell-wide
    grid), then the plane's slope for the way from the clamped point to the query."""
    nx, ny = model.heights.shape
    cs = model.cell_size
    out = []
    for x, y in xy.tolist():
        gx, gy = (x - model.origin[0]) / cs - 0.5, (y - model.origin[1]) / cs - 0.5
        if math.isnan(gx) or math.isnan(gy):
            out.append(math.nan)
            continue
        cx, cy = min(max(gx, 0.0), nx - 1.0), min(max(gy, 0.0), ny - 1.0)
        i0, j0 = min(math.floor(cx), max(nx - 2, 0)), min(math.floor(cy), max(ny - 2, 0))
        i1, j1 = min(i0 + 1, nx - 1), min(j0 + 1, ny - 1)
        fx, fy = cx - i0, cy - j0
        h = model.heights
        value = (
            h[i0, j0] * (1 - fx) * (1 - fy)
            + h[i0, j1] * (1 - fx) * fy
            + h[i1, j0] * fx * (1 - fy)
            + h[i1, j1] * fx * fy
        )
        out.append(value + (gx - cx) * cs * model.plane[0] + (gy - cy) * cs * model.plane[1])
    return np.array(out)


def test_height_at_follows_the_naive_bilinear_interpolation():
    rng = np.random.default_rng(42)
    grids = (((7, 5), 1.0), ((1, 6), 0.5), ((4, 1), 2.0), ((1, 1), 1.0), ((30, 40), 1.0))
    for shape, cell in grids:  # one cell wide or long: fewer than four centres
        heights = rng.normal(-1.7, 0.3, shape)
        plane = np.array([0.03, -0.02, -1.7])
        origin = np.array([-3.0, 7.5])
        model = GroundModel(plane, origin, cell, heights, np.ones(shape, bool), "points")
        extent = origin + np.array(shape) * cell
        inside = rng.uniform(origin, extent, (300, 2))
        outside = rng.uniform(origin - 20, extent + 20, (300, 2))
        centres = origin + (np.indices(shape).reshape(2, -1).T + 0.5) * cell  # exact nodes
        edges = np.array([origin, extent, [origin[0], extent[1]], origin + cell / 2])
        odd = np.array([[np.nan, 0.0], [0.0, np.nan], [1e9, -1e9]])
        xy = np.concatenate([inside, outside, centres, edges, odd])
        got = model.height_at(xy)
        want = naive_height_at(model, xy)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        np.testing.assert_allclose(model.height_at(centres), heights.reshape(-1), atol=1e-12)
    assert model.height_at(np.zeros((0, 2))).shape == (0,)


def test_bad_input_is_rejected():
    with pytest.raises(DataError, match="shape"):
        GroundModel.from_points(np.zeros((5, 2)))
    with pytest.raises(DataError, match="shape"):
        GroundModel.flat().height_at(np.zeros(3))
    with pytest.raises(DataError, match="calib"):
        GroundModel.from_points(np.zeros((5, 3)), plane=np.array([0, -1, 0, 1.7]))
    with pytest.raises(ConfigError, match="ground.cell_size"):
        GroundConfig(cell_size=0)
    with pytest.raises(ConfigError, match="max_tilt_deg"):
        GroundConfig(max_tilt_deg=90)


def kitti_like_calibration() -> Calibration:
    """Velodyne-to-camera axes as in KITTI, with small extra rotations so nothing is trivial."""
    axes = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    tilt = rotation_matrix_z(0.01)[[0, 2, 1]][:, [0, 2, 1]]  # a small turn about camera y
    tr = np.column_stack([tilt @ axes @ rotation_matrix_z(0.02), [0.004, -0.076, -0.27]])
    r0 = rotation_matrix_z(0.005)
    p2 = np.array([[721.5, 0, 609.6, 44.9], [0, 721.5, 172.9, 0.2], [0, 0, 1, 0.003]])
    return Calibration(P2=p2, R0_rect=r0, Tr_velo_to_cam=tr)


def test_kitti_road_plane_matches_openpcdet_box_placement():
    calib = kitti_like_calibration()
    plane = np.array([0.02, -0.999, 0.03, 1.65])
    plane /= np.linalg.norm(plane[:3])
    lidar_plane = road_plane_to_lidar(plane, calib)
    model = GroundModel.from_points(np.zeros((0, 4)), plane=plane, calib=calib)
    assert model.source == "road_plane"
    xy = np.array([[5.0, 1.0], [20.0, -6.0], [40.0, 10.0]])
    on_plane = np.column_stack([xy, model.height_at(xy)])
    rect = on_plane @ (calib.R0_rect @ calib.Tr_velo_to_cam[:, :3]).T.astype(np.float64)
    rect += calib.R0_rect.astype(np.float64) @ calib.Tr_velo_to_cam[:, 3]
    np.testing.assert_allclose(rect @ plane[:3] + plane[3], 0, atol=1e-5)
    # OpenPCDet's put_boxes_on_road_planes: solve the plane for rect y at the box centre's rect
    # x and z, convert back, take the LiDAR z.
    centres = np.column_stack([xy, np.zeros(len(xy))])
    rect_centres = calib.lidar_to_rect(centres.astype(np.float32)).astype(np.float64)
    a, b, c, d = plane
    rect_centres[:, 1] = (-d - a * rect_centres[:, 0] - c * rect_centres[:, 2]) / b
    back = calib.rect_to_lidar(rect_centres)
    ours = back[:, :2] @ lidar_plane[:2] + lidar_plane[2]
    np.testing.assert_allclose(ours, back[:, 2], atol=1e-4)


def test_road_plane_replaces_the_ransac_fit(rng):
    calib = kitti_like_calibration()
    plane = np.array([0.0, -1.0, 0.0, 1.65])
    points = ground_points(rng, lambda xy: road_z(xy, plane, calib))
    model = GroundModel.from_points(points, plane=plane, calib=calib)
    np.testing.assert_allclose(model.plane, road_plane_to_lidar(plane, calib))
    xy = query_grid()
    np.testing.assert_allclose(model.height_at(xy), road_z(xy, plane, calib), atol=0.1)


def road_z(xy, plane, calib):
    coef = road_plane_to_lidar(plane, calib)
    return xy @ coef[:2] + coef[2]


def test_vertical_road_plane_is_rejected():
    calib = kitti_like_calibration()
    with pytest.raises(DataError, match="vertical"):
        road_plane_to_lidar(np.array([0.0, 0.0, 1.0, -5.0]), calib)


def test_real_kitti_ground_is_plausible(kitti_sample):
    near = np.array([[6.0, 0.0], [8.0, -1.0], [10.0, 1.0], [12.0, 0.0]])
    for path in sorted((kitti_sample / "training" / "velodyne").glob("*.bin")):
        points = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
        model = GroundModel.from_points(points)
        assert model.source == "points", path.name
        heights = model.height_at(near)
        assert ((heights > -2.1) & (heights < -1.4)).all(), (path.name, heights)
        assert -2.0 < model.plane[2] < -1.5, (path.name, model.plane)
        normal = np.array([-model.plane[0], -model.plane[1], 1.0])
        assert normal[2] / np.linalg.norm(normal) > np.cos(np.deg2rad(5))
        # Within 40 m, nothing 2 m above the road is ground (far away, hills may rise that high).
        near_high = (np.hypot(points[:, 0], points[:, 1]) < 40) & (points[:, 2] > 0.3)
        assert not model.is_ground(points[near_high]).any(), path.name
        assert 0.2 < model.is_ground(points).mean() < 0.9
