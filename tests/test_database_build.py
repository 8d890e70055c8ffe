import json
import os
import pickle
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
from conftest import random_boxes
from typer.testing import CliRunner

from drcpo.cli import app
from drcpo.database import GroundTruthDatabase, safe_pickle
from drcpo.database.build import (
    DEFAULT_CLASSES,
    build_database,
    frame_records,
    points_in_boxes_openpcdet,
)
from drcpo.database.dbinfos import import_mmdet3d, import_openpcdet
from drcpo.datasets.kitti import KittiDataset
from drcpo.datasets.kitti_coordinates import fov_mask
from drcpo.errors import ConfigError, DataError
from drcpo.frame import Frame
from drcpo.geometry import from_canonical, points_in_boxes, rotate_points_z, wrap_angle


def _mirror(kitti_sample, tmp_path):
    """A KITTI root of symlinks to the sample, so a test can replace single files."""
    root = tmp_path / "kitti"
    for path in kitti_sample.rglob("*"):
        target = root / path.relative_to(kitti_sample)
        if path.is_dir():
            target.mkdir(parents=True, exist_ok=True)
        else:
            target.parent.mkdir(parents=True, exist_ok=True)
            target.symlink_to(path)
    return root


def _replace(path, data: bytes | str):
    path.unlink()
    if isinstance(data, str):
        path.write_text(data)
    else:
        path.write_bytes(data)


@pytest.fixture
def built(kitti_sample, tmp_path):
    return build_database(kitti_sample, "train", tmp_path / "db", classes="all")


def _openpcdet_objects(kitti_sample):
    dbinfos = safe_pickle.load(kitti_sample / "kitti_dbinfos_train.pkl")
    return [info for infos in dbinfos.values() for info in infos]


def _row(db, frame_id, index):
    rows = np.flatnonzero((db.frame_ids == frame_id) & (db.index_in_frame == index))
    assert len(rows) == 1, (frame_id, index)
    return int(rows[0])


def _assert_same_box(ours, theirs):
    np.testing.assert_allclose(ours[:6], theirs[:6], rtol=0, atol=1e-4)
    assert abs(wrap_angle(ours[6] - theirs[6])) < 1e-4


# Matching OpenPCDet ---------------------------------------------------------------------------
def test_build_matches_openpcdet_database(kitti_sample, built):
    objects = _openpcdet_objects(kitti_sample)
    expected = {}
    for info in objects:
        expected[str(info["name"])] = expected.get(str(info["name"]), 0) + 1
    assert {name: row["objects"] for name, row in built.summary().items()} == expected
    assert len(built) == len(objects)
    for info in objects:
        i = _row(built, info["image_idx"], info["gt_idx"])
        assert built.names[i] == info["name"]
        assert built.num_points[i] == info["num_points_in_gt"]
        assert built.difficulty[i] == info["difficulty"]
        _assert_same_box(built.boxes[i], info["box3d_lidar"])
        # OpenPCDet stores the points minus the box centre, not rotated.
        theirs = np.fromfile(kitti_sample / info["path"], dtype=np.float32).reshape(-1, 4)
        ours = rotate_points_z(built.object_points(i), built.boxes[i, 6])
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-5)


def test_build_records_metadata(built, kitti_sample):
    i = _row(built, "000001", 2)
    assert built.names[i] == "Cyclist"
    assert built.occlusion[i] == 3
    assert built.truncation[i] == 0.0
    params = built.manifest["parameters"]
    assert params["source"] == "kitti"
    assert params["split"] == "train"
    assert params["classes"] == "all"
    assert params["root"] == str(kitti_sample.resolve())
    built.verify()


