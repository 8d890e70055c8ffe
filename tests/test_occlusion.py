"""Tests for drcpo.occlusion (hpr, scopes, frame_grid, external): HPR against
Open3D's answers, the fast paths against the plain one, awkward inputs, forked workers, s-HPR /
e-HPR presets and the range-image mode."""

from __future__ import annotations

import math
import multiprocessing
import threading
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drcpo.errors import ConfigError, DataError
from drcpo.geometry import box_diagonal
from drcpo.occlusion import (
    external_occlusion,
    frame_grid,
    hidden_point_removal,
    hpr,
    local,
    self_occlusion,
)

FAST_METHODS = ("local", "auto")
ALL_METHODS = ("reference", *FAST_METHODS)


# ----------------------------------------------------------------------------------------------
# Scenes
# ----------------------------------------------------------------------------------------------
def _box_surface(rng: np.random.Generator, count: int, centre, dims, yaw: float) -> np.ndarray:
    local = rng.uniform(-0.5, 0.5, (count, 3)) * dims
    face = rng.integers(0, 3, count)
    local[np.arange(count), face] = rng.choice([-0.5, 0.5], count) * np.asarray(dims)[face]
    cos, sin = np.cos(yaw), np.sin(yaw)
    x = cos * local[:, 0] - sin * local[:, 1]
    y = sin * local[:, 0] + cos * local[:, 1]
    return np.column_stack([x, y, local[:, 2]]) + centre


def street_scene(rng: np.random.Generator, count: int, fov: float | None = None) -> np.ndarray:
    """A ground disc (radius 40 m, 1.7 m below the sensor) with a few box-shaped objects."""
    ground = count // 2
    radius = np.sqrt(rng.uniform(9.0, 1600.0, ground))
    angle = rng.uniform(-np.pi, np.pi, ground)
    parts = [
        np.column_stack(
            [radius * np.cos(angle), radius * np.sin(angle), rng.normal(-1.7, 0.02, ground)]
        )
    ]
    objects = int(rng.integers(3, 9))
    for _ in range(objects):
        distance, angle = rng.uniform(3.0, 30.0), rng.uniform(-np.pi, np.pi)
        dims = rng.uniform([0.5, 0.5, 1.0], [5.0, 2.5, 3.0])
        centre = [distance * np.cos(angle), distance * np.sin(angle), -1.7 + dims[2] / 2]
        parts.append(
            _box_surface(rng, (count - ground) // objects, centre, dims, rng.uniform(-3, 3))
        )
    points = np.vstack(parts)
    if fov is not None:
        points = points[np.abs(np.arctan2(points[:, 1], points[:, 0])) < fov]
    return points


def _fixture_mask(data) -> np.ndarray:
    mask = np.zeros(len(data["points"]), dtype=bool)
    mask[data["visible"]] = True
    return mask


def _jaccard(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


# ----------------------------------------------------------------------------------------------
# Open3D's answers
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ALL_METHODS)
def test_matches_open3d_fixtures(hpr_fixtures, method):
    files = sorted(hpr_fixtures.glob("*.npz"))
    assert len(files) >= 19
    for path in files:
        with np.load(path, allow_pickle=False) as data:
            expected = _fixture_mask(data)
            got = hidden_point_removal(
                data["points"], data["viewpoint"], float(data["radius"]), method=method
            )
        assert got.dtype == bool and got.shape == expected.shape
        if path.name.startswith("frame"):
            assert _jaccard(got, expected) >= 0.999, path.name
        else:
            assert np.array_equal(got, expected), path.name


def test_frame_fixture_through_external_occlusion_preset(hpr_fixtures):
    with np.load(hpr_fixtures / "frame000001_R1e5_z0.npz") as data:
        expected = _fixture_mask(data)
        points = data["points"]
    got = external_occlusion(points.astype(np.float32), 1e5, 0.0)  # PV-RCNN++'s in the paper
    assert _jaccard(got, expected) >= 0.999


# ----------------------------------------------------------------------------------------------
# Fast paths == plain path
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(6))
def test_fast_paths_equal_reference_on_random_scenes(seed):
    rng = np.random.default_rng(seed)
    points = street_scene(rng, int(rng.integers(1500, 4000)), fov=[None, 0.8][seed % 2])
    radius = [1e3, 1e4, 1e5, 3e5, 1e6, 1e9][seed]
    viewpoint = np.array([0.0, 0.0, [0.0, 1.0, 2.0][seed % 3]])
    reference = hidden_point_removal(points, viewpoint, radius, method="reference")
    assert 0 < reference.sum() <= len(points)
    for method in FAST_METHODS:
        got = hidden_point_removal(points, viewpoint, radius, method=method)
        assert np.array_equal(got, reference), method


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    count=st.integers(4, 120),
    log_ratio=st.floats(0.05, 6.0),
)
def test_local_equals_reference_on_random_clouds(seed, count, log_ratio):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(count, 3)) * rng.uniform(0.1, 10.0, 3) + rng.normal(0, 5, 3)
    ranges = np.linalg.norm(points, axis=1)
    radius = float(ranges.max() * 10**log_ratio)
    reference = hidden_point_removal(points, (0, 0, 0), radius, method="reference")
    local = hidden_point_removal(points, (0, 0, 0), radius, method="local")
    assert np.array_equal(local, reference)


@pytest.mark.parametrize("seed", range(4))
def test_fast_paths_equal_reference_on_lattices(seed):
    # integer lattices: duplicates, points on one ray, many coplanar quadruples
    rng = np.random.default_rng(100 + seed)
    for trial in range(25):
        points = rng.integers(-6, 7, size=(int(rng.integers(4, 400)), 3)).astype(float)
        if trial % 2:
            points[:, 2] = rng.integers(-2, 0, len(points))
        viewpoint = rng.normal(0, 0.3, 3) if trial % 3 == 0 else np.zeros(3)
        reach = np.linalg.norm(points - viewpoint, axis=1).max()
        radius = float(reach * 10 ** rng.uniform(0.05, 5))
        reference = hidden_point_removal(points, viewpoint, radius, method="reference")
        got = hidden_point_removal(points, viewpoint, radius, method="local")
        assert np.array_equal(got, reference), trial


