import numpy as np
import pytest

from drcpo.construction import (
    ConstructionConfig,
    _stored,
    construct_object,
    construct_objects,
)
from drcpo.construction_kernels import (
    _Box,  # test seam: the numba gather kernel, against partition_index
    _gather,
)
from drcpo.database import GroundTruthDatabase
from drcpo.errors import ConfigError, DataError
from drcpo.partitions import grid_for, mirror_points, partition_counts, partition_index

CAR = (4.0, 1.7, 1.5)
PEDESTRIAN = (0.8, 0.6, 1.75)


def partial_object(rng, dims, count):
    """Points on the surface of a box of size ``dims`` seen from one random side."""
    dims = np.asarray(dims)
    surface = rng.uniform(-0.5, 0.5, (count, 3)) * dims
    face = rng.integers(0, 3, count)
    surface[np.arange(count), face] = np.sign(rng.uniform(-1, 1, count)) * dims[face] / 2
    view = rng.normal(size=3) * [1, 1, 0]
    return surface[surface @ view > -0.1 * np.linalg.norm(view)]


def make_database(rng, classes=(("Car", CAR, 60), ("Pedestrian", PEDESTRIAN, 20)), features=1):
    """Objects of several classes; feature column 0 holds the object's row, 1.. are random."""
    chunks, boxes, names = [], [], []
    for name, base, count in classes:
        for _ in range(count):
            dims = np.asarray(base) * rng.uniform(0.9, 1.1, 3)
            xyz = partial_object(rng, dims, int(rng.integers(40, 400)))
            extra = rng.uniform(0, 1, (len(xyz), features - 1))
            row = np.full((len(xyz), 1), len(boxes))
            chunks.append(np.column_stack([xyz, row, extra]).astype(np.float32))
            boxes.append([0.0, 0.0, 0.0, *dims, 0.0])
            names.append(name)
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in chunks])])
    return GroundTruthDatabase.from_arrays(np.concatenate(chunks), offsets, names, boxes)


def class_max_counts(database, name, mirrored=True):
    return class_max_counts_for(database, name, grid_for(name), mirrored)


@pytest.fixture(scope="module")
def database():
    return make_database(np.random.default_rng(7))


def candidates_of(database, row):
    rows = database.rows_of_class(str(database.names[row]))
    return rows[rows != row]


def coverage_above(points, dims, grid, scale, threshold):
    """Fraction of fillable partitions whose density is above ``threshold``."""
    density = partition_counts(points, dims, grid) / np.where(scale > 0, scale, 1)
    return float(((density > threshold) & (scale > 0)).sum() / (scale > 0).sum())


@pytest.mark.parametrize("row", [0, 5, 17, 33])
def test_partition_mode_raises_coverage_and_respects_the_margin(database, rng, row):
    config = ConstructionConfig()
    scale = class_max_counts(database, "Car")
    out = construct_object(database, row, candidates_of(database, row), rng, config, scale)
    dims = database.boxes[row, 3:6]
    np.testing.assert_array_equal(out.dims, dims)
    assert out.coverage_initial < 0.6 and out.coverage >= config.coverage
    assert len(out.points) > 2 * database.num_points[row] or out.iterations == 0
    assert (np.abs(out.points[:, :3]) <= dims / 2 + config.margin + 1e-6).all()
    # The reported coverage is what the points show, against the source's initial threshold.
    source = mirror_points(database.object_points(row))
    initial_density = partition_counts(source, dims, (10, 4, 3)) / np.where(scale > 0, scale, 1)
    threshold = initial_density[(scale > 0) & (initial_density > 0)].mean()
    assert coverage_above(out.points, dims, (10, 4, 3), scale, threshold) == pytest.approx(
        out.coverage
    )
    assert coverage_above(source, dims, (10, 4, 3), scale, threshold) == pytest.approx(
        out.coverage_initial
    )


def test_iterations_are_recorded_and_capped(database, rng):
    scale = class_max_counts(database, "Car")
    capped = ConstructionConfig(max_iterations=2, coverage=1.0)
    out = construct_object(database, 3, candidates_of(database, 3), rng, capped, scale)
    assert out.iterations == 2
    off = ConstructionConfig(max_iterations=0)
    plain = construct_object(database, 3, candidates_of(database, 3), rng, off, scale)
    assert plain.iterations == 0
    assert len(plain.added_from) == 0
    np.testing.assert_array_equal(plain.points, mirror_points(database.object_points(3)))


