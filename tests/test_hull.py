"""Tests for drcpo.occlusion.hull: the certified HPR hull against Qhull (and Open3D's
fixtures), its handling of copies, and the inputs it leaves to the general path."""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull, QhullError

from drcpo.occlusion.hull import hpr_hull_visible

ORIGIN = np.zeros(3)


def qhull_visible(points: np.ndarray, center: np.ndarray, radius: float) -> np.ndarray | None:
    """Open3D's HPR with scipy's Qhull: hull of the distinct flipped points and the viewpoint;
    copies share their point's verdict. ``None`` where Qhull fails."""
    rel = np.asarray(points, dtype=np.float64)[:, :3] - center
    distinct, inverse = np.unique(rel, axis=0, return_inverse=True)
    ranges = np.sqrt(np.einsum("ij,ij->i", distinct, distinct))
    flipped = distinct + distinct * (2.0 * (radius - ranges) / ranges)[:, None]
    try:
        hull = ConvexHull(np.vstack([flipped, np.zeros((1, 3))]))
    except QhullError:
        return None
    vertex = np.zeros(len(distinct) + 1, dtype=bool)
    vertex[hull.vertices] = True
    return vertex[:-1][inverse.ravel()]


def lidar_object(rng: np.random.Generator, count: int) -> tuple[np.ndarray, float]:
    """A box-shaped object's surface points (float32, with an intensity column) somewhere in a
    KITTI-like scene, and its s-HPR radius (200 x the box diagonal)."""
    dims = rng.uniform([0.5, 0.5, 1.0], [5.0, 2.5, 3.0])
    local = rng.uniform(-0.5, 0.5, (count, 3)) * dims
    face = rng.integers(0, 3, count)
    local[np.arange(count), face] = rng.choice([-0.5, 0.5], count) * dims[face]
    local += rng.normal(0.0, 0.01, local.shape)
    yaw, distance, azimuth = rng.uniform(-np.pi, np.pi), rng.uniform(4.0, 60.0), rng.uniform(-3, 3)
    cos, sin = np.cos(yaw), np.sin(yaw)
    xyz = np.column_stack(
        [
            cos * local[:, 0] - sin * local[:, 1] + distance * np.cos(azimuth),
            sin * local[:, 0] + cos * local[:, 1] + distance * np.sin(azimuth),
            local[:, 2] - 1.7 + dims[2] / 2,
        ]
    )
    points = np.column_stack([xyz, rng.uniform(0, 1, count)]).astype(np.float32)
    return points, 200.0 * float(np.linalg.norm(dims))


def test_equals_qhull_on_objects():
    rng = np.random.default_rng(7)
    certified = 0
    for _ in range(40):
        points, radius = lidar_object(rng, int(rng.integers(20, 1500)))
        got = hpr_hull_visible(points, ORIGIN, radius)
        if got is None:
            continue
        certified += 1
        expected = qhull_visible(points, ORIGIN, radius)
        assert 0 < got.sum() < len(points)
        np.testing.assert_array_equal(got, expected)
    assert certified >= 38  # close calls are rare on real-looking objects


def test_matches_open3d_object_fixtures(hpr_fixtures):
    files = sorted(hpr_fixtures.glob("object*.npz"))
    assert files
    for path in files:
        with np.load(path, allow_pickle=False) as data:
            expected = np.zeros(len(data["points"]), dtype=bool)
            expected[data["visible"]] = True
            got = hpr_hull_visible(data["points"], data["viewpoint"], float(data["radius"]))
        assert got is not None, path.name
        np.testing.assert_array_equal(got, expected, err_msg=path.name)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    count=st.integers(4, 200),
    spacing=st.sampled_from([0.0, 0.05, 0.5]),
    copies=st.integers(0, 10),
    log_radius=st.floats(1.0, 12.0),
)
def test_answers_only_what_qhull_says(seed, count, spacing, copies, log_radius):
    # Blobs, lattices (many coplanar quadruples) and exact copies, near and far R.
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(count, 3)) * rng.uniform(0.1, 3.0, 3)
    if spacing:
        points = np.round(points / spacing) * spacing
    points += [rng.uniform(3.0, 40.0), rng.uniform(-5.0, 5.0), rng.uniform(-2.0, 2.0)]
    points = np.vstack([points, points[rng.integers(0, count, copies)]])
    radius = 10.0**log_radius
    got = hpr_hull_visible(points, ORIGIN, radius)
    if got is not None:
        np.testing.assert_array_equal(got, qhull_visible(points, ORIGIN, radius))