def test_per_point_test_equals_qhull_written_out():
    # The per-point plane test ("local", drcpo.occlusion.kernels) against HPR's definition
    # with Qhull (test_hull.qhull_visible): street scenes, blobs with exact copies, integer
    # lattices (points on one ray, coplanar quadruples), each asked about every point and
    # about a random half.
    from test_hull import qhull_visible

    rng = np.random.default_rng(51)
    cases = []
    for seed in range(3):
        scene = street_scene(np.random.default_rng(seed), 2500, fov=[None, 0.8, None][seed])
        cases.append((scene, np.array([0.0, 0.0, [0.0, 1.0, 2.0][seed]]), [1e3, 1e4, 1e5][seed]))
    blob = rng.normal(size=(300, 3)) * [2.0, 0.5, 1.0] + [12.0, -3.0, 0.5]
    blob = np.vstack([blob, blob[rng.integers(0, 300, 60)]])
    cases += [(blob, np.zeros(3), 1e3), (blob, np.zeros(3), 40.0)]  # 40: R near the ranges
    for _ in range(6):
        lattice = rng.integers(-6, 7, size=(int(rng.integers(20, 300)), 3)).astype(float)
        lattice = lattice[np.abs(lattice).sum(axis=1) > 0]  # none at the viewpoint
        cases.append((lattice, np.zeros(3), float(10 ** rng.uniform(1.5, 4))))
    decided = 0
    for points, viewpoint, radius in cases:
        want = qhull_visible(points, viewpoint, radius)
        if want is None:  # Qhull cannot build this hull; the planar rule is tested elsewhere
            continue
        decided += 1
        got = hidden_point_removal(points, viewpoint, radius, method="local")
        np.testing.assert_array_equal(got, want)
        query = rng.random(len(points)) < 0.5
        asked = hidden_point_removal(points, viewpoint, radius, method="local", query=query)
        np.testing.assert_array_equal(asked, want | ~query)  # the others: reported visible
    assert decided >= 8


@pytest.mark.parametrize("method", ALL_METHODS)
def test_invariant_to_point_order(method):
    rng = np.random.default_rng(7)
    points = street_scene(rng, 3000)
    first = hidden_point_removal(points, (0, 0, 1.0), 3e5, method=method)
    order = rng.permutation(len(points))
    second = hidden_point_removal(points[order], (0, 0, 1.0), 3e5, method=method)
    assert np.array_equal(second, first[order])


def test_query_decides_only_the_asked_points():
    rng = np.random.default_rng(3)
    points = street_scene(rng, 4000)
    full = hidden_point_removal(points, (0, 0, 0), 1e5, method="reference")
    query = rng.random(len(points)) < 0.3
    for method in ALL_METHODS:
        got = hidden_point_removal(points, (0, 0, 0), 1e5, method=method, query=query)
        assert np.array_equal(got[query], full[query]), method
        assert got[~query].all(), method
    indices = np.flatnonzero(query)
    by_index = hidden_point_removal(points, (0, 0, 0), 1e5, query=indices)
    assert np.array_equal(by_index[query], full[query])


# ----------------------------------------------------------------------------------------------
# Awkward input
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ALL_METHODS)
def test_tiny_inputs(method):
    assert hidden_point_removal(np.zeros((0, 3)), (0, 0, 0), 10.0, method=method).shape == (0,)
    assert hidden_point_removal([[1.0, 2.0, 3.0]], (0, 0, 0), 10.0, method=method).tolist() == [
        True
    ]
    two = np.array([[5.0, 0.0, 0.0], [0.0, 5.0, 0.0]])
    assert hidden_point_removal(two, (0, 0, 0), 100.0, method=method).all()
    # one ray: the nearer point hides the farther one
    ray = np.array([[2.0, 1.0, 0.5], [4.0, 2.0, 1.0], [6.0, 3.0, 1.5]])
    assert hidden_point_removal(ray, (0, 0, 0), 100.0, method=method).tolist() == [
        True,
        False,
        False,
    ]


@pytest.mark.parametrize("method", ALL_METHODS)
def test_flat_configurations_use_the_planar_answer(method):
    rng = np.random.default_rng(11)
    # all points and the viewpoint in the plane z = 0: a 2-D HPR
    circle = rng.uniform(-np.pi, np.pi, 200)
    near = np.column_stack([10 + np.cos(circle), np.sin(circle), np.zeros(200)])
    visible = hidden_point_removal(near, (0, 0, 0), 1e4, method=method)
    facing = near[:, 0] < 10 - 0.2  # the half of the circle towards the viewpoint
    behind = near[:, 0] > 10 + 0.2
    assert visible[facing].mean() > 0.9 and not visible[behind].any()
    # collinear points off the viewpoint's line: all visible (each is extreme along the line)
    line = np.column_stack([np.linspace(1, 5, 20), np.full(20, 3.0), np.zeros(20)])
    assert hidden_point_removal(line, (0, 0, 0), 1e3, method=method).all()


@pytest.mark.parametrize("method", ALL_METHODS)
def test_duplicates_share_one_verdict(method):
    rng = np.random.default_rng(5)
    points = street_scene(rng, 2500)
    doubled = np.vstack([points, points[::3]])
    visible = hidden_point_removal(doubled, (0, 0, 0), 1e5, method=method)
    assert np.array_equal(visible[len(points) :], visible[: len(points)][::3])
    single = hidden_point_removal(points, (0, 0, 0), 1e5, method="reference")
    assert np.array_equal(visible[: len(points)], single)