def test_database_is_cut_from_the_full_point_cloud(kitti_sample, tmp_path):
    # OpenPCDet's create_groundtruth_database cuts objects from get_lidar(), not from the
    # FOV-filtered points. A box behind the camera sees no point in the FOV but keeps its points.
    root = _mirror(kitti_sample, tmp_path)
    label = root / "training" / "label_2" / "000005.txt"
    behind = "Van 0.00 0 0.0 0 0 10 50 3.0 4.0 6.0 0.0 2.0 -10.0 0.0\n"
    _replace(label, label.read_text() + behind)
    db = build_database(root, "train", tmp_path / "db", classes=["Van"])
    frame = KittiDataset(root, "train").frame("000005")
    inside = points_in_boxes_openpcdet(frame.points, frame.boxes)[:, -1]
    visible = fov_mask(frame.points, frame.metadata["calib"])
    assert inside.sum() > 100 and not (inside & visible).any()
    assert db.num_points.tolist() == [inside.sum()]


def test_import_gives_the_same_database(kitti_sample, built, tmp_path):
    imported = import_openpcdet(kitti_sample / "kitti_dbinfos_train.pkl", tmp_path / "imported")
    assert len(imported) == len(built)
    for column in ("names", "frame_ids", "index_in_frame", "num_points", "difficulty", "occlusion"):
        np.testing.assert_array_equal(getattr(imported, column), getattr(built, column))
    np.testing.assert_array_equal(imported.truncation, built.truncation)
    np.testing.assert_allclose(imported.boxes, built.boxes, rtol=0, atol=1e-4)
    np.testing.assert_array_equal(imported.offsets, built.offsets)
    np.testing.assert_allclose(imported.points, built.points, rtol=0, atol=1e-5)
    assert imported.manifest["parameters"]["source"] == "openpcdet"


def _mmdet3d_layout(kitti_sample, tmp_path):
    from mmdet3d_support import write_mmdet3d_dbinfos

    return write_mmdet3d_dbinfos(kitti_sample, tmp_path / "mmdet3d").parent


def test_mmdet3d_import_equals_the_openpcdet_import(kitti_sample, tmp_path):
    root = _mmdet3d_layout(kitti_sample, tmp_path)
    ours = import_mmdet3d(root / "kitti_dbinfos_train.pkl", tmp_path / "from_mmdet3d")
    reference = import_openpcdet(kitti_sample / "kitti_dbinfos_train.pkl", tmp_path / "from_pcdet")
    assert len(ours) == len(reference) == 10
    for column in ("names", "frame_ids", "index_in_frame", "num_points", "difficulty", "occlusion"):
        np.testing.assert_array_equal(getattr(ours, column), getattr(reference, column))
    np.testing.assert_array_equal(ours.truncation, reference.truncation)
    np.testing.assert_array_equal(ours.offsets, reference.offsets)
    # Only float32 rounding of the shifted files separates them (a missed dz / 2 is metres).
    np.testing.assert_allclose(ours.boxes, reference.boxes, rtol=0, atol=1e-6)
    np.testing.assert_allclose(ours.points, reference.points, rtol=0, atol=1e-6)
    assert ours.manifest["parameters"]["source"] == "mmdet3d"


def test_cli_import_mmdet3d(kitti_sample, tmp_path):
    root = _mmdet3d_layout(kitti_sample, tmp_path)
    pkl = str(root / "kitti_dbinfos_train.pkl")
    result = CliRunner().invoke(app, ["import-mmdet3d", pkl, "--out", str(tmp_path / "db")])
    assert result.exit_code == 0, result.output
    assert GroundTruthDatabase.open(tmp_path / "db").frame_ids[0] == "000000"


def test_mmdet3d_import_checks_the_fields_as_the_openpcdet_one(kitti_sample, tmp_path):
    root = _mmdet3d_layout(kitti_sample, tmp_path)
    infos = safe_pickle.load(root / "kitti_dbinfos_train.pkl")
    infos["Car"][1]["image_idx"] = True  # not a sample index
    with open(root / "bad.pkl", "wb") as f:
        pickle.dump(infos, f)
    with pytest.raises(DataError, match=r"bad.pkl: Car\[1\]: field 'image_idx' = True"):
        import_mmdet3d(root / "bad.pkl", tmp_path / "db")