def test_added_points_come_from_candidates_with_features_intact(database, rng):
    cands = candidates_of(database, 9)[:25]
    out = construct_object(database, 9, cands, rng, None, class_max_counts(database, "Car"))
    assert out.points.dtype == np.float32 and out.points.shape[1] == 4
    sources = np.unique(out.points[:, 3]).astype(int)
    assert set(sources) == {9, *out.added_from.tolist()}
    assert set(out.added_from.tolist()) <= set(cands.tolist())
    # Every point is a stored point of its object, possibly mirrored (y -> -y).
    for row in sources:
        stored = database.object_points(row)
        mine = out.points[out.points[:, 3] == row]
        known = {tuple(p) for p in mirror_points(stored).tolist()}
        assert all(tuple(p) in known for p in mine.tolist())


def test_many_feature_columns_pass_through(rng):
    database = make_database(rng, classes=(("Car", CAR, 12),), features=4)
    out = construct_object(database, 0, np.arange(1, 12), rng)
    assert out.points.shape[1] == 3 + 4
    stored = {tuple(p[3:]) for p in database.points.tolist()}
    assert all(tuple(p[3:]) in stored for p in out.points.tolist())


def test_only_mirrored_classes_are_mirrored(database, rng):
    car, pedestrian = 0, int(database.rows_of_class("Pedestrian")[0])
    config = ConstructionConfig(max_iterations=0)
    car_out = construct_object(database, car, [], rng, config)
    assert len(car_out.points) == 2 * database.num_points[car]
    ped_out = construct_object(database, pedestrian, [], rng, config)
    np.testing.assert_array_equal(ped_out.points, database.object_points(pedestrian))
    unmirrored = ConstructionConfig(max_iterations=0, mirror=())
    assert (
        len(construct_object(database, car, [], rng, unmirrored).points)
        == (database.num_points[car])
    )


def test_pedestrians_are_constructed_without_mirroring(database, rng):
    row = int(database.rows_of_class("Pedestrian")[0])
    scale = class_max_counts(database, "Pedestrian", mirrored=False)
    out = construct_object(database, row, candidates_of(database, row), rng, None, scale)
    assert out.coverage >= out.coverage_initial
    stored = {tuple(p) for p in database.points.tolist()}
    assert all(tuple(p) in stored for p in out.points.tolist())


@pytest.mark.parametrize("candidates", [[], [-1, -1, -1], np.zeros((0,), dtype=np.int32)])
def test_no_candidates_returns_the_mirrored_object(database, rng, candidates):
    out = construct_object(database, 4, candidates, rng)
    assert out.iterations == 0
    np.testing.assert_array_equal(out.points, mirror_points(database.object_points(4)))
    assert out.added_from.dtype == np.int64 and len(out.added_from) == 0


def test_padded_candidate_rows_skip_minus_one(database):
    cands = np.concatenate([candidates_of(database, 2)[:10], [-1] * 30]).astype(np.int32)
    a = construct_object(database, 2, cands, np.random.default_rng(1))
    b = construct_object(database, 2, cands[:10], np.random.default_rng(1))
    np.testing.assert_array_equal(a.points, b.points)


def test_same_seed_same_object(database):
    config = ConstructionConfig()
    cands = candidates_of(database, 11)
    runs = [
        construct_object(database, 11, cands, np.random.default_rng(s), config) for s in (5, 5, 6)
    ]
    np.testing.assert_array_equal(runs[0].points, runs[1].points)
    np.testing.assert_array_equal(runs[0].added_from, runs[1].added_from)
    assert runs[0].iterations == runs[1].iterations
    assert not np.array_equal(runs[0].added_from, runs[2].added_from) or not np.array_equal(
        runs[0].points, runs[2].points
    )


def test_own_maximum_is_the_fallback_normalisation(database, rng):
    out = construct_object(database, 6, candidates_of(database, 6), rng, None, None)
    assert out.iterations >= 1
    assert out.coverage >= out.coverage_initial


def test_gather_kernel_matches_partition_index(database, rng):
    dims = np.array([3.7, 1.6, 1.4])
    grid = (10, 4, 3)
    rows = rng.integers(0, 60, 40)
    cells = rng.integers(0, 120, 40)
    stored = _stored(database)
    for mirror in (False, True):
        refs, count, near = np.zeros(1, np.int64), 0, np.zeros(1, np.int64)
        per_pair = []
        for row, cell in zip(rows, cells, strict=True):
            box = _Box(dims, np.array(grid), 0.05, 2 if mirror else 1)
            refs, after, near = _gather(stored, row, cell, box, refs, count, near)
            per_pair.append(refs[count:after])
            count = after
        for row, cell, got in zip(rows, cells, per_pair, strict=True):
            own = np.arange(database.offsets[row], database.offsets[row + 1])
            # Each point, then its mirror image (odd reference), in stored order.
            want = np.stack([2 * own, 2 * own + 1], axis=1)[:, : 2 if mirror else 1]
            want = want.reshape(-1)
            np.testing.assert_array_equal(got, want[partition_mask(database, want, dims, cell)])