def test_huge_radius_keeps_every_point_as_qhull_does():
    rng = np.random.default_rng(8)
    points, _ = lidar_object(rng, 300)
    for radius in (1e9, 1e12, 1e15):
        got = hpr_hull_visible(points, ORIGIN, radius)
        assert got is not None and got.all()
        np.testing.assert_array_equal(got, qhull_visible(points, ORIGIN, radius))


def test_exact_copies_take_their_verdict():
    rng = np.random.default_rng(3)
    points, radius = lidar_object(rng, 800)
    once = hpr_hull_visible(points, ORIGIN, radius)
    assert once is not None
    rows = np.concatenate([np.flatnonzero(once)[:20], np.flatnonzero(~once)[:20]])
    doubled = np.vstack([points, points[rows], points[rows[::2]]])
    got = hpr_hull_visible(doubled, ORIGIN, radius)
    assert got is not None
    np.testing.assert_array_equal(got[: len(points)], once)
    np.testing.assert_array_equal(got[len(points) :], np.concatenate([once[rows], once[rows[::2]]]))


def test_order_dtype_and_features_do_not_matter():
    rng = np.random.default_rng(4)
    points, radius = lidar_object(rng, 600)
    base = hpr_hull_visible(points, ORIGIN, radius)
    order = rng.permutation(len(points))
    np.testing.assert_array_equal(hpr_hull_visible(points[order], ORIGIN, radius), base[order])
    as_float64 = points[:, :3].astype(np.float64)
    np.testing.assert_array_equal(hpr_hull_visible(as_float64, ORIGIN, radius), base)
    viewpoint = np.array([0.5, -1.0, 1.5])
    moved = as_float64 + viewpoint
    np.testing.assert_array_equal(hpr_hull_visible(moved, viewpoint, radius), base)


def test_gives_up_where_the_general_path_decides():
    rng = np.random.default_rng(5)
    points, radius = lidar_object(rng, 300)
    xyz = points[:, :3].astype(np.float64)
    assert hpr_hull_visible(xyz[:3], ORIGIN, radius) is None  # no 3-D hull
    at_viewpoint = np.vstack([xyz, np.zeros((1, 3))])
    assert hpr_hull_visible(at_viewpoint, ORIGIN, radius) is None
    broken = xyz.copy()
    broken[7, 1] = np.nan
    assert hpr_hull_visible(broken, ORIGIN, radius) is None
    assert hpr_hull_visible(xyz, ORIGIN, 0.4 * np.linalg.norm(xyz, axis=1).max()) is None
    assert hpr_hull_visible(xyz, ORIGIN, radius, max_ratio=1.0) is None
    around = np.vstack([xyz, -xyz])  # around the viewpoint: not one cone
    assert hpr_hull_visible(around, ORIGIN, radius) is None
    flat = xyz.copy()
    flat[:, 2] = 0.0  # every point in one plane with the viewpoint
    assert hpr_hull_visible(flat, ORIGIN, radius) is None


def test_threads_give_the_same_answers():
    rng = np.random.default_rng(6)
    jobs = [lidar_object(rng, int(rng.integers(100, 1200))) for _ in range(12)]
    alone = [hpr_hull_visible(p, ORIGIN, r) for p, r in jobs]
    with ThreadPoolExecutor(max_workers=2) as pool:
        together = list(pool.map(lambda job: hpr_hull_visible(job[0], ORIGIN, job[1]), jobs))
    for a, b in zip(alone, together, strict=True):
        assert a is not None
        np.testing.assert_array_equal(a, b)


# --------------------------------------------------------------------------------------------
# The insertion order (drcpo.occlusion.hull_order) against a naive reference
# --------------------------------------------------------------------------------------------
def test_hilbert_rank_walks_from_each_cell_to_a_neighbour():
    from drcpo.occlusion.hull_order import _hilbert_rank

    for side in (1, 2, 4, 8, 32):
        rank = _hilbert_rank(side)
        assert sorted(rank.tolist()) == list(range(side * side))  # a walk through every cell
        row, col = np.divmod(np.argsort(rank), side)  # the cells in walk order
        assert (np.abs(np.diff(row)) + np.abs(np.diff(col)) == 1).all()
        assert rank[0] == 0  # starting in a corner


