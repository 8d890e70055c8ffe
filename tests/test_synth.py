"""The built-in LiDAR world: sensor, ray casting, procedural world, labels from true visibility."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import spearmanr

from drcpo.datasets.kitti import KittiDataset, read_split
from drcpo.errors import ConfigError
from drcpo.geometry import bev_overlap_area, points_in_boxes, wrap_angle
from drcpo.synth import (
    CLASSES,
    Ground,
    LidarConfig,
    Scene,
    Solids,
    WorldConfig,
    frame_rng,
    free_pose,
    generate_world,
    hdl64e_elevations,
    make_actor,
    occlusion_level,
    place_object,
    ray_grid,
    scan,
    synthesize_frame,
    visible_points,
    write_synthetic_kitti,
)
from drcpo.synth.actors import SIZE_STATS
from drcpo.synth.raycast import GROUND, MISS
from drcpo.synth.solids import BOX, CYLINDER, ELLIPSOID, make_solids

# Sensor ---------------------------------------------------------------------------------------


def test_hdl64e_beams_span_the_datasheet_elevations():
    elevations = np.array(hdl64e_elevations())
    assert len(elevations) == 64
    assert elevations.max() == pytest.approx(2.0) and elevations.min() == pytest.approx(-24.9)
    assert (np.diff(elevations) < 0).all()


def test_ray_grid_is_unit_and_beam_major():
    config = LidarConfig(azimuth_step_deg=1.0)
    grid = ray_grid(config, azimuth_offset=0.3)
    assert grid.directions.shape == (64 * 360, 3)
    np.testing.assert_allclose(np.linalg.norm(grid.directions, axis=1), 1.0)
    assert (np.diff(grid.azimuth) > 0).all()
    beam = 5
    rows = grid.directions[beam * 360 : (beam + 1) * 360]
    np.testing.assert_allclose(np.arcsin(rows[:, 2]), np.deg2rad(config.elevations_deg[beam]))


@pytest.mark.parametrize(
    "field, value",
    [("azimuth_step_deg", 0.0), ("dropout", 1.0), ("max_range", 0.5), ("range_noise", -1.0)],
)
def test_lidar_config_rejects_bad_values_naming_the_field(field, value):
    with pytest.raises(ConfigError, match=field):
        LidarConfig(**{field: value})


def test_world_config_rejects_reversed_ranges():
    with pytest.raises(ConfigError, match="road_width"):
        WorldConfig(road_width=(12.0, 8.0))


def test_street_angle_sets_the_range_of_street_yaws():
    assert WorldConfig().street_yaw == (-0.1, 0.1)  # the default world is unchanged
    wide = WorldConfig().with_street_angle(45.0)
    assert wide.street_yaw == pytest.approx((-np.pi / 4, np.pi / 4))
    yaws = np.array([generate_world(frame_rng(3, i), wide).street.yaw for i in range(12)])
    assert np.abs(yaws).max() <= np.pi / 4 and np.abs(yaws).max() > 0.3
    straight = WorldConfig().with_street_angle(0.0)
    assert generate_world(frame_rng(3, 0), straight).street.yaw == 0.0


@pytest.mark.parametrize("degrees", [-1.0, 90.5, float("nan")])
def test_street_angle_rejects_values_outside_0_to_90_degrees(degrees):
    with pytest.raises(ConfigError, match="street angle"):
        WorldConfig().with_street_angle(degrees)


# Ray casting ----------------------------------------------------------------------------------


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_rays_hit_each_primitive_at_the_analytic_distance():
    solids = make_solids(
        [
            (BOX, (10, 0, 0), (1, 2, 3), np.pi / 2, "paint"),  # rotated: x half-extent is 2
            (ELLIPSOID, (0, 10, 0), (1, 2, 1), 0.0, "paint"),
            (CYLINDER, (-10, 0, 0), (0.5, 0.5, 2), 0.0, "metal"),
        ]
    )
    hits = Scene(solids).cast(_unit([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, 0, 1]]), 100.0)
    np.testing.assert_allclose(hits.t[:3], [8.0, 8.0, 9.5], atol=1e-12)
    np.testing.assert_array_equal(hits.hit, [0, 1, 2, MISS])
    np.testing.assert_allclose(hits.normal[:3], [[-1, 0, 0], [0, -1, 0], [1, 0, 0]], atol=1e-12)


def test_cylinder_caps_and_box_top_are_hit_from_above():
    solids = make_solids([(CYLINDER, (5, 0, -3), (1, 1, 1), 0.0, "metal")])
    direction = _unit([[5, 0, -2]])
    hits = Scene(solids).cast(direction, 100.0)
    np.testing.assert_allclose(hits.t, np.linalg.norm([5, 0, -2]), atol=1e-12)
    np.testing.assert_allclose(hits.normal, [[0, 0, 1]], atol=1e-12)


def test_ground_hits_lie_on_the_height_field():
    ground = Ground(-1.73, [0.05, 0.03], [0.1, -0.05], [0.07, 0.2], [0.3, 1.0])
    grid = ray_grid(LidarConfig(azimuth_step_deg=2.0))
    hits = Scene(Solids.empty(), ground).cast(grid.directions, 120.0)
    on_ground = hits.hit == GROUND
    assert on_ground.sum() > 0.8 * (grid.directions[:, 2] < -0.02).sum()
    points = grid.directions[on_ground] * hits.t[on_ground, None]
    np.testing.assert_allclose(points[:, 2], ground.height(points[:, 0], points[:, 1]), atol=1e-7)
    assert (hits.hit[grid.directions[:, 2] >= 0] == MISS).all()


def test_azimuth_binning_gives_the_brute_force_answer(rng):
    count = 300
    rows = [
        (
            int(rng.integers(0, 3)),
            (*rng.uniform(-40, 40, 2), rng.uniform(-2, 2)),
            tuple(rng.uniform(0.1, 3, 3)),
            rng.uniform(-np.pi, np.pi),
            "paint",
        )
        for _ in range(count)
    ]
    solids = make_solids(rows)
    centres = solids.centre
    keep = np.hypot(centres[:, 0], centres[:, 1]) > 5  # the sensor must not sit inside a solid
    solids = solids.take(np.flatnonzero(keep))
    directions = _unit(rng.normal(size=(4000, 3)))
    fast = Scene(solids, num_bins=720).cast(directions, 200.0)
    slow = Scene(solids, num_bins=1).cast(directions, 200.0)
    np.testing.assert_array_equal(fast.hit, slow.hit)
    np.testing.assert_allclose(fast.t, slow.t)
    assert (fast.hit >= 0).sum() > 100


def naive_solid_hits(solids, directions):
    """Distance ``(R,)`` to each ray's entry into solid ``s`` and the unit normal there, for
    every solid in turn: the ray from the origin taken into the solid's frame and its equation
    solved in plain numpy (box: slabs; ellipsoid: the unit sphere after scaling; cylinder: the
    side's roots within its height and the caps within its radius), the nearest positive
    root; the normal from the solid's gradient at the hit. ``(S, R)`` and ``(S, R, 3)``."""
    count = len(directions)
    t_all, normal_all = np.full((len(solids), count), np.inf), np.zeros((len(solids), count, 3))
    for s in range(len(solids)):
        c, sn = np.cos(solids.yaw[s]), np.sin(solids.yaw[s])
        o = -solids.centre[s]
        o = np.array([c * o[0] + sn * o[1], -sn * o[0] + c * o[1], o[2]])
        q = np.column_stack(
            [
                c * directions[:, 0] + sn * directions[:, 1],
                -sn * directions[:, 0] + c * directions[:, 1],
                directions[:, 2],
            ]
        )
        h = solids.half[s]
        with np.errstate(divide="ignore", invalid="ignore"):
            if solids.kind[s] == BOX:
                enter, leave = np.full(count, -np.inf), np.full(count, np.inf)
                for a in range(3):
                    t1, t2 = (-h[a] - o[a]) / q[:, a], (h[a] - o[a]) / q[:, a]
                    parallel = q[:, a] == 0
                    outside = parallel & (abs(o[a]) > h[a])
                    enter = np.maximum(enter, np.where(parallel, -np.inf, np.minimum(t1, t2)))
                    leave = np.minimum(leave, np.where(parallel, np.inf, np.maximum(t1, t2)))
                    leave[outside] = -np.inf
                t = np.where((enter <= leave) & (enter > 0), enter, np.inf)
            elif solids.kind[s] == ELLIPSOID:
                p, w = o / h, q / h
                a, b, cc = (w * w).sum(1), 2 * (w @ p), p @ p - 1.0
                t = (-b - np.sqrt(b * b - 4 * a * cc)) / (2 * a)
                t = np.where(t > 0, t, np.inf)  # NaN (no real root) fails too
            else:
                r, candidates = h[0], []
                a, b = (q[:, :2] ** 2).sum(1), 2 * (q[:, :2] @ o[:2])
                cc = o[:2] @ o[:2] - r * r
                for sign in (-1.0, 1.0):
                    side = (-b + sign * np.sqrt(b * b - 4 * a * cc)) / (2 * a)
                    candidates.append(np.where(abs(o[2] + side * q[:, 2]) <= h[2], side, np.nan))
                    cap = (sign * h[2] - o[2]) / q[:, 2]
                    spot = o[:2] + cap[:, None] * q[:, :2]
                    candidates.append(np.where((spot**2).sum(1) <= r * r, cap, np.nan))
                candidates = np.where(np.array(candidates) > 0, candidates, np.inf)
                t = candidates.min(axis=0)
        hit = np.isfinite(t)
        point = o + t[hit, None] * q[hit]
        if solids.kind[s] == BOX:
            face = np.argmax(np.abs(point) / h, axis=1)
            local = np.zeros_like(point)
            local[np.arange(len(point)), face] = np.sign(point[np.arange(len(point)), face])
        elif solids.kind[s] == ELLIPSOID:
            local = point / h**2
        else:
            on_cap = abs(abs(point[:, 2]) - h[2]) < abs(np.hypot(point[:, 0], point[:, 1]) - h[0])
            local = np.where(
                on_cap[:, None],
                np.column_stack([0 * point[:, :2], np.sign(point[:, 2])]),
                np.column_stack([point[:, :2], 0 * point[:, 2]]),
            )
        local /= np.linalg.norm(local, axis=1, keepdims=True)
        t_all[s] = t
        normal_all[s, hit] = np.column_stack(
            [c * local[:, 0] - sn * local[:, 1], sn * local[:, 0] + c * local[:, 1], local[:, 2]]
        )
    return t_all, normal_all


def naive_ground_hit(ground, d, t_max):
    """The first distance below ``t_max`` where the ray reaches the height field: a march in
    1 cm steps, then bisection of the first step that crosses (inf on none)."""
    if d[2] >= 0:
        return np.inf
    t = np.arange(0.0, t_max + 0.01, 0.01)
    below = np.flatnonzero(t * d[2] <= ground.height(t * d[0], t * d[1]))
    if len(below) == 0:
        return np.inf
    a, b = t[below[0] - 1], t[below[0]]
    for _ in range(60):
        m = (a + b) / 2
        if m * d[2] <= ground.height(m * d[0], m * d[1]):
            b = m
        else:
            a = m
    return b if b < t_max else np.inf


def test_cast_matches_the_naive_intersections(rng):
    # Boxes, ellipsoids and cylinders around the sensor over a bumpy ground, cast against
    # each solid's own equation and a marched ground; rays at random, along the axes, level
    # (dz exactly 0), straight up and down, and aimed at the solids' centres; per-ray range.
    rows = []
    for _ in range(150):
        kind = int(rng.integers(0, 3))
        half = rng.uniform(0.1, 3, 3)
        if kind == CYLINDER:
            half[1] = half[0]  # (radius, radius, half height)
        angle, distance = rng.uniform(-np.pi, np.pi), rng.uniform(5.5, 60)
        centre = (distance * np.cos(angle), distance * np.sin(angle), rng.uniform(-2, 2))
        rows.append((kind, centre, tuple(half), rng.uniform(-np.pi, np.pi), "paint"))
    solids = make_solids(rows)
    ground = Ground(-1.73, [0.05, 0.03], [0.1, -0.05], [0.07, 0.2], [0.3, 1.0])
    axes = np.vstack([np.eye(3), -np.eye(3)])
    level = np.column_stack([np.cos(a := rng.uniform(-np.pi, np.pi, 200)), np.sin(a), 0 * a])
    aimed = _unit(solids.centre + rng.normal(0, 0.3, solids.centre.shape))
    directions = np.vstack([_unit(rng.normal(size=(1500, 3))), axes, level, aimed])
    t_max = rng.uniform(5.0, 120.0, len(directions))
    t_solid, n_solid = naive_solid_hits(solids, directions)
    for with_ground in (True, False):
        scene = Scene(solids, ground if with_ground else None)
        hits = scene.cast(directions, t_max)
        t_ground = np.array(
            [
                naive_ground_hit(ground, d, m) if with_ground else np.inf
                for d, m in zip(directions, t_max, strict=True)
            ]
        )
        nearest = np.argmin(t_solid, axis=0)
        t_near = t_solid[nearest, np.arange(len(directions))]
        want_hit = np.where(t_ground < t_near, GROUND, nearest)
        want_t = np.minimum(t_ground, t_near)
        want_hit = np.where(want_t < t_max, want_hit, MISS)
        want_t = np.where(want_t < t_max, want_t, np.inf)
        assert (want_hit >= 0).sum() > 200 and (want_hit == MISS).sum() > 100
        assert (want_hit == GROUND).sum() > 200 or not with_ground
        np.testing.assert_array_equal(hits.hit, want_hit)
        np.testing.assert_allclose(hits.t, want_t, rtol=1e-9, atol=1e-6)
        solid = want_hit >= 0
        np.testing.assert_allclose(
            hits.normal[solid], n_solid[want_hit[solid], np.flatnonzero(solid)], atol=1e-6
        )
        on_ground = want_hit == GROUND
        spot = directions[on_ground] * want_t[on_ground, None]
        phase = spot[:, :1] * ground.wave_x + spot[:, 1:2] * ground.wave_y + ground.phase
        slope = ground.amplitude * np.cos(phase)
        up = np.column_stack([-(slope * ground.wave_x).sum(1), -(slope * ground.wave_y).sum(1)])
        up = _unit(np.column_stack([up, np.ones(len(up))]))
        np.testing.assert_allclose(hits.normal[on_ground], up, atol=1e-6)
        assert not hits.normal[want_hit == MISS].any()
    empty = Scene(Solids.empty(), ground).cast(directions[:50], 100.0)
    np.testing.assert_array_equal(empty.hit[directions[:50, 2] >= 0], MISS)


def test_surface_samples_are_on_the_outside_of_an_actor(rng):
    actor = make_actor("Car", rng)
    points, rows = actor.solids.surface_samples(rng, 0.05)
    assert len(points) > 1000
    inside = actor.solids.contains(points)
    inside[np.arange(len(points)), rows] = False  # on its own solid's surface, up to rounding
    assert not inside.any()
    low, high = actor.solids.bounds()
    np.testing.assert_allclose(high - low, actor.dims)
    np.testing.assert_allclose((low + high) / 2, 0.0, atol=1e-12)
    assert (np.abs(points) <= actor.dims / 2 + 1e-9).all()


# Objects and worlds ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", CLASSES)
def test_actor_sizes_follow_kitti_statistics(name):
    rng = np.random.default_rng(7)
    dims = np.array([make_actor(name, rng).dims for _ in range(300)])
    mean = np.array(SIZE_STATS[name][0])
    np.testing.assert_allclose(dims.mean(axis=0), mean, rtol=0.06)
    assert len(make_actor(name, rng).solids) >= 3  # built from several solids


def test_same_seed_same_world_and_sweep():
    a = synthesize_frame(frame_rng(3, 0))
    b = synthesize_frame(frame_rng(3, 0))
    np.testing.assert_array_equal(a.sweep.points, b.sweep.points)
    np.testing.assert_array_equal(a.world.boxes, b.world.boxes)
    c = synthesize_frame(frame_rng(3, 1))
    assert len(c.sweep.points) != len(a.sweep.points) or len(c.world.boxes) != len(a.world.boxes)


@pytest.fixture(scope="module")
def frames():
    return [synthesize_frame(frame_rng(2024, i)) for i in range(3)]


def test_point_count_per_frame_is_kitti_like(frames):
    for frame in frames:
        assert 15_000 <= len(frame.sweep.points) <= 130_000
        points = frame.sweep.points
        assert points.dtype == np.float32 and points.shape[1] == 4
        assert np.isfinite(points).all()
        assert 0.0 <= points[:, 3].min() and points[:, 3].max() <= 1.0
        assert np.linalg.norm(points[:, :3], axis=1).max() <= 120.2


def test_boxes_do_not_overlap_and_hold_their_objects_points(frames):
    for frame in frames:
        world = frame.world
        overlap = bev_overlap_area(world.boxes)
        np.fill_diagonal(overlap, 0.0)
        assert overlap.max() == 0.0
        own = frame.sweep.owner
        grown = world.boxes.copy()
        grown[:, 3:6] += 0.2  # range noise (2 cm sigma) may push points out of the tight box
        for i in np.unique(own[own >= 0]):
            inside = points_in_boxes(frame.sweep.points[own == i], grown[i : i + 1])
            assert inside.all()


def test_points_per_object_fall_with_distance(frames):
    counts, distances = [], []
    for frame in frames:
        counts += points_in_boxes(frame.sweep.points, frame.boxes).sum(axis=0).tolist()
        distances += np.hypot(frame.boxes[:, 0], frame.boxes[:, 1]).tolist()
    assert len(counts) >= 15
    rho = spearmanr(counts, distances).statistic
    assert rho <= -0.7, rho


def _monte_carlo_blocked(world, actor, elevations, rng, rays=4000):
    """Blocked fraction of an actor from random-azimuth rays at the beam elevations: the rays
    that hit the actor alone give surface points, and the truth API says which are seen."""
    solids = world.solids.take(np.flatnonzero(world.solids.owner == actor))
    angle = np.arctan2(solids.centre[:, 1], solids.centre[:, 0])
    spread = np.arcsin(solids.horizontal_radius() / np.hypot(*solids.centre[:, :2].T))
    ref = angle[0]
    rel = wrap_angle(angle - ref)
    azimuth = ref + rng.uniform((rel - spread).min(), (rel + spread).max(), rays)
    elevation = rng.choice(elevations, rays)
    directions = np.column_stack(
        [
            np.cos(elevation) * np.cos(azimuth),
            np.cos(elevation) * np.sin(azimuth),
            np.sin(elevation),
        ]
    )
    alone = Scene(solids).cast(directions, 120.0)
    hit = alone.hit != MISS
    surface = directions[hit] * alone.t[hit, None]
    seen = visible_points(world.scene, surface, tolerance=1e-6)
    return 1.0 - seen.mean(), hit.sum()


def test_labels_agree_with_ray_cast_visibility(frames):
    elevations = np.deg2rad(LidarConfig().elevations_deg)
    rng = np.random.default_rng(0)
    levels, compared = [], 0
    for frame in frames:
        levels += frame.occlusion.tolist()
        blocked = frame.visibility.blocked[frame.labelled]
        np.testing.assert_array_equal(frame.occlusion, occlusion_level(blocked))
        for actor, rays_blocked, reachable in zip(
            frame.labelled, blocked, frame.visibility.reachable[frame.labelled], strict=True
        ):
            if reachable < 40:
                continue  # too few beams cross a small far object for a stable fraction
            estimate, _ = _monte_carlo_blocked(frame.world, actor, elevations, rng)
            assert abs(estimate - rays_blocked) < 0.15, (actor, estimate, rays_blocked)
            compared += 1
    assert compared >= 10
    assert max(levels) >= 1  # some objects are partly occluded
    assert min(levels) == 0


def test_labelled_objects_are_in_the_camera_view_and_reached(frames):
    for frame in frames:
        assert (frame.truncation < 1.0).all()
        assert (frame.visibility.seen[frame.labelled] > 0).all()
        assert (frame.boxes[:, 0] > 0).all()  # the camera looks forward


# Occlusion truth ------------------------------------------------------------------------------


def test_visible_points_hides_what_is_behind_a_wall():
    wall = make_solids([(BOX, (10, 0, 0), (0.5, 5, 5), 0.0, "facade")])
    points = np.array([[9.5, 0, 0], [10.5, 0, 0], [20, 1, 1], [5, 0, 0], [9.5, 6, 0]])
    visible = visible_points(Scene(wall), points)
    np.testing.assert_array_equal(visible, [True, False, False, True, True])


def test_place_object_truth_has_self_and_external_occlusion(frames):
    world = frames[0].world
    rng = np.random.default_rng(5)
    actor = make_actor("Car", rng)
    box = actor.box(12.0, 0.0, world.ground.height(12.0, 0.0) + 0.0, 0.4)
    truth = place_object(world, actor, box, rng, spacing=0.08)
    fraction = truth.self_visible.mean()
    assert 0.15 < fraction < 0.6  # a car shows less than its near half
    assert not (truth.visible & ~truth.self_visible).any()
    near = np.linalg.norm(truth.points[:, :2] - [12.0, 0.0], axis=1)
    assert near.max() < np.linalg.norm(actor.dims[:2]) / 2 + 1e-6
    # Points on the side facing the sensor are visible; on the far side they are not.
    towards = truth.points[:, 0] < 12.0 - actor.dims[0] / 4
    assert truth.self_visible[towards].mean() > truth.self_visible[~towards].mean()


# KITTI layout ---------------------------------------------------------------------------------


def test_synthetic_kitti_round_trip(tmp_path):
    root = tmp_path / "kitti"
    summary = write_synthetic_kitti(root, frames=2, seed=11)
    assert summary["frames"] == 2 and sum(summary["objects"].values()) > 0
    assert read_split(root, "train") == ["000000"] and read_split(root, "val") == ["000001"]
    for split, index in (("train", 0), ("val", 1)):
        frame = KittiDataset(root, split)[0]
        truth = synthesize_frame(frame_rng(11, index))
        np.testing.assert_array_equal(frame.points, truth.sweep.points)
        np.testing.assert_array_equal(frame.names, truth.names)
        np.testing.assert_allclose(frame.boxes[:, :6], truth.boxes[:, :6], atol=1e-4)
        np.testing.assert_allclose(wrap_angle(frame.boxes[:, 6] - truth.boxes[:, 6]), 0, atol=1e-4)
        np.testing.assert_array_equal(frame.metadata["occlusion"], truth.occlusion)
        np.testing.assert_allclose(frame.metadata["truncation"], truth.truncation, atol=0.005)
    assert not list(tmp_path.glob(".*"))  # no temporary directory left behind


def test_synthetic_kitti_refuses_to_overwrite(tmp_path):
    (tmp_path / "kitti").mkdir()
    with pytest.raises(FileExistsError):
        write_synthetic_kitti(tmp_path / "kitti", frames=1)
    with pytest.raises(ConfigError, match="frames"):
        write_synthetic_kitti(tmp_path / "other", frames=0)
    assert not (tmp_path / "other").exists()


def test_scan_with_custom_sensor_changes_the_density():
    world = generate_world(np.random.default_rng(1))
    coarse = scan(world, np.random.default_rng(0), LidarConfig(azimuth_step_deg=0.4))
    fine = scan(world, np.random.default_rng(0), LidarConfig(azimuth_step_deg=0.2))
    assert 1.7 < len(fine.points) / len(coarse.points) < 2.3


def test_synth_command_writes_a_kitti_root(tmp_path):
    from typer.testing import CliRunner

    from drcpo.cli import app

    root = tmp_path / "kitti"
    result = CliRunner().invoke(
        app, ["synth", "--out", str(root), "--frames", "2", "--seed", "4", "--azimuth-step", "0.4"]
    )
    assert result.exit_code == 0, result.output
    assert "points per frame" in result.output
    assert read_split(root, "train") == ["000000"] and read_split(root, "val") == ["000001"]
    for kind, suffix in (("velodyne", ".bin"), ("label_2", ".txt"), ("calib", ".txt")):
        assert (root / "training" / kind / f"000001{suffix}").is_file()
    again = CliRunner().invoke(app, ["synth", "--out", str(root), "--frames", "1"])
    assert again.exit_code == 1 and "already exists" in again.output


def test_synth_command_street_angle_reaches_the_world(tmp_path):
    import json

    from typer.testing import CliRunner

    from drcpo.cli import app

    args = ["synth", "--frames", "1", "--azimuth-step", "1.0"]
    wide = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "a"), "--street-angle", "30"])
    assert wide.exit_code == 0, wide.output
    stored = json.loads((tmp_path / "a" / "synth.json").read_text())["world"]["street_yaw"]
    assert stored == pytest.approx([-np.pi / 6, np.pi / 6])
    default = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "b")])
    assert default.exit_code == 0, default.output
    stored = json.loads((tmp_path / "b" / "synth.json").read_text())["world"]["street_yaw"]
    assert stored == [-0.1, 0.1]
    bad = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "c"), "--street-angle", "120"])
    assert bad.exit_code != 0 and "street-angle" in bad.output and not (tmp_path / "c").exists()


