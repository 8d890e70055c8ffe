"""The partition cell rule (drcpo.partitions.cell_of / flat_cell) against a naive reference, and
every former copy of it (the candidate index's occupancy, iterative construction's kernels)
against the rule, on adversarial values: points exactly on cell borders and faces, their float
neighbours, beyond the faces, large values, float32 inputs and NaN."""

import math

import numpy as np
import pytest

from drcpo.construction_kernels import _add_source, _Box, _gather, _Stored
from drcpo.database import GroundTruthDatabase
from drcpo.index_build import partition_occupancy
from drcpo.partitions import (
    cell_of,
    flat_cell,
    mirror_points,
    num_partitions,
    partition_counts,
    partition_index,
)

# Sizes and counts whose cell borders are exact in float32 and ones whose borders are not.
SIZES = (4.0, 3.0, 3.7, 1.6, 0.3, 1e-3)
COUNTS = (1, 2, 3, 4, 7, 10)
GRIDS = ((10, 4, 3), (4, 2, 3), (2, 2, 3), (1, 1, 1), (7, 3, 5))
DIMS = ((4.0, 1.6, 1.5), (3.7, 1.6, 1.4), (3.0, 0.3, 1.7), (1e-3, 2.0, 0.75))


def naive_cell(value, size, count):
    """The rule written out in plain Python floats: ``floor((value + size/2) / size * count)``
    clipped to ``[0, count - 1]``; a floor outside int64 (and NaN) is cell 0, as numpy's cast of
    such values to int64 (int64's minimum on x86) then clipped gives."""
    scaled = (float(value) + size / 2.0) / size * count
    if scaled != scaled or not -(2.0**63) <= math.floor(scaled) < 2.0**63:
        return 0
    return min(max(math.floor(scaled), 0), count - 1)


def naive_flat(point, dims, grid):
    cells = [naive_cell(point[a], float(dims[a]), int(grid[a])) for a in range(3)]
    return (cells[0] * grid[1] + cells[1]) * grid[2] + cells[2]


def border_values(size, count, dtype=np.float64):
    """Every cell border and face of one axis, their float neighbours (in ``dtype``), points
    beyond the faces, large values and NaN."""
    borders = np.array([k * size / count - size / 2.0 for k in range(count + 1)])
    borders = borders.astype(dtype)
    up = np.nextafter(borders, dtype(np.inf))
    down = np.nextafter(borders, dtype(-np.inf))
    far = np.array([1.5, -1.5, 1e3, -1e3]) * size
    large = np.array([1e6, -1e6, 1e12, -1e12, 1e18, -1e18, 1e19, -1e19, 1e300, -1e300])
    values = np.concatenate([borders, up, down, far.astype(dtype), [0.0, -0.0, np.nan]])
    if dtype == np.float64:
        values = np.concatenate([values, large])
    return values.astype(dtype)


def adversarial_points(dims, grid, dtype, rng, finite=False):
    """``(N, 4)`` canonical points whose coordinates are each axis's border values, mixed."""
    axes = [border_values(float(dims[a]), int(grid[a]), dtype) for a in range(3)]
    if finite:
        axes = [a[np.isfinite(a) & (np.abs(a) < 1e6)] for a in axes]
    n = 3 * max(len(a) for a in axes)
    xyz = np.column_stack([rng.choice(a, n) for a in axes])
    # Also each axis's values with the other two at the centre (one border at a time).
    for a, values in enumerate(axes):
        single = np.zeros((len(values), 3), dtype)
        single[:, a] = values
        xyz = np.concatenate([xyz, single])
    return np.column_stack([xyz, rng.random(len(xyz))]).astype(dtype)


def test_cell_of_matches_the_naive_rule():
    for size in SIZES:
        for count in COUNTS:
            for dtype in (np.float64, np.float32):
                for value in border_values(size, count, dtype):
                    got = cell_of(np.float64(value), size, np.int64(count))
                    assert got == naive_cell(value, size, count), (value, size, count)