def naive_insertion_order(flipped, ranges, radius, axis):
    """The order by its definition, one point at a time in Python floats: each point's
    coordinates (u, v) across the unit mean direction (on e1, the coordinate axis least
    aligned with it made orthogonal, and e2 = direction x e1); empty when a point lies 84
    degrees or more from the direction or the first three do not span a triangle. Then the
    extremes of u (first of equals), the point farthest from their line, the nearest point
    (least range, first of equals) of each coarse cell in the cells' boustrophedon order,
    and every other point by its fine cell's Hilbert rank, then by index."""
    from drcpo.occlusion.hull_order import _HILBERT_RANK, _HILBERT_SIDE

    n = len(ranges)
    norm = math.sqrt(axis[0] ** 2 + axis[1] ** 2 + axis[2] ** 2)
    if not norm > 0.0:
        return []
    d = [axis[0] / norm, axis[1] / norm, axis[2] / norm]
    k = min(range(3), key=lambda a: abs(d[a]))  # first of equals: x, then y
    e1 = [(1.0 if a == k else 0.0) - d[k] * d[a] for a in range(3)]
    norm = math.sqrt(e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2])
    e1 = [e / norm for e in e1]
    e2 = [d[1] * e1[2] - d[2] * e1[1], d[2] * e1[0] - d[0] * e1[2], d[0] * e1[1] - d[1] * e1[0]]
    rows = flipped[:n].tolist()
    u, v = [], []
    for i, p in enumerate(rows):
        if not p[0] * d[0] + p[1] * d[1] + p[2] * d[2] > 0.1 * (2.0 * radius - ranges[i]):
            return []
        u.append(p[0] * e1[0] + p[1] * e1[1] + p[2] * e1[2])
        v.append(p[0] * e2[0] + p[1] * e2[1] + p[2] * e2[2])
    a, b = u.index(min(u)), u.index(max(u))
    du, dv = u[b] - u[a], v[b] - v[a]
    off = [abs(du * (v[i] - v[a]) - dv * (u[i] - u[a])) for i in range(n)]
    c = off.index(max(off))
    if a == b or c in (a, b):
        return []
    side, fine = max(1, int(math.sqrt(n / 16.0))), _HILBERT_SIDE
    su = 1.0 / max(du, 1e-300) * (1.0 - 1e-9)
    sv = 1.0 / max(max(v) - min(v), 1e-300) * (1.0 - 1e-9)
    nearest, coarse, fine_rank = {}, [], []
    for i in range(n):
        x, y = (u[i] - u[a]) * su, (v[i] - min(v)) * sv
        row, col = min(side - 1, int(x * side)), min(side - 1, int(y * side))
        cell = row * side + (side - 1 - col if row % 2 else col)
        coarse.append(cell)
        if cell not in nearest or ranges[i] < ranges[nearest[cell]]:
            nearest[cell] = i
        fine_rank.append(
            _HILBERT_RANK[min(fine - 1, int(x * fine)) * fine + min(fine - 1, int(y * fine))]
        )
    first = [a, b, c] + [nearest[k] for k in sorted(nearest) if nearest[k] not in (a, b, c)]
    rest = [i for i in range(n) if i not in (a, b, c) and nearest[coarse[i]] != i]
    return first + sorted(rest, key=lambda i: (fine_rank[i], i))


def flip(points, radius):
    """Ranges and flipped points (the viewpoint at the origin, appended), as the hull flips."""
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    ranges = np.sqrt(xyz[:, 0] * xyz[:, 0] + xyz[:, 1] * xyz[:, 1] + xyz[:, 2] * xyz[:, 2])
    flipped = xyz + xyz * (2.0 * (radius - ranges) / ranges)[:, None]
    return np.vstack([flipped, np.zeros((1, 3))]), ranges


def test_insertion_order_follows_the_naive_order():
    from drcpo.occlusion.hull_order import _insertion_order

    rng = np.random.default_rng(9)
    cases = [lidar_object(rng, int(count)) for count in (4, 17, 300, 2000)]
    lattice = np.indices((8, 8, 3)).reshape(3, -1).T * 0.25 + [10.0, -1.0, -1.0]  # ties in u
    cases.append((lattice, 1e4))
    ranged = lidar_object(rng, 200)[0][:, :3].astype(np.float64)
    cases.append((np.vstack([ranged, ranged[:50]]), 1e3))  # copies: equal ranges, equal u
    cases.append((np.vstack([ranged, [[-10.0, 0.0, 0.0]]]), 1e3))  # one point behind: empty
    cases.append((np.tile(ranged[:1], (6, 1)), 1e3))  # all one point: no triangle, empty
    cases.append((np.array([[5.0, 0, 0], [6, 0, 0], [7, 0, 0], [8, 0, 0]]), 1e3))  # one line
    for points, radius in cases:
        flipped, ranges = flip(points, radius)
        for axis in (flipped[:-1].sum(axis=0), np.array([1.0, 0.0, 0.0]), np.zeros(3)):
            want = naive_insertion_order(flipped, ranges.tolist(), radius, axis.tolist())
            got = _insertion_order(flipped, ranges, radius, axis)
            np.testing.assert_array_equal(got, np.array(want, dtype=np.int64))
            if want:
                assert sorted(want) == list(range(len(ranges)))  # a permutation