def test_import_rejects_an_unknown_origin(kitti_sample, tmp_path):
    pkl = kitti_sample / "kitti_dbinfos_train.pkl"
    with pytest.raises(ConfigError, match="origin must be one of centre, bottom, got 'top'"):
        import_openpcdet(pkl, tmp_path / "db", origin="top")


def test_import_without_labels_leaves_occlusion_unknown(kitti_sample, tmp_path):
    root = tmp_path / "openpcdet"
    root.mkdir()
    (root / "gt_database").symlink_to(kitti_sample / "gt_database")
    (root / "kitti_dbinfos_train.pkl").symlink_to(kitti_sample / "kitti_dbinfos_train.pkl")
    db = import_openpcdet(root / "kitti_dbinfos_train.pkl", tmp_path / "db")
    assert (db.occlusion == -1).all() and np.isnan(db.truncation).all()
    assert len(db) == 10


# Parallelism, classes, atomic writes ------------------------------------------------------
def test_workers_do_not_change_the_database(kitti_sample, built, tmp_path):
    parallel = build_database(kitti_sample, "train", tmp_path / "p", classes="all", workers=2)
    assert parallel.checksum == built.checksum


def test_default_classes(kitti_sample, tmp_path):
    db = build_database(kitti_sample, "train", tmp_path / "db")
    assert set(db.classes) == set(DEFAULT_CLASSES)
    assert db.manifest["parameters"]["classes"] == list(DEFAULT_CLASSES)
    only_cars = build_database(kitti_sample, "train", tmp_path / "cars", classes=["Car"])
    assert only_cars.classes == ["Car"] and len(only_cars) == 5


def test_bad_class_choices(kitti_sample, tmp_path):
    with pytest.raises(DataError, match="holds no object of classes \\['Tram'\\]"):
        build_database(kitti_sample, "train", tmp_path / "db", classes=["Tram"])
    with pytest.raises(ConfigError, match="DontCare"):
        build_database(kitti_sample, "train", tmp_path / "db", classes=["Car", "DontCare"])
    with pytest.raises(ConfigError, match="at least one"):
        build_database(kitti_sample, "train", tmp_path / "db", classes=[])
    assert not (tmp_path / "db").exists()


def test_existing_output_needs_overwrite(kitti_sample, built, tmp_path):
    with pytest.raises(FileExistsError, match="already exists"):
        build_database(kitti_sample, "train", tmp_path / "db", classes=["Car"])
    replaced = build_database(kitti_sample, "train", tmp_path / "db", ["Car"], overwrite=True)
    assert replaced.classes == ["Car"]


def _no_database_left(tmp_path):
    assert not (tmp_path / "db").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".db.tmp")]


def test_corrupt_frame_stops_the_build_without_output(kitti_sample, tmp_path):
    root = _mirror(kitti_sample, tmp_path)
    _replace(root / "training" / "velodyne" / "000004.bin", bytes(100))
    with pytest.raises(DataError, match=r"velodyne/000004\.bin: size 100 bytes"):
        build_database(root, "train", tmp_path / "db", workers=2)
    _no_database_left(tmp_path)


def test_missing_calib_stops_the_build(kitti_sample, tmp_path):
    root = _mirror(kitti_sample, tmp_path)
    (root / "training" / "calib" / "000002.txt").unlink()
    with pytest.raises(DataError, match=r"calib/000002\.txt: calibration file missing"):
        build_database(root, "train", tmp_path / "db")
    _no_database_left(tmp_path)