def test_cell_rule_boundaries_belong_to_the_upper_cell():
    # Exact borders (4 m in 8 cells: multiples of 0.5 m): the upper cell; faces: outermost.
    assert [cell_of(v, 4.0, 8) for v in (-2.0, -1.5, -0.5, 0.0, 1.5, 2.0)] == [0, 1, 3, 4, 7, 7]
    assert cell_of(np.nextafter(-1.5, -2.0), 4.0, 8) == 0
    assert cell_of(-7.0, 4.0, 8) == 0 and cell_of(7.0, 4.0, 8) == 7


def test_partition_index_and_counts_follow_the_rule(rng):
    for dims in DIMS:
        for grid in GRIDS:
            for dtype in (np.float64, np.float32):
                points = adversarial_points(dims, grid, dtype, rng)
                want = np.array([naive_flat(p, dims, grid) for p in points])
                np.testing.assert_array_equal(partition_index(points, dims, grid), want)
                np.testing.assert_array_equal(
                    partition_counts(points, dims, grid),
                    np.bincount(want, minlength=num_partitions(grid)),
                )
                assert (
                    flat_cell(*points[0, :3].astype(np.float64), dims, np.asarray(grid)) == want[0]
                )


def test_index_occupancy_follows_the_rule(rng):
    objects, boxes, names = [], [], []
    for dims in DIMS:
        for grid in GRIDS[:3]:
            objects.append(adversarial_points(dims, grid, np.float32, rng, finite=True))
            boxes.append([0.0, 0.0, 0.0, *dims, 0.0])
            names.append(("Car", "Pedestrian", "Cyclist")[len(names) % 3])
    grids = {"Car": GRIDS[0], "Pedestrian": GRIDS[1], "Cyclist": GRIDS[2]}
    offsets = np.concatenate([[0], np.cumsum([len(o) for o in objects])])
    db = GroundTruthDatabase.from_arrays(np.concatenate(objects), offsets, names, boxes)
    for mirrored in ((), ("Car", "Cyclist")):
        counts = partition_occupancy(db, grids, mirrored, chunk_points=50)
        for i, name in enumerate(names):
            points = db.object_points(i)
            if name in mirrored:
                points = mirror_points(points)
            grid = grids[name]
            want = np.bincount(
                [naive_flat(p, boxes[i][3:6], grid) for p in points],
                minlength=counts.shape[1],
            )
            np.testing.assert_array_equal(counts[i], want)


def construction_inputs(dims, grid, rng):
    points = adversarial_points(dims, grid, np.float32, rng)
    return points, np.array([0, len(points)], np.int64), np.asarray(dims), np.asarray(grid)


def mirrored_refs(points, copies):
    """Per reference ``2 * i + mirrored``, its point (y negated for mirror images)."""
    refs = np.arange(2 * len(points)).reshape(-1, 2)[:, :copies].reshape(-1)
    out = points[refs >> 1].astype(np.float64)
    out[refs & 1 == 1, 1] *= -1
    return refs, out


@pytest.mark.parametrize("copies", [1, 2])
def test_construction_kernels_follow_the_rule(rng, copies):
    margin = 0.05
    for dims in DIMS:
        for grid in GRIDS:
            points, offsets, d, g = construction_inputs(dims, grid, rng)
            stored = _Stored(points, offsets)
            refs, shown = mirrored_refs(points, copies)
            cells = np.array([naive_flat(p, dims, grid) for p in shown])
            near = (np.abs(shown[:, :3]) <= d / 2.0 + margin).all(axis=1)
            p = num_partitions(grid)
            # the source: points within the margin of the box
            box = _Box(d, g, margin, copies)
            counts = np.zeros(p, np.int64)
            _add_source(stored, 0, box, counts, np.zeros(1, np.int64), 0)
            np.testing.assert_array_equal(counts, np.bincount(cells[near], minlength=p))
            # a candidate's points in one cell (the band shortcut at borders)
            for cell in range(p):
                got, n_refs, _ = _gather(
                    stored, 0, cell, box, np.zeros(1, np.int64), 0, np.zeros(1, np.int64)
                )
                want = refs[near & (cells == cell)]
                np.testing.assert_array_equal(got[:n_refs], want)  # in stored order
