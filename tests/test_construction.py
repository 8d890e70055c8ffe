import numpy as np
import pytest

from drcpo.construction import (
    ConstructionConfig,
    _gather_partition_points,
    construct_object,
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
    grid = grid_for(name)
    counts = []
    for row in database.rows_of_class(name):
        points = database.object_points(row)
        points = mirror_points(points) if mirrored else points
        counts.append(partition_counts(points, database.boxes[row, 3:6], grid))
    return np.max(counts, axis=0)


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
    unmirrored = ConstructionConfig(max_iterations=0, mirrored_classes=())
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


@pytest.mark.parametrize("mode", ["partition", "whole"])
def test_same_seed_same_object(database, mode):
    config = ConstructionConfig(mode=mode)
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


def test_whole_mode_adds_whole_candidates_and_grows_the_box(database, rng):
    config = ConstructionConfig(mode="whole")
    row = 21
    cands = candidates_of(database, row)
    out = construct_object(database, row, cands, rng, config, class_max_counts(database, "Car"))
    assert 1 <= out.iterations <= config.max_iterations
    assert out.coverage >= out.coverage_initial
    expected = 2 * (database.num_points[row] + database.num_points[out.added_from].sum())
    assert len(out.points) == expected
    assert (out.dims >= database.boxes[row, 3:6]).all()
    assert (np.abs(out.points[:, :3]) <= out.dims / 2 + 1e-6).all()
    assert len(set(out.added_from.tolist())) == len(out.added_from)  # without replacement


def test_own_maximum_is_the_fallback_normalisation(database, rng):
    out = construct_object(database, 6, candidates_of(database, 6), rng, None, None)
    assert out.iterations >= 1
    assert out.coverage >= out.coverage_initial


def test_gather_kernel_matches_partition_index(database, rng):
    dims = np.array([3.7, 1.6, 1.4])
    grid = (10, 4, 3)
    rows = rng.integers(0, 60, 40)
    cells = rng.integers(0, 120, 40)
    for mirror in (False, True):
        got, per_pair = _gather_partition_points(
            np.asarray(database.points),
            database.offsets,
            rows.astype(np.int64),
            cells.astype(np.int64),
            dims,
            np.array(grid),
            mirror,
            0.05,
        )
        expected = []
        for row, cell in zip(rows, cells, strict=True):
            points = database.object_points(row)
            points = mirror_points(points) if mirror else points
            inside = (np.abs(points[:, :3].astype(np.float64)) <= dims / 2 + 0.05).all(axis=1)
            points = points[inside]
            expected.append(points[partition_index(points, dims, grid) == cell])
        np.testing.assert_array_equal(per_pair, [len(e) for e in expected])
        key = np.lexsort(got.T)
        want = np.concatenate(expected)
        np.testing.assert_array_equal(got[key], want[np.lexsort(want.T)])


def test_bad_input_is_rejected(database, rng):
    with pytest.raises(DataError, match="out of range"):
        construct_object(database, 0, [1, 2, len(database)], rng)
    with pytest.raises(DataError, match="out of range"):
        construct_object(database, len(database), [1], rng)
    with pytest.raises(DataError, match="integers"):
        construct_object(database, 0, [1.5], rng)
    with pytest.raises(DataError, match="partitions"):
        construct_object(database, 0, [1], rng, None, np.ones(7))
    with pytest.raises(ConfigError, match="construction.mode"):
        ConstructionConfig(mode="magic")
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
    from drcpo.database_build import build_database
    from drcpo.index import IndexConfig, build_index

    database = build_database(kitti_sample, "train", tmp_path / "db", classes="all")
    index = build_index(database, IndexConfig(workers=1))
    rng = np.random.default_rng(0)
    constructed = 0
    for row in range(len(database)):
        name = str(database.names[row])
        if name not in index.max_counts or database.num_points[row] < 5:
            continue
        cands = index.candidates_of(row)
        for mode in ("partition", "whole"):
            config = ConstructionConfig(mode=mode)
            out = construct_object(database, row, cands, rng, config, index.max_counts[name])
            assert set(out.added_from.tolist()) <= set(cands.tolist())
            assert out.coverage >= out.coverage_initial
            assert (np.abs(out.points[:, :3]) <= out.dims / 2 + config.margin + 1e-6).all()
            assert out.points.shape[1] == database.points.shape[1]
            constructed += 1
    assert constructed >= 4