def test_malformed_label_stops_the_build(kitti_sample, tmp_path):
    root = _mirror(kitti_sample, tmp_path)
    label = root / "training" / "label_2" / "000003.txt"
    lines = label.read_text().splitlines()
    lines[0] = lines[0].rsplit(" ", 2)[0]
    _replace(label, "\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"label_2/000003\.txt:1: expected 15 or 16 fields"):
        build_database(root, "train", tmp_path / "db")
    _no_database_left(tmp_path)


def test_unknown_split_is_reported(kitti_sample, tmp_path):
    with pytest.raises(DataError, match="unknown split 'tain' \\(available: test, train, val\\)"):
        build_database(kitti_sample, "tain", tmp_path / "db")


# Importer bad input ---------------------------------------------------------------------------
def _openpcdet_copy(kitti_sample, tmp_path):
    root = tmp_path / "openpcdet"
    shutil.copytree(kitti_sample / "gt_database", root / "gt_database")
    return root


def test_import_refuses_a_malicious_pickle(kitti_sample, tmp_path):
    root = _openpcdet_copy(kitti_sample, tmp_path)
    marker = tmp_path / "pwned"

    class Exploit:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    (root / "kitti_dbinfos_train.pkl").write_bytes(pickle.dumps({"Car": [Exploit()]}))
    with pytest.raises(DataError, match=r"kitti_dbinfos_train\.pkl: refused to load global"):
        import_openpcdet(root / "kitti_dbinfos_train.pkl", tmp_path / "db")
    assert not marker.exists()
    _no_database_left(tmp_path)


def test_import_checks_point_counts_and_keys(kitti_sample, tmp_path):
    root = _openpcdet_copy(kitti_sample, tmp_path)
    dbinfos = safe_pickle.load(kitti_sample / "kitti_dbinfos_train.pkl")
    dbinfos["Car"][0]["num_points_in_gt"] += 1
    (root / "dbinfos.pkl").write_bytes(pickle.dumps(dbinfos))
    with pytest.raises(DataError, match=r"000001_Car_1\.bin: holds 9 points, the infos say"):
        import_openpcdet(root / "dbinfos.pkl", tmp_path / "db")
    del dbinfos["Car"][0]["box3d_lidar"]
    (root / "dbinfos.pkl").write_bytes(pickle.dumps(dbinfos))
    with pytest.raises(DataError, match=r"dbinfos\.pkl: Car\[0\]: missing key\(s\) box3d_lidar"):
        import_openpcdet(root / "dbinfos.pkl", tmp_path / "db")
    _no_database_left(tmp_path)


def test_frame_records_of_a_plain_frame(rng):
    boxes = np.array([[5.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.7], [-5.0, 3.0, 0.0, 1.0, 1.0, 1.8, 0.0]])
    xyz = rng.uniform([-8, -8, -1], [8, 8, 1], (5000, 3))
    points = np.column_stack([xyz, rng.uniform(0, 1, 5000)])
    frame = Frame(points, boxes, np.array(["Car", "Pedestrian"]), {"frame_id": "synthetic"})
    (record,) = frame_records(frame, classes=("Pedestrian",))
    assert (record.name, record.frame_id, record.index_in_frame) == ("Pedestrian", "synthetic", 1)
    assert (record.difficulty, record.occlusion) == (-1, -1) and np.isnan(record.truncation)
    inside = points_in_boxes_openpcdet(frame.points, boxes[1:])[:, 0]
    assert len(record.points) == inside.sum() > 10
    np.testing.assert_allclose(
        from_canonical(record.points, boxes[1]), frame.points[inside], atol=1e-5
    )
    bad = frame.replace(metadata={"frame_id": "x", "difficulty": np.zeros(3)})
    with pytest.raises(DataError, match="frame x: metadata 'difficulty' has shape"):
        frame_records(bad)


# The inside rule ------------------------------------------------------------------------------
def test_openpcdet_rule_lies_between_shrunk_and_widened_boxes(rng):
    boxes = random_boxes(rng, 8)
    points = rng.uniform(-7, 7, (20000, 3)).astype(np.float32)
    rule = points_in_boxes_openpcdet(points, boxes)
    # float32 rounding can move a point by ~1e-6 m; stay clear of it
    assert not (points_in_boxes(points, boxes, margin=-1e-4) & ~rule).any()
    widened = points_in_boxes(points, boxes, margin=0.01 + 1e-4)
    assert not (rule & ~widened).any()
    # the x/y margin counts: some points within 0.01 m outside a side face are inside
    assert (rule & ~points_in_boxes(points, boxes)).any()


def test_openpcdet_rule_has_no_z_margin():
    box = np.array([[0.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.3]])
    points = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.005], [0.0, 0.0, -1.0]], np.float32)
    assert points_in_boxes_openpcdet(points, box)[:, 0].tolist() == [True, False, True]


