import dataclasses
import json

import numpy as np
import pytest

from drcpo.database import GroundTruthDatabase
from drcpo.errors import ConfigError, DataError
from drcpo.geometry import canonical_iou3d
from drcpo.index import CandidateIndex, IndexConfig, load_index
from drcpo.index_build import build_index, indexed_mask, partition_occupancy
from drcpo.partitions import grid_for, mirror_points, num_partitions, partition_counts
from drcpo.similarity import SimilaritySearch, similarity_recall

CLASSES = ("Car", "Pedestrian", "Cyclist", "Van")


def random_database(rng, n, classes=CLASSES, step=0.25, max_points=60, point_dim=4):
    """Objects with sizes on a coarse lattice (many exact IoU ties) and points partly outside."""
    names = rng.choice(np.asarray(classes), n)
    base = {"Car": (3.9, 1.6, 1.5), "Pedestrian": (0.8, 0.6, 1.7), "Cyclist": (1.7, 0.6, 1.7)}
    dims = np.array([base.get(str(c), (2.0, 1.0, 1.0)) for c in names])
    dims = dims * rng.uniform(0.6, 1.4, (n, 3))
    dims = np.maximum(np.round(dims / step) * step, step)
    sizes = rng.integers(0, max_points, n)
    sizes[rng.random(n) < 0.1] = 0
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    owner = np.repeat(np.arange(n), sizes)
    xyz = rng.uniform(-0.6, 0.6, (len(owner), 3)) * dims[owner]
    # Points exactly on inner cell boundaries and on the faces exercise the cell rule.
    snap = rng.random(len(owner)) < 0.2
    xyz[snap] = np.round(xyz[snap] / (dims[owner][snap] / 4)) * (dims[owner][snap] / 4)
    points = np.column_stack([xyz, rng.random((len(owner), point_dim - 3))]).astype(np.float32)
    boxes = np.column_stack([rng.normal(size=(n, 3)), dims, rng.uniform(-3, 3, n)])
    difficulty = rng.integers(-1, 3, n).astype(np.int8)
    return GroundTruthDatabase.from_arrays(points, offsets, names, boxes, difficulty=difficulty)


def reference_index(db, config):
    """Brute force: full N x N IoU matrices and per-object partition counts."""
    n = len(db)
    keep = indexed_mask(db, config)
    classes = sorted(set(db.names.tolist()))
    p_max = max(num_partitions(grid_for(c, config.grids)) for c in classes)
    counts = np.zeros((n, p_max), np.int64)
    for i in range(n):
        name = str(db.names[i])
        grid = grid_for(name, config.grids)
        pts = db.object_points(i)
        if name in config.mirror:
            pts = mirror_points(pts)
        counts[i, : num_partitions(grid)] = partition_counts(pts, db.boxes[i, 3:6], grid)
    densities = np.zeros((n, p_max), np.float32)
    candidates = np.full((n, config.k), -1, np.int32)
    for name in classes:
        p = num_partitions(grid_for(name, config.grids))
        rows = np.flatnonzero(db.names == name)
        idx = rows[keep[rows]]
        top = counts[idx, :p].max(axis=0) if len(idx) else np.zeros(p)
        with np.errstate(invalid="ignore", divide="ignore"):
            densities[rows, :p] = np.where(top > 0, counts[rows, :p] / top, 0.0)
        dims = db.boxes[idx, 3:6]
        iou = canonical_iou3d(dims[:, None, :], dims[None, :, :])
        dens = densities[idx, :p].astype(np.float64)
        for a, row in enumerate(idx):
            others = np.flatnonzero(np.arange(len(idx)) != a)
            first = others[np.lexsort((idx[others], -iou[a, others]))][: 2 * config.k]
            d = dens[a]
            filled = d > 0
            low = d < config.alpha * (d[filled].sum() / filled.sum()) if filled.any() else ~filled
            score = dens[first][:, low].sum(axis=1)
            second = first[np.lexsort((np.arange(len(first)), -score))][: config.k]
            candidates[row, : len(second)] = idx[second]
    return candidates, densities