def test_free_pose_stands_on_the_ground_clear_of_everything(frames):
    world = frames[1].world
    rng = np.random.default_rng(8)
    for name in CLASSES:
        actor = make_actor(name, rng)
        box = free_pose(world, actor, rng)
        assert box is not None
        bottom = box[2] - box[5] / 2
        assert bottom == pytest.approx(float(world.support_height(box[0], box[1])))
        taken = np.concatenate([world.boxes, world.obstacles])
        assert bev_overlap_area(box[None], taken).max() == 0.0
    crowded = free_pose(world, make_actor("Car", rng), rng, x_range=(-1, 1), y_range=(-1, 1))
    assert crowded is None  # the recording car sits there


def test_visibility_counts_rays_across_the_azimuth_seam():
    from drcpo.synth import World, actor_visibility
    from drcpo.synth.world import Street

    rng = np.random.default_rng(2)
    actors = (make_actor("Car", rng), make_actor("Pedestrian", rng))
    boxes = np.array([actors[0].box(-10.0, 0.0, -1.73, 0.3), actors[1].box(-6.0, 0.3, -1.73, 0.0)])
    world = World(
        Ground.flat(-1.73),
        Street(0.0, -2.0, 5.0, 3.0, 0.15),
        Solids.empty(),
        actors,
        boxes,
        np.array(["Car", "Pedestrian"]),
    )
    config = LidarConfig(azimuth_step_deg=0.5)
    sweep = scan(world, np.random.default_rng(0), config)
    visibility = actor_visibility(world, sweep, config)
    assert visibility.reachable[0] > 100 and visibility.reachable[1] > 20
    assert visibility.seen[1] == visibility.reachable[1]  # nothing stands in front of it
    assert 0 < visibility.seen[0] < visibility.reachable[0]  # the pedestrian hides part of it
    rays_on_car = int((sweep.ray_owner == 0).sum())
    assert visibility.seen[0] == rays_on_car