# CLI ------------------------------------------------------------------------------------------
def _words(output: str) -> str:
    """CLI output with rich's line wrapping undone."""
    return " ".join(output.split())


def test_cli_build_db_then_info_json(kitti_sample, tmp_path):
    runner = CliRunner()
    out = tmp_path / "db"
    args = ["build-db", "--kitti", str(kitti_sample), "--split", "train", "--out", str(out)]
    result = runner.invoke(app, [*args, "--classes", "Car", "Pedestrian", "--workers", "2"])
    assert result.exit_code == 0, result.output
    assert "Pedestrian" in result.stdout and "total" in result.stdout
    result = runner.invoke(app, ["info", str(out), "--json"])
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert payload["classes"] == {
        "Car": {"objects": 5, "points": 858},
        "Pedestrian": {"objects": 2, "points": 453},
    }
    assert payload["format_version"] == GroundTruthDatabase.open(out).manifest["format_version"]
    again = runner.invoke(app, args)
    assert again.exit_code == 1 and "already exists" in _words(again.output)


def test_cli_bad_input_exits_1_with_message(kitti_sample, tmp_path):
    runner = CliRunner()
    result = runner.invoke(
        app,
        [
            "build-db",
            "--kitti",
            str(kitti_sample),
            "--split",
            "nope",
            "--out",
            str(tmp_path / "db"),
        ],
    )
    assert result.exit_code == 1
    assert "unknown split 'nope' (available: test, train, val)" in _words(result.output)
    result = runner.invoke(
        app, ["import-openpcdet", str(tmp_path / "missing.pkl"), "--out", str(tmp_path / "db")]
    )
    assert result.exit_code == 1 and "missing.pkl: cannot read" in _words(result.output)
    result = runner.invoke(app, ["build-db", "--kitti", str(kitti_sample), "--out", "x", "stray"])
    assert result.exit_code == 1 and "unexpected argument(s): stray" in _words(result.output)


def test_cli_import_openpcdet(kitti_sample, tmp_path):
    pkl = kitti_sample / "kitti_dbinfos_train.pkl"
    result = CliRunner().invoke(app, ["import-openpcdet", str(pkl), "--out", str(tmp_path / "db")])
    assert result.exit_code == 0, result.output
    assert "total" in result.stdout
    assert len(GroundTruthDatabase.open(tmp_path / "db")) == 10


# Importer: every field checked ----------------------------------------------------------------
def _import_with(kitti_sample, tmp_path, edit, root=None):
    """Import the sample's dbinfos after ``edit(dbinfos)``, re-pickled into ``tmp_path``."""
    dbinfos = safe_pickle.load(kitti_sample / "kitti_dbinfos_train.pkl")
    edit(dbinfos)
    path = tmp_path / "dbinfos.pkl"
    path.write_bytes(pickle.dumps(dbinfos))
    return import_openpcdet(path, tmp_path / "db", root=root or kitti_sample)


def _setter(field, value, record=("Car", 2)):
    def edit(dbinfos):
        dbinfos[record[0]][record[1]][field] = value

    return edit


INT32 = r"an int in \[0, 2147483647\]"