@pytest.mark.parametrize(
    ("seed", "n", "k", "extra"),
    [
        (0, 300, 5, {}),
        (1, 400, 40, {"exclude_difficulty": (-1,), "min_points": 10}),
        (2, 250, 400, {}),  # every class smaller than K: all candidates
        (3, 500, 12, {"grids": {"Van": (3, 3, 2)}, "mirror": ("Pedestrian",), "alpha": 1.0}),
    ],
)
def test_matches_brute_force(seed, n, k, extra):
    db = random_database(np.random.default_rng(seed), n)
    config = IndexConfig(k=k, block_size=37, **extra)
    index = build_index(db, config)
    ref_candidates, ref_densities = reference_index(db, config)
    np.testing.assert_array_equal(index.densities, ref_densities)
    np.testing.assert_array_equal(index.candidates, ref_candidates)


def test_large_class_with_many_ties_matches_brute_force():
    # Coarse sizes: thousands of objects share a handful of boxes, so IoU ties are everywhere.
    db = random_database(np.random.default_rng(7), 2500, classes=("Car",), step=0.2)
    config = IndexConfig(k=30)
    index = build_index(db, config)
    ref_candidates, ref_densities = reference_index(db, config)
    np.testing.assert_array_equal(index.densities, ref_densities)
    np.testing.assert_array_equal(index.candidates, ref_candidates)


def test_many_identical_boxes_match_brute_force(rng):
    # Only the lowest rows of each group of identical boxes are searchable; the result must
    # not change.
    db = random_database(rng, 3000, classes=("Car",), step=1.0)
    assert len(np.unique(db.boxes[:, 3:6], axis=0)) < 30
    config = IndexConfig(k=20)
    index = build_index(db, config)
    ref_candidates, _ = reference_index(db, config)
    np.testing.assert_array_equal(index.candidates, ref_candidates)


def test_grid_search_first_stage_is_exact_on_continuous_sizes(rng):
    dims = np.exp(rng.normal([1.36, 0.48, 0.42], [0.11, 0.06, 0.09], (3000, 3)))
    dims[::10] = dims[1::10]  # exact duplicates
    search = SimilaritySearch(dims, 64)
    assert search.shape.prod() > 1
    queries = np.arange(0, 3000, 7)
    ids, ious = search.top(queries)
    iou = canonical_iou3d(dims[queries][:, None], dims[None])
    for b, q in enumerate(queries):
        iou[b, q] = -1
        expected = np.lexsort((np.arange(len(dims)), -iou[b]))[:64]
        np.testing.assert_array_equal(ids[b], expected)
        np.testing.assert_array_equal(ious[b], iou[b, expected])


def test_approximate_mode_ranks_its_neighbours_as_the_naive_sort(rng):
    # The approximate first stage: the L1 nearest neighbours in log-size space (the tree's
    # answer, taken as given), then the best s of them but the query itself by canonical IoU,
    # ties to the lower id; -1 where fewer than s remain.
    dims = np.round(np.exp(rng.normal([1.36, 0.48, 0.42], [0.11, 0.06, 0.09], (1500, 3))), 1)
    dims[:40] = dims[40]  # a large group of identical boxes: only some are searchable
    for s, factor in ((8, 1.5), (30, 1.0), (1, 3.0)):
        search = SimilaritySearch(dims, s, mode="approximate", approx_factor=factor)
        queries = np.concatenate([np.arange(0, 60), rng.integers(0, len(dims), 100)])
        ids, ious = search.top(queries)
        _, near = search.tree.query(search.u[queries], k=search.neighbours, p=1)
        for b, q in enumerate(queries):
            others = search.pool[near[b].reshape(-1)]
            others = others[others != q]
            iou = canonical_iou3d(dims[q], dims[others])
            best = np.lexsort((others, -iou))[:s]
            want_ids = np.full(s, -1)
            want_ids[: len(best)] = others[best]
            want_ious = np.full(s, -1.0)
            want_ious[: len(best)] = iou[best]
            np.testing.assert_array_equal(ids[b], want_ids)
            np.testing.assert_array_equal(ious[b], want_ious)
    # Fewer neighbours than s (a tree over two objects): the rest is padding.
    few = SimilaritySearch(np.array([[1.0, 1.0, 1.0], [2.0, 1.0, 1.0]]), 1, mode="approximate")
    few.neighbours = 1  # only the query itself comes back
    np.testing.assert_array_equal(few.top(np.array([0, 1]))[0], [[-1], [-1]])