@pytest.mark.parametrize("method", ALL_METHODS)
def test_points_at_the_viewpoint_are_visible(method):
    rng = np.random.default_rng(2)
    points = np.vstack([street_scene(rng, 500), [[0.0, 0.0, 1.0]], [[0.0, 0.0, 1.0 + 1e-12]]])
    visible = hidden_point_removal(points, (0, 0, 1.0), 1e5, method=method)
    assert visible[-2:].all()
    rest = hidden_point_removal(points[:-2], (0, 0, 1.0), 1e5, method="reference")
    assert np.array_equal(visible[:-2], rest)
    assert hidden_point_removal(np.ones((4, 3)), (1, 1, 1), 5.0, method=method).all()


@pytest.mark.parametrize("method", ALL_METHODS)
def test_huge_and_tiny_radii(method):
    rng = np.random.default_rng(4)
    points = street_scene(rng, 800)
    for radius in (1e12, 1e150):
        # R -> infinity keeps every point not exactly behind another one
        assert hidden_point_removal(points, (0, 0, 0), radius, method=method).all()
    ranges = np.linalg.norm(points, axis=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for radius in (ranges.max() / 4, ranges.max() * 0.75, 1e-9):
            visible = hidden_point_removal(points, (0, 0, 0), radius, method=method)
            assert visible.shape == (len(points),) and visible.dtype == bool


def test_bad_input_raises_clear_errors():
    good = np.ones((5, 4), dtype=np.float32) * np.arange(5)[:, None]
    for bad_value in (np.nan, np.inf, -np.inf):
        broken = good.copy()
        broken[2, 1] = bad_value
        with pytest.raises(DataError, match="row 2"):
            hidden_point_removal(broken, (0, 0, 0), 10.0)
    with pytest.raises(DataError, match="shape"):
        hidden_point_removal(np.ones((5, 2)), (0, 0, 0), 10.0)
    with pytest.raises(DataError, match="viewpoint"):
        hidden_point_removal(good, (0, 0), 10.0)
    with pytest.raises(DataError, match="viewpoint"):
        hidden_point_removal(good, (0, np.nan, 0), 10.0)
    for radius in (0.0, -1.0, np.nan, np.inf, 1e300, "big"):
        with pytest.raises(ConfigError, match="radius"):
            hidden_point_removal(good, (0, 0, 0), radius)
    with pytest.raises(ConfigError, match="method"):
        hidden_point_removal(good, (0, 0, 0), 10.0, method="fast")
    with pytest.raises(DataError, match="query"):
        hidden_point_removal(good, (0, 0, 0), 10.0, query=np.ones(3, dtype=bool))
    with pytest.raises(DataError, match="too far"):
        hidden_point_removal(np.full((3, 3), 1e200), (0, 0, 0), 10.0)
    with pytest.raises(DataError, match="box"):
        self_occlusion(good, np.ones(6))


def test_features_and_dtypes_pass_through():
    rng = np.random.default_rng(8)
    points = street_scene(rng, 600)
    with_features = np.column_stack([points, rng.random((len(points), 2))]).astype(np.float32)
    expected = hidden_point_removal(points.astype(np.float32).astype(np.float64), (0, 0, 0), 1e5)
    assert np.array_equal(hidden_point_removal(with_features, (0, 0, 0), 1e5), expected)


# ----------------------------------------------------------------------------------------------
# Forked workers (PyTorch DataLoader style)
# ----------------------------------------------------------------------------------------------
def _worker_job(args):
    points, method = args
    return hidden_point_removal(points, (0, 0, 0), 1e5, method=method)


def test_runs_in_forked_workers():
    rng = np.random.default_rng(9)
    points = street_scene(rng, 25000)
    # run in the parent first: compiled kernels and Qhull state exist before fork
    expected = {m: _worker_job((points, m)) for m in ("local", "reference")}
    context = multiprocessing.get_context("fork")
    with context.Pool(2) as pool:
        jobs = [(points, m) for m in expected for _ in range(2)]
        results = pool.map_async(_worker_job, jobs).get(timeout=120)
    for (_, method), got in zip(jobs, results, strict=True):
        assert np.array_equal(got, expected[method]), method


# ----------------------------------------------------------------------------------------------
# s-HPR, e-HPR, focus
# ----------------------------------------------------------------------------------------------
def test_self_occlusion_uses_the_box_diagonal():
    rng = np.random.default_rng(12)
    box = np.array([20.0, 5.0, -0.9, 4.2, 1.8, 1.6, 0.7])
    points = _box_surface(rng, 800, box[:3], box[3:6], box[6])
    radius = float(box_diagonal(box)[0]) * 200
    expected = hidden_point_removal(points, (0, 0, 0), radius)
    got = self_occlusion(points, box)
    assert np.array_equal(got, expected)
    assert 0.1 < got.mean() < 0.7  # the far side is gone
    near_side = np.linalg.norm(points, axis=1) < np.linalg.norm(box[:3]) - 0.5
    assert got[near_side].mean() > got.mean()
    with pytest.raises(DataError):
        self_occlusion(points, np.zeros(7))


@pytest.mark.parametrize("method", ["reference", "auto"])
def test_objects_take_the_certified_hull_with_qhull_s_answer(method, monkeypatch):
    rng = np.random.default_rng(13)
    jobs = []
    for _ in range(12):
        centre = rng.uniform([3, -30, -1.5], [60, 30, -0.5])
        box = np.array([*centre, *rng.uniform([0.5, 0.5, 1], [5, 2.5, 3]), rng.uniform(-3, 3)])
        points = _box_surface(rng, int(rng.integers(50, 1500)), box[:3], box[3:6], box[6])
        copies = points[rng.integers(0, len(points), 5)]  # exact duplicates
        jobs.append((np.vstack([points, copies]).astype(np.float32), box))
    answered = []
    real = hpr.hpr_hull_visible

    def spy(*args, **kwargs):
        answered.append(real(*args, **kwargs) is not None)
        return real(*args, **kwargs)

    monkeypatch.setattr(hpr, "hpr_hull_visible", spy)
    got = [self_occlusion(points, box, method=method) for points, box in jobs]
    assert len(answered) == len(jobs) and sum(answered) >= len(jobs) - 1
    monkeypatch.setattr(hpr, "hpr_hull_visible", lambda *args, **kwargs: None)
    for (points, box), mask in zip(jobs, got, strict=True):
        np.testing.assert_array_equal(mask, self_occlusion(points, box, method=method))


@pytest.mark.parametrize(("radius", "viewpoint_z"), [(3e5, 2.0), (3e5, 1.0), (1e5, 0.0)])
def test_external_occlusion_looks_from_the_viewpoint_height(radius, viewpoint_z):
    rng = np.random.default_rng(13)
    points = street_scene(rng, 3000)
    expected = hidden_point_removal(points, (0, 0, viewpoint_z), radius, method="reference")
    assert np.array_equal(external_occlusion(points, radius, viewpoint_z), expected)
    custom = external_occlusion(points, radius=500.0, viewpoint_z=0.5)
    assert np.array_equal(custom, hidden_point_removal(points, (0, 0, 0.5), 500.0))
    with pytest.raises(ConfigError):
        external_occlusion(points, radius=-1.0)
    with pytest.raises(ConfigError):
        external_occlusion(points, method="raytrace")


def test_counting_sort_is_the_stable_argsort(rng):
    from drcpo.occlusion.grid import _counting_sort  # test seam: the numba sort

    for size, cells in ((0, 3), (1, 1), (500, 7), (5000, 900)):
        cell = rng.integers(0, cells, size)
        starts = np.zeros(cells + 1, dtype=np.int64)
        np.cumsum(np.bincount(cell, minlength=cells), out=starts[1:])
        np.testing.assert_array_equal(_counting_sort(cell, starts), np.argsort(cell, kind="stable"))


def test_distinct_without_duplicates_is_the_same_setup(rng):
    from drcpo.occlusion.flip import _Setup  # test seam: duplicate detection of the set-up

    xyz = rng.normal(size=(200, 3)) + 5.0
    setup = _Setup.build(xyz, np.zeros(3), 1000.0)
    distinct, inverse = setup.distinct()
    assert distinct is setup
    np.testing.assert_array_equal(inverse, np.arange(200))
    # Equal x alone is not a duplicate; a real copy is.
    xyz[1, 0] = xyz[0, 0]
    xyz[5, :2] = xyz[4, :2]
    tied = _Setup.build(xyz, np.zeros(3), 1000.0)
    assert tied.distinct()[0] is tied
    xyz[3] = xyz[2]
    distinct, inverse = _Setup.build(xyz, np.zeros(3), 1000.0).distinct()
    assert distinct.size == 199 and inverse[3] == inverse[2] and inverse[1] != inverse[0]


def wall_and_cube(rng):
    """A wall at x = 20 m (with a second, hidden layer just behind part of it) and a dense cube
    inserted at x = 10 m in front of the wall's middle. Returns points, inserted, behind."""
    y, z = np.meshgrid(np.linspace(-4, 4, 81), np.linspace(-1.5, 1.5, 31))
    wall = np.column_stack([np.full(y.size, 20.0), y.ravel(), z.ravel()])
    hidden_layer = wall[wall[:, 1] > 2.5] * 1.05  # same rays, farther
    cube = rng.uniform(-0.5, 0.5, (400, 3)) + np.array([10.0, 0.0, 0.0])
    points = np.concatenate([wall, hidden_layer, cube])
    inserted = np.zeros(len(points), dtype=bool)
    inserted[-len(cube) :] = True
    return points, inserted, ~inserted


def hidden_by_insertion(points, inserted, behind, viewpoint=(0.0, 0.0, 0.0), radius=1e5, **kw):
    """Both steps of e-HPR's inserted scope for a fixed set ``behind``: ``bool (N,)`` points
    to remove."""
    from drcpo.occlusion import inserted_scope

    removed = np.zeros(len(points), dtype=bool)
    if not (inserted | behind).any():
        return removed
    scope = inserted_scope(points, inserted, viewpoint, radius, **kw)
    removed[inserted] = scope.removed_inserted
    removed[~inserted] = scope.removed_of((behind & ~inserted)[~inserted])
    return removed


def test_inserted_scope_removes_what_the_objects_hide_and_only_that(rng):
    points, inserted, behind = wall_and_cube(rng)
    removed = hidden_by_insertion(points, inserted, behind, radius=1e5)
    n_wall = 81 * 31
    wall = points[:n_wall]
    shadow = (np.abs(wall[:, 1]) < 0.8) & (np.abs(wall[:, 2]) < 0.8)  # inside the cube's shadow
    assert removed[:n_wall][shadow].all()  # wall points the cube hides go
    clear = (np.abs(wall[:, 1]) > 1.5) | (np.abs(wall[:, 2]) > 1.5)
    assert not removed[:n_wall][clear].any()
    # The layer behind the wall was hidden before anything was inserted: it stays.
    assert not removed[n_wall : n_wall + (wall[:, 1] > 2.5).sum()].any()
    assert removed[inserted].any() and not removed[inserted].all()
    # The same as the two passes spelled out with hidden_point_removal.
    visible = hidden_point_removal(points, radius=1e5, query=inserted | behind)
    suspects = behind & ~visible
    rows = np.flatnonzero(~inserted)
    before = hidden_point_removal(points[rows], radius=1e5, query=suspects[rows])
    expected = inserted & ~visible
    expected[rows[suspects[rows] & before]] = True
    np.testing.assert_array_equal(removed, expected)
    for method in ("reference", "local"):
        np.testing.assert_array_equal(
            hidden_by_insertion(points, inserted, behind, radius=1e5, method=method), expected
        )
    assert not hidden_by_insertion(
        points, np.zeros(len(points), bool), np.zeros(len(points), bool)
    ).any()


# ----------------------------------------------------------------------------------------------
# FrameGrid: e-HPR's inserted scope on a frame sorted once
# ----------------------------------------------------------------------------------------------
def _two_passes(points, inserted, behind, viewpoint, radius):
    """Both steps of the inserted scope spelled out with hidden_point_removal (the
    definition)."""
    visible = hidden_point_removal(points, viewpoint, radius, query=inserted | behind)
    suspects = behind & ~visible
    rows = np.flatnonzero(~inserted)
    before = hidden_point_removal(points[rows], viewpoint, radius, query=suspects[rows])
    expected = inserted & ~visible
    expected[rows[suspects[rows] & before]] = True
    return expected


def grid_steps(grid, cleared, inserted, behind, **options):
    """Both steps on a FrameGrid: the frame points and the inserted points to remove."""
    step = grid.insert(cleared, inserted, **options)
    return step.hidden_behind(behind), step.removed_inserted


def _insertion_scene(seed: int):
    """A street frame, some of its points cleared, objects inserted (one of them above every
    frame point and one with copies of frame points), and the frame points behind them."""
    rng = np.random.default_rng(seed)
    frame = street_scene(rng, 3000, fov=1.2).astype(np.float32)
    boxes = [([12.0, 2.0, -1.0], [4.0, 1.8, 1.5]), ([20.0, -4.0, -0.8], [1.0, 1.0, 1.8])]
    objects = [_box_surface(rng, 300, c, d, rng.uniform(-3, 3)) for c, d in boxes]
    objects.append(rng.normal([8.0, 1.0, 3.5], 0.3, (40, 3)))  # above the frame's elevations
    objects.append(frame[rng.choice(len(frame), 20)] * 1.0)  # exact copies of frame points
    inserted = np.concatenate(objects).astype(np.float32)
    cleared = np.zeros(len(frame), dtype=bool)
    for centre, dims in boxes:
        cleared |= np.all(np.abs(frame - np.asarray(centre)) <= np.asarray(dims) / 2, axis=1)
    azimuth = np.arctan2(frame[:, 1], frame[:, 0])
    behind = ~cleared & (np.hypot(frame[:, 0], frame[:, 1]) > 7.0) & (np.abs(azimuth) < 0.8)
    return frame, cleared, inserted, behind


@pytest.mark.parametrize("seed", range(3))
def test_frame_grid_equals_the_two_passes(seed):
    from drcpo.occlusion import FrameGrid

    frame, cleared, inserted, behind = _insertion_scene(seed)
    viewpoint, radius = np.array([0.0, 0.0, [0.0, 0.5, 1.0][seed]]), [1e4, 1e5, 3e5][seed]
    points = np.concatenate([frame[~cleared], inserted])
    is_inserted = np.repeat([False, True], [int((~cleared).sum()), len(inserted)])
    expected = _two_passes(
        points,
        is_inserted,
        np.concatenate([behind[~cleared], np.zeros(len(inserted), bool)]),
        viewpoint,
        radius,
    )
    assert expected[is_inserted].any() and expected[~is_inserted].any()
    grid = FrameGrid.build(frame, viewpoint, radius, spare=10)  # grows for the objects
    found = grid_steps(grid, cleared, inserted, behind, method="local")
    np.testing.assert_array_equal(np.concatenate([found[0][~cleared], found[1]]), expected)
    assert not found[0][cleared].any()


@pytest.mark.parametrize("path", ["grid", "own grid", "reference"])
def test_inserted_scope_steps_equal_the_definition(path, seed=1):
    # Step 1 decides the inserted points alone; the caller then picks the frame points to
    # decide (DR.CPO: those behind the objects that keep enough points), and step 2 decides
    # those: hidden with the objects, visible without them. Each path against its naive
    # reference: hidden_point_removal with and without the objects.
    from drcpo.occlusion import FrameGrid, inserted_scope

    frame, cleared, inserted, behind = _insertion_scene(seed)
    radius = 1e5
    points = np.concatenate([frame[~cleared], inserted])
    is_inserted = np.repeat([False, True], [int((~cleared).sum()), len(inserted)])
    half = (behind & (np.arange(len(frame)) % 2 == 0))[~cleared]  # what the caller picks
    options = {
        "grid": {
            "grid": FrameGrid.build(frame, radius=radius),
            "cleared": cleared,
            "method": "local",
        },
        "own grid": {"method": "local"},
        "reference": {"method": "reference"},
    }[path]
    scope = inserted_scope(points, is_inserted, np.zeros(3), radius, **options)
    nothing = np.zeros(len(points), bool)
    expected_inserted = _two_passes(points, is_inserted, nothing, np.zeros(3), radius)
    expected_inserted = expected_inserted[is_inserted]
    expected = _two_passes(
        points, is_inserted, np.append(half, np.zeros(len(inserted), bool)), np.zeros(3), radius
    )[~is_inserted]
    assert expected_inserted.any() and expected.any()
    np.testing.assert_array_equal(scope.removed_inserted, expected_inserted)
    np.testing.assert_array_equal(scope.removed_of(half), expected)
    assert not scope.removed_of(np.zeros_like(half)).any()


@pytest.mark.parametrize("path", ["grid", "own grid"])
def test_inserted_scope_decides_the_original_points_in_the_windows(path):
    # removed_behind(windows) is removed_of(the original points in those view windows, by
    # view_windows.in_windows); None: every direction.
    from drcpo.occlusion import FrameGrid, inserted_scope
    from drcpo.occlusion.view_windows import in_windows, window_spans

    frame, cleared, inserted, _ = _insertion_scene(0)
    points = np.concatenate([frame[~cleared], inserted])
    is_inserted = np.repeat([False, True], [int((~cleared).sum()), len(inserted)])
    viewpoint = np.array([0.0, 0.0, 0.5])
    options = {
        "grid": {
            "grid": FrameGrid.build(frame, viewpoint, 1e5),
            "cleared": cleared,
            "method": "local",
        },
        "own grid": {"method": "local"},
    }[path]
    scope = inserted_scope(points, is_inserted, viewpoint, 1e5, **options)
    boxes = np.array(
        [[12.0, 2.0, -1.0, 4.2, 2.0, 1.7, 0.0], [20.0, -4.0, -0.8, 1.2, 1.2, 2.0, 0.3]]
    )
    windows = window_spans(boxes, viewpoint, True)
    members = in_windows(points[~is_inserted], windows, viewpoint)
    assert 0 < members.sum() < len(members)
    np.testing.assert_array_equal(scope.in_windows(windows), members)
    np.testing.assert_array_equal(scope.removed_behind(windows), scope.removed_of(members))
    every = np.ones(len(members), dtype=bool)
    np.testing.assert_array_equal(scope.removed_behind(None), scope.removed_of(every))


def test_inserted_scope_picks_its_path_and_refuses_bad_settings():
    from drcpo.occlusion import FrameGrid, inserted_scope

    frame, cleared, inserted, _ = _insertion_scene(0)
    points = np.concatenate([frame[~cleared], inserted])
    is_inserted = np.repeat([False, True], [int((~cleared).sum()), len(inserted)])
    grid = FrameGrid.build(frame, radius=1e5)
    local = {"grid": grid, "cleared": cleared, "method": "local"}
    assert type(inserted_scope(points, is_inserted, **local)).__name__ == "_GridScope"
    # R below the ranges: the grid does not apply; the plain passes decide
    small = FrameGrid.build(frame, radius=10.0)
    assert not small.applies(cleared, inserted)
    chosen = inserted_scope(points, is_inserted, radius=10.0, grid=small, cleared=cleared)
    assert type(chosen).__name__ == "_PointsScope"
    with pytest.raises(ValueError, match="needs cleared"):
        inserted_scope(points, is_inserted, grid=grid)
    with pytest.raises(ConfigError, match="method"):
        inserted_scope(points, is_inserted, method="zbuffer")


@pytest.mark.parametrize("seed", range(2))
def test_hidden_groups_count_samples_hidden_among_the_frame_points(seed):
    # Each sample decided as a point added to the frame's points without the cleared ones
    # (the definition: one HPR per sample), then counted per group against the share.
    from drcpo.occlusion import FrameGrid

    frame, cleared, _, _ = _insertion_scene(seed)
    rng = np.random.default_rng(seed)
    # Groups of samples in small boxes: half anywhere, half right behind the frame's objects.
    anywhere = np.column_stack(
        [rng.uniform(8, 35, 12), rng.uniform(-12, 12, 12), rng.uniform(-1.6, 0.5, 12)]
    )
    on_objects = np.flatnonzero(~cleared & (frame[:, 2] > -1.0))
    behind = frame[rng.choice(on_objects, 12)] * 1.4
    centres = np.concatenate([anywhere, behind])
    samples = np.concatenate([c + rng.uniform(-0.2, 0.2, (10, 3)) for c in centres])
    offsets = np.append(np.arange(0, len(samples), 10), len(samples))
    offsets = np.insert(offsets, 3, offsets[3])  # and a group without samples
    kept = frame[~cleared].astype(np.float64)
    hidden_each = np.array(
        [
            not hidden_point_removal(np.vstack([kept, sample]), np.zeros(3), 1e5)[-1]
            for sample in samples
        ]
    )
    counts = np.add.reduceat(hidden_each, offsets[:-1]) * (np.diff(offsets) > 0)
    sizes = np.diff(offsets)
    assert 0 < hidden_each.mean() < 1
    grid = FrameGrid.build(frame, radius=1e5)
    mixed = False
    for share in (0.2, 0.5, 0.8, 1.0):
        expected = (sizes > 0) & (counts >= np.ceil(share * sizes - 1e-9))
        mixed |= 0 < expected.sum() < len(expected) - 1
        found = grid.hidden_groups(samples, offsets, cleared, share)
        np.testing.assert_array_equal(found, expected)
    assert mixed
    # Not applicable where R is not above the ranges.
    assert grid.groups_apply(samples) and grid.groups_apply(samples[:0])
    near = FrameGrid.build(frame, radius=10.0)
    assert not near.groups_apply(samples)
    with pytest.raises(ValueError, match="does not apply"):
        near.hidden_groups(samples, offsets, cleared, 1.0)
    for bad, message in (
        (offsets[:-1], "offsets must run"),
        (offsets[::-1], "offsets must run"),
        (np.array([0, 30, 20, len(samples)]), "must not decrease"),
    ):
        with pytest.raises(ValueError, match=message):
            grid.hidden_groups(samples, bad, cleared, 1.0)
    with pytest.raises(ValueError, match="share"):
        grid.hidden_groups(samples, offsets, cleared, 1.5)


def test_frame_grid_memory_is_reused_and_grown():
    from drcpo.occlusion import FrameGrid, GridMemory

    frame, cleared, inserted, behind = _insertion_scene(0)
    expected = grid_steps(FrameGrid.build(frame), cleared, inserted, behind, method="local")
    memory = GridMemory()
    memory.ints = np.empty(10, dtype=np.int64)  # far too short for the cells: replaced
    small = FrameGrid.build(frame[:500], spare=0, memory=memory)
    assert len(memory.ints) >= 3 * 500 and small.size == 500
    floats = memory.floats
    for _ in range(2):  # the second build finds its memory ready
        found = grid_steps(
            FrameGrid.build(frame, memory=memory), cleared, inserted, behind, method="local"
        )
        for a, b in zip(found, expected, strict=True):
            np.testing.assert_array_equal(a, b)
    assert memory.floats is not floats  # grown once, for the larger frame
    grown = memory.floats
    FrameGrid.build(frame[:1000], memory=memory)
    assert memory.floats is grown  # and kept
    # One memory per thread: a thread's grid never lands in another's.
    from drcpo.occlusion import thread_grid_memory

    other = []
    worker = threading.Thread(target=lambda: other.append(thread_grid_memory()))
    worker.start()
    worker.join()
    assert thread_grid_memory() is thread_grid_memory() is not other[0]


def test_frame_grid_settles_what_its_kernel_gives_up_on(monkeypatch):
    from drcpo.occlusion import FrameGrid

    frame, cleared, inserted, behind = _insertion_scene(2)
    radius = 100.0  # R near the ranges: wide neighbourhoods, full scans
    points = np.concatenate([frame[~cleared], inserted])
    is_inserted = np.repeat([False, True], [int((~cleared).sum()), len(inserted)])
    behind_points = np.concatenate([behind[~cleared], np.zeros(len(inserted), bool)])
    expected = _two_passes(points, is_inserted, behind_points, np.zeros(3), radius)
    for module in (frame_grid, local):  # every full scan is refused
        monkeypatch.setattr(module, "_BRUTE_BUDGET", 0)
    settled = []
    undecided = FrameGrid._undecided
    monkeypatch.setattr(FrameGrid, "_undecided", lambda *a: settled.append(1) or undecided(*a))
    grid = FrameGrid.build(frame, radius=radius)
    found = grid_steps(grid, cleared, inserted, behind, method="local")
    assert settled  # the plain passes took over
    np.testing.assert_array_equal(np.concatenate([found[0][~cleared], found[1]]), expected)


def test_frame_grid_declines_where_auto_takes_one_hull():
    from drcpo.occlusion import FrameGrid

    frame, cleared, inserted, _ = _insertion_scene(0)
    grid = FrameGrid.build(frame[:500], radius=1e5)
    # "auto" runs one hull on a few hundred points: the grid leaves it to the caller
    assert not grid.applies(cleared[:500], inserted[:100])
    with pytest.raises(ValueError, match="does not apply"):
        grid.insert(cleared[:500], inserted[:100])
    assert grid.applies(cleared[:500], inserted[:100], method="local")
    assert grid.applies(cleared[:500], inserted[:0], method="local")  # no objects: the frame's
    at_origin = np.vstack([frame, np.zeros((1, 3), np.float32)])
    grid = FrameGrid.build(at_origin)
    assert not grid.applies(np.zeros(len(at_origin), bool), inserted)
    with pytest.raises(DataError, match="NaN"):
        FrameGrid.build(np.vstack([frame, [[np.nan, 0, 0]]]))


def naive_directions(points, viewpoint):
    """Azimuth, elevation and distance ``(N,)`` of points seen from ``viewpoint``, in float64
    with libm's atan2 (math's), which the kernels use on every CPU."""
    rel = np.asarray(points, dtype=np.float64)[:, :3] - np.asarray(viewpoint, dtype=np.float64)
    horizontal = np.sqrt(rel[:, 0] * rel[:, 0] + rel[:, 1] * rel[:, 1])
    azimuth = np.array([math.atan2(y, x) for x, y in rel[:, :2].tolist()])
    elevation = np.array([math.atan2(z, h) for z, h in zip(rel[:, 2], horizontal, strict=True)])
    distance = np.sqrt(rel[:, 0] * rel[:, 0] + rel[:, 1] * rel[:, 1] + rel[:, 2] * rel[:, 2])
    return azimuth, elevation, distance


def naive_in_windows(points, windows, viewpoint):
    """A point is in a window when its azimuth and elevation lie in the window's closed
    ranges and it is at least the window's nearest distance away; in any window, in any."""
    azimuth, elevation, distance = naive_directions(points, viewpoint)
    expected = np.zeros(len(azimuth), dtype=bool)
    for az0, az1, el0, el1, near in windows:
        expected |= (
            (azimuth >= az0)
            & (azimuth <= az1)
            & (elevation >= el0)
            & (elevation <= el1)
            & (distance >= near)
        )
    return expected


def test_frame_grid_windows_select_by_direction(rng):
    from drcpo.occlusion import FrameGrid

    points = rng.normal(0, 20, (4000, 3))
    grid = FrameGrid.build(points, (0.0, 0.0, 0.5))
    windows = np.array([[-0.3, 0.2, -0.1, 0.3, 10.0], [2.9, np.pi, -1.0, 1.0, -np.inf]])
    expected = naive_in_windows(points, windows, (0.0, 0.0, 0.5))
    assert expected.sum() > 50
    np.testing.assert_array_equal(grid.in_windows(windows), expected)
    rows = np.flatnonzero(expected)[:40]
    got = grid.directions(rows)
    for values, want in zip(got, naive_directions(points, (0.0, 0.0, 0.5)), strict=True):
        np.testing.assert_array_equal(values, want[rows])


def test_in_windows_follows_the_naive_rule():
    # view_windows.in_windows (its own kernel, not the FrameGrid's) on windows whose bounds
    # are some points' own azimuth, elevation and distance (exact ties: closed bounds), the
    # seam at +-pi, float32 and float64 points, NaN and a point at the viewpoint.
    from drcpo.occlusion.view_windows import in_windows, window_spans

    rng = np.random.default_rng(52)
    viewpoint = np.array([0.3, -0.2, 1.7])
    points = np.vstack([rng.normal(0, 20, (3000, 3)), [[np.nan, 0.0, 0.0], viewpoint]])
    for dtype in (np.float64, np.float32):
        cloud = points.astype(dtype)
        azimuth, elevation, distance = naive_directions(cloud, viewpoint)
        a, b, c = rng.choice(3000, (3, 6))
        windows = np.array(
            [
                [azimuth[a[0]], azimuth[a[1]], elevation[b[0]], elevation[b[1]], -np.inf],
                [azimuth[a[2]], azimuth[a[3]], -1.0, elevation[b[2]], distance[c[0]]],
                [-np.pi, azimuth[a[4]], elevation[b[3]], np.pi / 2, distance[c[1]]],
                [azimuth[a[5]], np.pi, -np.pi / 2, elevation[b[4]], 0.0],
            ]
        )
        windows[:, :2].sort(axis=1)
        windows[:, 2:4].sort(axis=1)
        boxes = np.array(
            [[-10.0, 0.3, -1.0, 4.0, 1.8, 1.5, 0.4], [9.0, 2.0, 0.0, 1.0, 1.0, 2.0, 0]]
        )
        spans = window_spans(boxes, viewpoint, behind=True)  # the first crosses the seam
        for case in (windows, windows[:1], spans, np.zeros((0, 5))):
            want = naive_in_windows(cloud, case, viewpoint)
            np.testing.assert_array_equal(in_windows(cloud, case, viewpoint), want)
        assert naive_in_windows(cloud, windows, viewpoint).sum() > 100
        np.testing.assert_array_equal(in_windows(cloud, None, viewpoint), np.ones(len(cloud), bool))
        assert in_windows(cloud[:0], windows, viewpoint).shape == (0,)


# ----------------------------------------------------------------------------------------------
# "auto" on inputs that crowd the per-point test's neighbourhoods
# ----------------------------------------------------------------------------------------------
def _tiny_sphere(rng: np.random.Generator, count: int, radius: float = 0.1) -> np.ndarray:
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    return (directions * radius + [10.0, 0.0, 0.0]).astype(np.float32)


def _no_per_point_test(monkeypatch) -> None:
    """Fail if the per-point test runs on more than a few points (a degenerate hull's
    fallback may run it on the distinct points)."""
    original = hpr._LocalState.visible  # test seam: which path "auto" takes

    def refuse(self, *args):
        if self.size > 100:
            raise AssertionError(f"the per-point test ran on {self.size} crowded points")
        return original(self, *args)

    monkeypatch.setattr(hpr._LocalState, "visible", refuse)


@pytest.mark.parametrize(
    "scene",
    ["tiny_sphere", "copies", "sphere_and_copies"],
)
def test_auto_sends_crowded_sets_to_one_hull(rng, monkeypatch, scene):
    # The per-point test is quadratic in the points per neighbourhood: 30,000 points on a
    # 0.1 m sphere 10 m away with R = 100 took it 11.6 CPU-s (one hull: 0.1 s).
    sphere = _tiny_sphere(rng, 6000)
    copies = np.tile(np.float32([[10.0, 2.0, -1.0]]), (6000, 1))
    points = {"tiny_sphere": sphere, "copies": copies}.get(scene)
    if points is None:
        points = np.concatenate([sphere, copies, sphere[:50]])
    reference = hidden_point_removal(points, radius=100.0, method="reference")
    _no_per_point_test(monkeypatch)
    auto = hidden_point_removal(points, radius=100.0)
    np.testing.assert_array_equal(auto, reference)
    query = rng.random(len(points)) < 0.3
    np.testing.assert_array_equal(
        hidden_point_removal(points, radius=100.0, query=query), reference | ~query
    )


def test_auto_keeps_the_per_point_test_on_lidar_like_frames(rng, monkeypatch):
    # A sweep over flat ground (and a wall where the ground is out of reach).
    azimuth = rng.uniform(-np.pi, np.pi, 40000)
    elevation = rng.uniform(-0.4, 0.05, 40000)
    ranges = np.minimum(1.73 / np.maximum(-np.sin(elevation), 0.02), 80.0)
    points = np.column_stack(
        [
            ranges * np.cos(elevation) * np.cos(azimuth),
            ranges * np.cos(elevation) * np.sin(azimuth),
            ranges * np.sin(elevation),
        ]
    )
    calls = []
    original = hpr._LocalState.visible  # test seam: which path "auto" takes
    monkeypatch.setattr(
        hpr._LocalState,
        "visible",
        lambda self, *args: calls.append(self.size) or original(self, *args),
    )
    hidden_point_removal(points, radius=1e5)
    assert calls == [len(points)]


def test_copies_under_a_radius_too_large_for_a_hull_are_decided_once_each(monkeypatch):
    # R / range above 1e7: no hull; the per-point test runs on the one distinct point.
    copies = np.tile(np.float32([[10.0, 2.0, -1.0]]), (5000, 1))
    sizes = []
    original = hpr._local  # test seam: how many points the per-point test gets
    monkeypatch.setattr(
        hpr,
        "_local",
        lambda setup, *args: sizes.append(setup.size) or original(setup, *args),
    )
    assert hidden_point_removal(copies, radius=1e10).all()
    assert sizes == [1]
    sizes.clear()
    assert hidden_point_removal(copies, radius=100.0, method="reference").all()
    assert sizes == [1]  # a hull of one distinct point is degenerate: the fallback runs once


def test_inserted_scope_on_a_crowded_set_matches_the_reference(rng):
    points = np.concatenate([_tiny_sphere(rng, 3000), _tiny_sphere(rng, 3000, 0.05) + 0.3])
    inserted = np.zeros(len(points), dtype=bool)
    inserted[3000:] = True
    behind = ~inserted
    removed = hidden_by_insertion(points, inserted, behind, radius=100.0)
    expected = hidden_by_insertion(points, inserted, behind, radius=100.0, method="reference")
    np.testing.assert_array_equal(removed, expected)