@pytest.mark.parametrize(
    ("field", "value", "expected"),
    [
        ("gt_idx", "abc", rf"field 'gt_idx' = 'abc' is not {INT32}"),
        ("gt_idx", -1, rf"field 'gt_idx' = -1 is not {INT32}"),
        ("gt_idx", True, rf"field 'gt_idx' = True is not {INT32}"),
        ("gt_idx", 2**40, rf"field 'gt_idx' = 1099511627776 is not {INT32}"),
        pytest.param(
            "gt_idx", 10**5000, f"field 'gt_idx' = <an int of 16610 bits> is not {INT32}", id="huge"
        ),
        ("num_points_in_gt", "12", rf"field 'num_points_in_gt' = '12' is not {INT32}"),
        ("num_points_in_gt", 12.0, rf"field 'num_points_in_gt' = 12.0 is not {INT32}"),
        ("difficulty", "hard", r"field 'difficulty' = 'hard' is not an int in \[-1, 2\]"),
        ("difficulty", np.int32(300), r"field 'difficulty' = np.int32\(300\) is not an int"),
        ("box3d_lidar", "abc", "field 'box3d_lidar' = 'abc' is not a box of >= 7 finite"),
        ("box3d_lidar", np.zeros(6), r"field 'box3d_lidar' = <array float64 \(6,\)> is not a box"),
        ("box3d_lidar", np.ones((1, 7)), r"field 'box3d_lidar' = <array float64 \(1, 7\)>"),
        ("box3d_lidar", [1, 2, 3, 1, 1, np.nan, 0], "field 'box3d_lidar' = .* is not a box"),
        ("box3d_lidar", [1, 2, 3, 1, 1, "1", 0], "field 'box3d_lidar' = .* is not a box"),
        ("box3d_lidar", [1, 2, 3, 1, 1, 10**400, 0], "field 'box3d_lidar' = .* is not a box"),
        pytest.param("score", 10**5000, "field 'score' = <an int of 16610 bits>", id="huge"),
        ("box3d_lidar", np.array(["1"] * 7), r"field 'box3d_lidar' = <array <U1 \(7,\)> is not a"),
        ("bbox", np.zeros(3), r"field 'bbox' = <array float64 \(3,\)> is not 4 numbers"),
        ("score", None, "field 'score' = None is not a number"),
        ("name", 5, r"field 'name' = 5 is not a class name"),
        ("name", "Van", "name 'Van' is not its class 'Car'"),
        ("path", 7, r"field 'path' = 7 is not a file path"),
        ("image_idx", 1, r"field 'image_idx' = 1 is not a frame id"),
        ("image_idx", "../000001", r"field 'image_idx' = '../000001' is not a frame id"),
    ],
)
def test_import_checks_every_field(kitti_sample, tmp_path, field, value, expected):
    with pytest.raises(DataError, match=rf"dbinfos\.pkl: Car\[2\]: {expected}"):
        _import_with(kitti_sample, tmp_path, _setter(field, value))
    _no_database_left(tmp_path)


@pytest.mark.parametrize("where", ["absolute", "../stolen.bin", "gt_database/../../stolen.bin"])
def test_import_refuses_paths_outside_the_root(kitti_sample, tmp_path, where):
    # A valid object file outside the root: without the check, it would be imported.
    stolen = tmp_path / "stolen.bin"
    shutil.copyfile(kitti_sample / "gt_database" / "000001_Car_1.bin", stolen)
    root = _mirror(kitti_sample, tmp_path / "kitti")
    path = str(stolen) if where == "absolute" else where
    expected = rf"Car\[0\]: field 'path' = '{re.escape(path)}' is not a path inside the data root"
    with pytest.raises(DataError, match=expected):
        _import_with(kitti_sample, tmp_path, _setter("path", path, ("Car", 0)), root=root)
    _no_database_left(tmp_path)