def test_blocks_do_not_change_the_result():
    db = random_database(np.random.default_rng(4), 600)
    one = build_index(db, IndexConfig(k=20, block_size=1000))
    two = build_index(db, IndexConfig(k=20, block_size=16))
    np.testing.assert_array_equal(one.candidates, two.candidates)


def test_objects_below_min_points_or_excluded_are_never_candidates():
    db = random_database(np.random.default_rng(5), 400)
    config = IndexConfig(k=50, min_points=20, exclude_difficulty=(0,))
    index = build_index(db, config)
    keep = indexed_mask(db, config)
    assert (index.candidates[~keep] == -1).all()
    used = index.candidates[index.candidates >= 0]
    assert keep[used].all()
    assert (db.num_points[used] >= 20).all()
    assert not np.isin(db.difficulty[used], [0]).any()
    for row in np.flatnonzero(keep)[:50]:
        cands = index.candidates_of(row)
        assert row not in cands
        assert (db.names[cands] == db.names[row]).all()
        assert len(set(cands.tolist())) == len(cands)


def test_small_class_gets_all_it_has():
    db = random_database(np.random.default_rng(6), 200, classes=("Car", "Tram"))
    index = build_index(db, IndexConfig(k=400, min_points=0))
    for name in ("Car", "Tram"):
        rows = db.rows_of_class(name)
        for row in rows:
            cands = index.candidates_of(row)
            assert sorted(cands.tolist()) == sorted(set(rows.tolist()) - {row})
        assert index.classes[name]["mean_candidates"] == len(rows) - 1


def test_single_object_class_and_empty_objects():
    rng = np.random.default_rng(8)
    points = rng.uniform(-0.4, 0.4, (10, 4)).astype(np.float32)
    db = GroundTruthDatabase.from_arrays(
        points,
        [0, 10, 10],
        ["Car", "Pedestrian"],
        np.array([[0, 0, 0, 4, 2, 1.5, 0], [0, 0, 0, 1, 1, 2, 0]], float),
    )
    index = build_index(db, IndexConfig(k=3, min_points=0))
    assert (index.candidates == -1).all()
    assert index.densities[1].max() == 0  # no points, no density
    assert index.densities[0].max() == 1  # its own maxima


def test_partition_occupancy_matches_per_object_counts():
    db = random_database(np.random.default_rng(9), 300, point_dim=5)
    grids = {c: grid_for(c) for c in CLASSES}
    counts = partition_occupancy(db, grids, ("Car", "Cyclist"), chunk_points=97)
    for i in range(len(db)):
        name = str(db.names[i])
        pts = db.object_points(i)
        if name in ("Car", "Cyclist"):
            pts = mirror_points(pts)
        expected = partition_counts(pts, db.boxes[i, 3:6], grids[name])
        np.testing.assert_array_equal(counts[i, : len(expected)], expected)
        assert not counts[i, len(expected) :].any()


def test_degenerate_box_is_reported():
    db = random_database(np.random.default_rng(10), 20)
    boxes = db.boxes.copy()
    boxes[3, 4] = 0.0
    bad = GroundTruthDatabase.from_arrays(db.points, db.offsets, db.names, boxes)
    with pytest.raises(DataError, match="object 3"):
        build_index(bad)