def partition_mask(database, refs, dims, cell, grid=(10, 4, 3), margin=0.05):
    """Which referenced points (``2 * row + mirrored``) lie in ``cell`` within the margin."""
    points = np.asarray(database.points)[refs >> 1].copy()
    points[refs & 1 == 1, 1] *= -1
    inside = (np.abs(points[:, :3].astype(np.float64)) <= dims / 2 + margin).all(axis=1)
    return inside & (partition_index(points, dims, grid) == cell)


def test_bad_input_is_rejected(database, rng):
    with pytest.raises(DataError, match="out of range"):
        construct_object(database, 0, [1, 2, len(database)], rng)
    with pytest.raises(DataError, match="out of range"):
        construct_object(database, len(database), [1], rng)
    with pytest.raises(DataError, match="integers"):
        construct_object(database, 0, [1.5], rng)
    with pytest.raises(DataError, match="partitions"):
        construct_object(database, 0, [1], rng, None, np.ones(7))
    with pytest.raises(ConfigError, match="construction.margin"):
        ConstructionConfig(margin=-0.1)
    with pytest.raises(ConfigError, match="construction.coverage"):
        ConstructionConfig(coverage=0)
    with pytest.raises(ConfigError, match="construction.max_iterations"):
        ConstructionConfig(max_iterations=-1)
    with pytest.raises(ConfigError, match="construction.margin"):
        ConstructionConfig(margin=-0.1)
    with pytest.raises(ConfigError, match="construction.grids.Car"):
        ConstructionConfig(grids={"Car": (10, 0, 3)})


def test_config_grids_and_padded_class_maxima(database, rng):
    config = ConstructionConfig(grids={"Car": (4, 2, 2)})
    assert config.grid("Car") == (4, 2, 2) and config.grid("Pedestrian") == (2, 2, 3)
    scale = np.zeros(120)
    scale[:16] = 50
    out = construct_object(database, 1, candidates_of(database, 1), rng, config, scale)
    assert out.coverage >= out.coverage_initial
    hash(config)  # frozen and hashable, so it can key caches


def test_real_kitti_database_with_its_index(kitti_sample, tmp_path):
    from drcpo.database.build import build_database
    from drcpo.index import IndexConfig
    from drcpo.index_build import build_index

    database = build_database(kitti_sample, "train", tmp_path / "db", classes="all")
    index = build_index(database, IndexConfig())
    rng = np.random.default_rng(0)
    constructed = 0
    for row in range(len(database)):
        name = str(database.names[row])
        if name not in index.max_counts or database.num_points[row] < 5:
            continue
        cands = index.candidates_of(row)
        config = ConstructionConfig()
        out = construct_object(database, row, cands, rng, config, index.max_counts[name])
        assert set(out.added_from.tolist()) <= set(cands.tolist())
        assert out.coverage >= out.coverage_initial
        assert (np.abs(out.points[:, :3]) <= out.dims / 2 + config.margin + 1e-6).all()
        assert out.points.shape[1] == database.points.shape[1]
        constructed += 1
    assert constructed >= 4


# The implementation before the compiled kernels (numpy, one object at a time), kept as the
# plain statement of what construct_object(s) must reproduce bit for bit: the same points in
# the same order, the same draws from the rng.


def reference_construct(database, row, candidate_rows, rng, config, class_max_counts):
    """``(points, dims, iterations, added_from, coverage_initial, coverage)``."""
    row = int(row) % len(database)
    name = str(database.names[row])
    dims = np.asarray(database.boxes[row, 3:6], dtype=np.float64)
    candidates = np.asarray(candidate_rows).reshape(-1)
    candidates = candidates[candidates >= 0].astype(np.int64)
    mirror = name in config.mirror
    grid = config.grid(name)
    source = np.asarray(database.object_points(row))
    source = mirror_points(source) if mirror else source.copy()
    source = source[reference_inside(source, dims, config.margin)]
    densities = ReferenceDensities(partition_counts(source, dims, grid), class_max_counts)
    initial = current = densities.coverage()
    chunks, contributors, iterations = [source], [], 0
    while candidates.size and iterations < config.max_iterations and current < config.coverage:
        deficient = densities.deficient()
        drawn = candidates[rng.integers(0, len(candidates), size=len(deficient))]
        per_pair = []
        for candidate, cell in zip(drawn, deficient, strict=True):
            points = np.asarray(database.object_points(int(candidate)))
            copies = [points, mirror_points(points)[len(points) :]] if mirror else [points]
            both = np.stack(copies, axis=1).reshape(-1, points.shape[1])
            keep = reference_inside(both, dims, config.margin)
            keep &= partition_index(both, dims, grid) == cell
            chunks.append(both[keep])
            per_pair.append(int(keep.sum()))
        per_pair = np.array(per_pair, dtype=np.int64)
        iterations += 1
        densities.counts[deficient] += per_pair
        contributors.append(drawn[per_pair > 0])
        current = densities.coverage()
    points = np.concatenate(chunks)
    out_dims = dims.copy()
    added_from = np.zeros(0, dtype=np.int64)
    if contributors:
        used = np.concatenate(contributors).astype(np.int64)
        added_from = used[np.sort(np.unique(used, return_index=True)[1])]
    return points, out_dims, iterations, added_from, initial, current