def test_import_refuses_a_negative_gt_idx_that_labels_would_accept(kitti_sample, tmp_path):
    # Frame 000001's labels are Truck, Car, Cyclist: labels[-2] is a Car, as Car[0] says.
    with pytest.raises(DataError, match=rf"Car\[0\]: field 'gt_idx' = -2 is not {INT32}"):
        _import_with(kitti_sample, tmp_path, _setter("gt_idx", -2, ("Car", 0)))
    with pytest.raises(DataError, match=r"label_2/000001\.txt: object 5 is not a Car"):
        _import_with(kitti_sample, tmp_path, _setter("gt_idx", 5, ("Car", 0)))


def test_import_refuses_an_object_listed_twice(kitti_sample, tmp_path):
    def duplicate(dbinfos):
        dbinfos["Car"].append(dict(dbinfos["Car"][1]))

    with pytest.raises(DataError, match=r"Car\[5\]: object 1 of frame 000002 is already listed"):
        _import_with(kitti_sample, tmp_path, duplicate)


@pytest.mark.parametrize("protocol", range(6))
def test_import_does_not_depend_on_the_pickle_protocol(kitti_sample, tmp_path, protocol):
    # The sample was written under numpy 1.x (numpy.core.*), these under numpy 2 (numpy._core.*).
    original = import_openpcdet(kitti_sample / "kitti_dbinfos_train.pkl", tmp_path / "original")
    data = pickle.dumps(pickle.loads((kitti_sample / "kitti_dbinfos_train.pkl").read_bytes()))
    (tmp_path / "again.pkl").write_bytes(pickle.dumps(pickle.loads(data), protocol=protocol))
    again = import_openpcdet(tmp_path / "again.pkl", tmp_path / "again", root=kitti_sample)
    assert again.checksum == original.checksum


def test_cli_import_of_a_corrupted_pickle_fails_in_one_line(kitti_sample, tmp_path):
    # Flags 0x78 on a dtype used to crash the process; run it in a child to see a crash.
    data = bytearray((kitti_sample / "kitti_dbinfos_train.pkl").read_bytes())
    data[2318] = 0x78
    root = _openpcdet_copy(kitti_sample, tmp_path)
    pkl = root / "kitti_dbinfos_train.pkl"
    pkl.write_bytes(bytes(data))
    command = ["import-openpcdet", str(pkl), "--out", str(tmp_path / "db")]
    child = subprocess.run(
        [sys.executable, "-m", "drcpo.cli", *command],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert child.returncode == 1, (child.returncode, child.stderr[-2000:])
    message = _words(child.stderr)
    assert "error:" in message and "Traceback" not in message
    assert "kitti_dbinfos_train.pkl: not a readable pickle: dtype <U3: flags 120" in message
    _no_database_left(tmp_path)


def test_import_refuses_points_far_outside_their_box(kitti_sample, tmp_path):
    root = _openpcdet_copy(kitti_sample, tmp_path)
    dbinfos = safe_pickle.load(kitti_sample / "kitti_dbinfos_train.pkl")
    (root / "dbinfos.pkl").write_bytes(pickle.dumps(dbinfos))
    first = root / dbinfos["Car"][0]["path"]
    points = np.fromfile(first, dtype=np.float32).reshape(-1, 4)
    points[3, :3] = (5e6, 0.0, 0.0)  # 5,000 km from its box: beyond drcpo's own limit
    points.tofile(first)
    with pytest.raises(DataError, match=r"000001_Car_1\.bin: 1 of its 9 points lie more than 1"):
        import_openpcdet(root / "dbinfos.pkl", tmp_path / "db")
    points[3, :3] = (0.0, 0.0, 4.0)  # 4 m above the centre of a 1.5 m tall car
    points.tofile(first)
    with pytest.raises(DataError, match="outside the object's box"):
        import_openpcdet(root / "dbinfos.pkl", tmp_path / "db")
    _no_database_left(tmp_path)
    points[3, :3] = (0.0, 0.0, 0.2)  # inside: imported
    points.tofile(first)
    import_openpcdet(root / "dbinfos.pkl", tmp_path / "db")