def test_save_load_round_trip(tmp_path):
    db = random_database(np.random.default_rng(11), 300)
    db.save(tmp_path / "db")
    opened = GroundTruthDatabase.open(tmp_path / "db")
    config = IndexConfig(k=16, grids={"Van": (2, 2, 2)})
    index = build_index(opened, config)
    index.save(tmp_path / "db")
    assert sorted(p.name for p in (tmp_path / "db" / "index").iterdir()) == [
        "candidates.npy",
        "densities.npy",
        "manifest.json",
    ]
    loaded = load_index(opened)
    np.testing.assert_array_equal(loaded.candidates, index.candidates)
    np.testing.assert_array_equal(loaded.densities, index.densities)
    assert loaded.config == config
    assert loaded.grids == index.grids
    assert loaded.classes == index.classes
    for name in index.max_counts:
        np.testing.assert_array_equal(loaded.max_counts[name], index.max_counts[name])
    manifest = json.loads((tmp_path / "db" / "index" / "manifest.json").read_text())
    assert manifest["database_checksum"] == opened.checksum
    assert manifest["format_version"] == 1
    with pytest.raises(FileExistsError):
        index.save(tmp_path / "db")
    index.save(tmp_path / "db", overwrite=True)


def test_index_of_another_database_is_refused(tmp_path):
    rng = np.random.default_rng(12)
    db = random_database(rng, 100)
    db.save(tmp_path / "a")
    build_index(db, IndexConfig(k=4)).save(tmp_path / "a")
    other = random_database(rng, 100)
    with pytest.raises(DataError, match="checksum"):
        CandidateIndex.load(other, tmp_path / "a" / "index")
    with pytest.raises(DataError, match="no candidate index"):
        load_index(GroundTruthDatabase.open(tmp_path / "a"), tmp_path / "missing")


def test_corrupt_index_files_are_reported(tmp_path):
    db = random_database(np.random.default_rng(13), 50)
    db.save(tmp_path / "db")
    opened = GroundTruthDatabase.open(tmp_path / "db")
    build_index(opened, IndexConfig(k=4)).save(tmp_path / "db")
    np.save(tmp_path / "db" / "index" / "candidates.npy", np.zeros((3, 4), np.int32))
    with pytest.raises(DataError, match=r"candidates\.npy"):
        load_index(opened)


def test_failed_save_leaves_nothing(tmp_path, monkeypatch):
    db = random_database(np.random.default_rng(14), 50)
    index = build_index(db, IndexConfig(k=4))

    def broken(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np, "save", broken)
    with pytest.raises(OSError, match="disk full"):
        index.save(tmp_path / "db")
    assert not (tmp_path / "db" / "index").exists()
    assert not list((tmp_path / "db").iterdir())


def test_approximate_mode_recall_and_validity():
    rng = np.random.default_rng(15)
    dims = np.round(np.exp(rng.normal([1.36, 0.48, 0.42], [0.11, 0.06, 0.09], (4000, 3))), 2)
    recall = similarity_recall(dims, 100, np.arange(0, 4000, 13), approx_factor=2.0)
    assert 0.95 <= recall <= 1.0
    n = len(dims)
    db = GroundTruthDatabase.from_arrays(
        np.zeros((5 * n, 4), np.float32),
        np.arange(0, 5 * n + 1, 5),
        ["Car"] * n,
        np.column_stack([np.zeros((n, 3)), dims, np.zeros(n)]),
    )
    index = build_index(db, IndexConfig(k=50, approximate_above=1000))
    assert index.classes["Car"]["mode"] == "approximate"
    assert (index.candidates >= 0).all()
    assert not (index.candidates == np.arange(n)[:, None]).any()


@pytest.mark.parametrize(
    "bad",
    [{"k": 0}, {"alpha": 0}, {"min_points": -1}, {"block_size": 0}, {"grids": {"Car": (1, 0, 2)}}],
)
def test_bad_config_is_refused(bad):
    with pytest.raises(ConfigError):
        IndexConfig(**bad)