def reference_inside(points, dims, margin):
    return (np.abs(points[:, :3].astype(np.float64)) <= dims / 2.0 + margin).all(axis=1)


class ReferenceDensities:
    def __init__(self, counts, class_max_counts):
        n = len(counts)
        if class_max_counts is None:
            scale = np.full(n, float(max(counts.max(initial=0), 1)))
        else:
            scale = np.asarray(class_max_counts, dtype=np.float64).reshape(-1)[:n]
        self.fillable = scale > 0
        self.scale = np.where(self.fillable, scale, 1.0)
        self.counts = counts.astype(np.int64)
        density = self.counts / self.scale
        occupied = self.fillable & (self.counts > 0)
        # the mean summed in partition order, as the kernel sums it (numpy.mean sums pairwise)
        summed = np.cumsum(density[occupied])
        self.threshold = float(summed[-1] / len(summed)) if occupied.any() else 0.0

    def above(self):
        return self.fillable & (self.counts / self.scale > self.threshold)

    def coverage(self):
        fillable = int(self.fillable.sum())
        return float(self.above().sum() / fillable) if fillable else 1.0

    def deficient(self):
        return np.flatnonzero(self.fillable & ~self.above())


def assert_same_as_reference(out, expected):
    points, dims, iterations, added_from, initial, final = expected
    assert out.points.dtype == points.dtype
    np.testing.assert_array_equal(out.points, points)
    np.testing.assert_array_equal(out.dims, dims)
    assert out.iterations == iterations
    assert out.added_from.dtype == np.int64
    np.testing.assert_array_equal(out.added_from, added_from)
    assert (out.coverage_initial, out.coverage) == (initial, final)


REFERENCE_CONFIGS = [
    ConstructionConfig(),
    ConstructionConfig(mirror=()),
    ConstructionConfig(coverage=1.0, max_iterations=4),
    ConstructionConfig(max_iterations=0),
    # 160 partitions: a long sum for the threshold's mean
    ConstructionConfig(margin=0.0, grids={"Car": (10, 4, 4), "Pedestrian": (1, 1, 1)}),
]


def reference_case(database, config, seed, count=24):
    """Random objects, candidate lists (some empty, padded or repeating) and normalisers (the
    class maxima, some partitions never fillable, none at all, or the object's own)."""
    rng = np.random.default_rng(seed)
    rows = rng.integers(-len(database), len(database), count)
    candidates, scales = [], []
    for row in rows:
        pool = candidates_of(database, row % len(database))
        size = int(rng.integers(0, min(30, len(pool))))
        line = rng.choice(pool, size=size, replace=bool(rng.integers(0, 2)))
        if rng.uniform() < 0.2:
            line = np.concatenate([line, [-1] * 5])
        candidates.append(line if rng.uniform() > 0.1 else [-1, -1])
        name = str(database.names[row])
        mirrored = name in config.mirror
        scale = class_max_counts_for(database, name, config.grid(name), mirrored)
        kind = rng.integers(0, 4)
        if kind == 1:
            scale = np.where(rng.uniform(size=len(scale)) < 0.4, 0, scale)
        elif kind == 2:
            scale = np.zeros_like(scale)
        elif kind == 3:
            scale = None
        scales.append(scale)
    return rows, candidates, scales


def class_max_counts_for(database, name, grid, mirrored):
    counts = []
    for row in database.rows_of_class(name):
        points = database.object_points(row)
        points = mirror_points(points) if mirrored else points
        counts.append(partition_counts(points, database.boxes[row, 3:6], grid))
    return np.max(counts, axis=0)