def test_config_round_trip():
    config = IndexConfig(k=7, grids={"Van": (1, 2, 3)}, classes=("Car",), exclude_difficulty=[2])
    assert IndexConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    with pytest.raises(ConfigError, match="unknown"):
        IndexConfig.from_dict({"kk": 3})


def test_an_index_saved_with_the_old_parameter_names_still_loads(tmp_path):
    db = random_database(np.random.default_rng(21), 60)
    db.save(tmp_path / "db")
    opened = GroundTruthDatabase.open(tmp_path / "db")
    config = IndexConfig(k=5, mirror=["Pedestrian"], exclude_difficulty=[-1])
    build_index(opened, config).save(tmp_path / "db")
    manifest_path = tmp_path / "db" / "index" / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    params = manifest["parameters"]
    # What drcpo wrote before the index section joined the YAML config.
    params["mirrored"] = params.pop("mirror")
    params["exclude_difficulties"] = params.pop("exclude_difficulty")
    params.update(workers=None, block_size=512)  # (how it was built: ignored)
    manifest_path.write_text(json.dumps(manifest))
    assert load_index(opened).config == config
    params["kk"] = 1
    manifest_path.write_text(json.dumps(manifest))
    with pytest.raises(
        DataError, match=r"manifest\.json: malformed.*unknown index parameters \['kk'\]"
    ):
        load_index(opened)


CUSTOM_YAML = (
    "drcpo:\n  construction:\n    grids: {Car: [5, 2, 3]}\n    mirror: [Cyclist]\n"
    "index:\n  k: 6\n  min_points: 2\n"
)


def test_cli_index_with_a_config_builds_the_index_that_config_needs(tmp_path):
    from typer.testing import CliRunner

    from drcpo.cli import app
    from drcpo.config import load_config
    from drcpo.transforms import DRCPO

    db = random_database(np.random.default_rng(22), 150)
    db.save(tmp_path / "db")
    opened = GroundTruthDatabase.open(tmp_path / "db")
    yaml_path = tmp_path / "my.yaml"
    yaml_path.write_text(CUSTOM_YAML)
    config = load_config(yaml_path)
    runner = CliRunner()
    args = ["index", str(tmp_path / "db")]

    # Without --config: the paper defaults, which DR.CPO with this config refuses, saying how.
    assert runner.invoke(app, args).exit_code == 0
    with pytest.raises(ConfigError) as info:
        DRCPO(opened, load_index(opened), config.drcpo)
    message = str(info.value)
    assert "drcpo.construction.grids.Car = [5, 2, 3]" in message and "[10, 4, 3]" in message
    assert f"drcpo index {tmp_path / 'db'} --config <your config.yaml> --overwrite" in message

    result = runner.invoke(app, [*args, "--config", str(yaml_path), "--overwrite"])
    assert result.exit_code == 0, result.output
    index = load_index(opened)
    assert index.k == 6 and index.grids["Car"] == (5, 2, 3)
    assert index.config == config.index
    np.testing.assert_array_equal(index.candidates, build_index(opened, config.index).candidates)
    DRCPO(opened, index, config.drcpo)  # accepted

    # An option given explicitly wins over the config; the grids stay the config's.
    result = runner.invoke(
        app, [*args, "--config", str(yaml_path), "--k", "3", "--min-points", "0", "--overwrite"]
    )
    assert result.exit_code == 0, result.output
    index = load_index(opened)
    assert (index.k, index.config.min_points, index.grids["Car"]) == (3, 0, (5, 2, 3))
    DRCPO(opened, index, config.drcpo)


def test_drcpo_refuses_an_index_mirroring_other_classes(tmp_path):
    from drcpo.config import load_config
    from drcpo.transforms import DRCPO

    db = random_database(np.random.default_rng(23), 80)
    config = load_config({"drcpo": {"construction": {"mirror": ["Car"]}}})
    with pytest.raises(ConfigError, match="disagree on whether Cyclist is mirrored.*--config"):
        DRCPO(db, build_index(db, IndexConfig(k=4)), config.drcpo)
    DRCPO(db, build_index(db, dataclasses.replace(config.index, k=4)), config.drcpo)


def test_cli_index_config_errors_name_the_file_and_key(tmp_path):
    from typer.testing import CliRunner

    from drcpo.cli import app

    db = random_database(np.random.default_rng(24), 20)
    db.save(tmp_path / "db")
    bad = tmp_path / "bad.yaml"
    bad.write_text("index:\n  grids: {Car: [5, 2, 3]}\n")
    result = CliRunner().invoke(app, ["index", str(tmp_path / "db"), "--config", str(bad)])
    assert result.exit_code == 1
    assert "bad.yaml" in result.output and "'index.grids' is not set in a config" in result.output
    assert "drcpo.construction.grids" in result.output
    assert not (tmp_path / "db" / "index").exists()


def test_cli_index_builds_saves_and_refuses_to_overwrite(tmp_path):
    from typer.testing import CliRunner

    from drcpo.cli import app

    db = random_database(np.random.default_rng(16), 120)
    db.save(tmp_path / "db")
    runner = CliRunner()
    result = runner.invoke(app, ["index", str(tmp_path / "db"), "--k", "8"])
    assert result.exit_code == 0, result.output
    assert "mean candidates" in result.output
    opened = GroundTruthDatabase.open(tmp_path / "db")
    index = load_index(opened)
    assert index.k == 8
    np.testing.assert_array_equal(
        index.candidates, build_index(opened, IndexConfig(k=8)).candidates
    )
    again = runner.invoke(app, ["index", str(tmp_path / "db")])
    assert again.exit_code == 1
    assert "already exists" in again.output
    rebuilt = runner.invoke(app, ["index", str(tmp_path / "db"), "--k", "3", "--overwrite"])
    assert rebuilt.exit_code == 0, rebuilt.output
    assert load_index(opened).k == 3
    missing = runner.invoke(app, ["index", str(tmp_path / "nowhere")])
    assert missing.exit_code == 1
    assert "not a drcpo database" in missing.output
    alone = runner.invoke(app, ["index", str(tmp_path / "db"), "--workers", "2", "--overwrite"])
    assert alone.exit_code == 1 and "--workers needs --cluster" in alone.output


def test_progress_reaches_every_indexed_object():
    db = random_database(np.random.default_rng(17), 700)
    config = IndexConfig(k=10, block_size=50)
    seen = {}
    build_index(
        db,
        config,
        progress=lambda name, done, total: seen.setdefault(name, []).append((done, total)),
    )
    keep = indexed_mask(db, config)
    for name, calls in seen.items():
        expected = int(keep[db.names == name].sum())
        assert calls[-1] == (expected, expected)
        assert [d for d, _ in calls] == sorted(d for d, _ in calls)
    assert set(seen) == set(db.names.tolist())


@pytest.mark.parametrize("k", [10**12, 100_001])
def test_k_above_the_bound_is_refused(k):
    with pytest.raises(
        ConfigError, match=rf"'index\.k' = {k} is out of range; allowed range: \[1, 100000\]"
    ):
        IndexConfig(k=k)


def test_candidate_table_too_large_for_memory_is_refused_before_allocating(monkeypatch):
    import drcpo.index_build

    db = random_database(np.random.default_rng(18), 300, classes=("Car", "Van"))
    largest = max(int((db.names == c).sum()) for c in ("Car", "Van"))
    # test seam: the memory probe, so that the refusal is tested without a huge table
    monkeypatch.setattr(drcpo.index_build, "_memory_bytes", lambda: 1 << 20)  # a 1 MiB machine
    with pytest.raises(ConfigError) as info:
        build_index(db, IndexConfig(k=5000, min_points=0))
    message = str(info.value)
    assert "K = 5000" in message and "300 objects" in message and "5.7 MiB" in message
    assert "1.0 MiB" in message and f"at most {largest - 1} candidates" in message
    build_index(db, IndexConfig(k=200, min_points=0))  # 234 KiB: fits