@pytest.mark.parametrize(
    "config", REFERENCE_CONFIGS, ids=[f"config{k}" for k in range(len(REFERENCE_CONFIGS))]
)
def test_matches_the_reference_implementation(database, config):
    rows, candidates, scales = reference_case(database, config, REFERENCE_CONFIGS.index(config))
    expected_rng, single_rng, batch_rng = (np.random.default_rng(11) for _ in range(3))
    expected = [
        reference_construct(database, row, cands, expected_rng, config, scale)
        for row, cands, scale in zip(rows, candidates, scales, strict=True)
    ]
    batch = construct_objects(database, rows, candidates, batch_rng, config, scales)
    for k, (row, cands, scale) in enumerate(zip(rows, candidates, scales, strict=True)):
        single = construct_object(database, row, cands, single_rng, config, scale)
        assert_same_as_reference(single, expected[k])
        assert_same_as_reference(batch[k], expected[k])
    state = expected_rng.bit_generator.state
    assert single_rng.bit_generator.state == state == batch_rng.bit_generator.state
    if config.max_iterations:
        assert sum(e[2] for e in expected) > 0  # the case does construct


def test_points_on_cell_cuts_and_margins_match_the_reference():
    """Coordinates on the cuts between partitions and on the margin, and their float32
    neighbours, fall in the same partitions as numpy's cell rule puts them."""
    rng = np.random.default_rng(3)
    dims, grid, margin = np.array([4.0, 1.7, 1.5]), (10, 4, 3), 0.05
    axes = []
    for d, n in zip(dims, grid, strict=True):
        cuts = np.concatenate([np.arange(n + 1) * d / n - d / 2, [-d / 2 - margin, d / 2 + margin]])
        near = np.float32(cuts)
        axes.append(
            np.concatenate([near, np.nextafter(near, np.float32(-9)), np.nextafter(near, 9)])
        )
    chunks = [
        np.column_stack([rng.choice(a, 150) for a in axes] + [np.full(150, k)]).astype(np.float32)
        for k in range(12)
    ]
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in chunks])])
    boxes = np.tile([0.0, 0.0, 0.0, *dims, 0.0], (12, 1))
    edge = GroundTruthDatabase.from_arrays(np.concatenate(chunks), offsets, ["Car"] * 12, boxes)
    for config in (ConstructionConfig(coverage=1.0), ConstructionConfig(margin=0.0)):
        for row in range(12):
            cands = np.delete(np.arange(12), row)
            scale = np.full(120, 30.0)
            a, b = np.random.default_rng(row), np.random.default_rng(row)
            expected = reference_construct(edge, row, cands, a, config, scale)
            assert_same_as_reference(construct_object(edge, row, cands, b, config, scale), expected)


def test_batches_take_the_index_layout_and_class_maxima_by_name(database):
    rows = np.array([3, 61, 7, 70, 3])
    width = 12
    padded = np.full((len(rows), width), -1, dtype=np.int32)
    lines = [candidates_of(database, row)[: 2 + 2 * k] for k, row in enumerate(rows)]
    for k, line in enumerate(lines):
        padded[k, : len(line)] = line
    maxima = {"Car": class_max_counts(database, "Car")}  # Pedestrian: their own maxima
    scales = [maxima.get(str(database.names[row])) for row in rows]
    a, b = np.random.default_rng(4), np.random.default_rng(4)
    batch = construct_objects(database, rows, padded, a, None, maxima)
    for k, row in enumerate(rows):
        single = construct_object(database, row, lines[k], b, None, scales[k])
        np.testing.assert_array_equal(batch[k].points, single.points)
        np.testing.assert_array_equal(batch[k].added_from, single.added_from)
        assert batch[k].coverage == single.coverage
    assert a.bit_generator.state == b.bit_generator.state
    assert construct_objects(database, [], np.zeros((0, 5), np.int32), a) == []
    with pytest.raises(DataError, match="candidate lists"):
        construct_objects(database, rows, padded[:2], a)
    with pytest.raises(DataError, match="class_max_counts"):
        construct_objects(database, rows, padded, a, None, [None])


def test_threshold_is_the_mean_density_within_rounding():
    # The kernel sums in partition order, numpy.mean pairwise: the same mean to rounding.
    from drcpo.construction_kernels import _threshold

    rng = np.random.default_rng(3)
    for n in (0, 1, 7, 8, 120, 160, 700):
        counts = rng.integers(0, 60, n)
        scale = rng.integers(0, 80, n).astype(np.float64)
        fillable = scale > 0
        scale[~fillable] = 1.0
        occupied = fillable & (counts > 0)
        want = (counts[occupied] / scale[occupied]).mean() if occupied.any() else 0.0
        assert _threshold(counts, scale, fillable) == pytest.approx(want, rel=1e-14, abs=0)
