"""How drcpo treats what it reads and writes (docs/your_files.md): what it reads back is verified
and a bad file gives one clear error naming it, never a traceback."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from drcpo.database import GroundTruthDatabase
from drcpo.errors import DataError, OutputError
from drcpo.outputs import OutputKind, write_directory

DEEP = "[" * 100_000 + "]" * 100_000  # json's recursion limit, far beyond any real file


def _database(path: Path) -> Path:
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.5, 0.5, (12, 4)).astype(np.float32)
    boxes = np.column_stack([rng.normal(size=(2, 3)), [[3.9, 1.6, 1.5]] * 2, np.zeros(2)])
    GroundTruthDatabase.from_arrays(points, np.array([0, 6, 12]), ["Car", "Car"], boxes).save(path)
    return path


def test_deeply_nested_json_is_an_unreadable_file_not_a_traceback(tmp_path):
    from drcpo.datasets.nuscenes import NuScenesTables
    from drcpo.index import load_index

    db = _database(tmp_path / "db")
    (db / "manifest.json").write_text(DEEP)
    with pytest.raises(DataError, match=r"db/manifest\.json: unreadable manifest"):
        GroundTruthDatabase.open(db)
    (tmp_path / "db2").mkdir()
    (tmp_path / "db2" / "index").mkdir()
    (tmp_path / "db2" / "index" / "manifest.json").write_text(DEEP)
    with pytest.raises(DataError, match=r"index/manifest\.json: unreadable manifest"):
        load_index(_database(tmp_path / "db3"), tmp_path / "db2" / "index")
    tables = tmp_path / "nuscenes" / "v1.0-mini"
    tables.mkdir(parents=True)
    (tables / "scene.json").write_text(DEEP)
    with pytest.raises(DataError, match="nested too deeply|cannot read table"):
        NuScenesTables(tmp_path / "nuscenes", "v1.0-mini")
    # a marker or a staging record nested so deep is not drcpo's: refused, never a traceback
    kind = OutputKind("test output", "marker.json", "drcpo-test")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "marker.json").write_text(DEEP)
    with pytest.raises(OutputError, match="is not drcpo's JSON"):
        write_directory(tmp_path / "out", lambda p: None, kind, overwrite=True)


def test_an_edited_index_is_refused_on_load(tmp_path):
    from drcpo.index import IndexConfig, load_index
    from drcpo.index_build import build_index

    rng = np.random.default_rng(1)
    sizes = rng.integers(6, 30, 12)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    points = rng.uniform(-0.5, 0.5, (offsets[-1], 4)).astype(np.float32)
    names = ["Car"] * 6 + ["Pedestrian"] * 6
    dims = [[3.9, 1.6, 1.5]] * 6 + [[0.8, 0.6, 1.7]] * 6
    boxes = np.column_stack([rng.normal(size=(12, 3)), dims, np.zeros(12)])
    GroundTruthDatabase.from_arrays(points, offsets, names, boxes).save(tmp_path / "db")
    db = GroundTruthDatabase.open(tmp_path / "db")
    build_index(db, IndexConfig(k=4)).save(db.path)
    load_index(db)  # as saved: fine
    index = tmp_path / "db" / "index"
    manifest = json.loads((index / "manifest.json").read_text())
    edited = json.loads(json.dumps(manifest))
    first = next(iter(edited["classes"].values()))
    first["max_counts"][0] += 1
    (index / "manifest.json").write_text(json.dumps(edited))
    with pytest.raises(DataError, match="the index changed since it was saved"):
        load_index(db)
    # a Car's candidate pointing at a Pedestrian
    (index / "manifest.json").write_text(json.dumps(manifest))
    candidates = np.load(index / "candidates.npy")
    candidates[0, 0] = 7
    np.save(index / "candidates.npy", candidates)
    with pytest.raises(DataError, match="the index changed since it was saved"):
        load_index(db)
    # an index saved before drcpo recorded checksums: the classes are still checked
    unchecked = {k: v for k, v in manifest.items() if k != "checksum"}
    (index / "manifest.json").write_text(json.dumps(unchecked))
    with pytest.raises(DataError, match=r"object 0 \(Car\) has candidate 7 \(Pedestrian\)"):
        load_index(db)


def test_every_size_validation_accepts_is_written_so_that_it_reads_back(tmp_path):
    from drcpo.datasets.kitti import read_labels
    from drcpo.datasets.kitti_writer import label_lines, reference_calibration, write_labels
    from drcpo.frame import Frame

    boxes = np.array(
        [
            [10.0, 0.0, -1.0, 1e-30, 1.6, 1.5, 0.0],
            [12.0, 3.0, -1.0, 3.9, 4e-4, 1.5, 0.3],
            [15.0, -3.0, -1.0, 3.9, 1.6, 1.5, 0.1],
        ]
    )
    Frame(np.zeros((1, 4), np.float32), boxes, np.array(["Car"] * 3)).validate()
    lines = label_lines(boxes, ["Car"] * 3, reference_calibration())
    write_labels(tmp_path / "000000.txt", lines)
    labels = read_labels(tmp_path / "000000.txt")
    lwh = labels.dimensions  # length, height, width
    np.testing.assert_allclose(lwh[:, 0], [1e-30, 3.9, 3.9], rtol=1e-9)
    np.testing.assert_allclose(lwh[:, 2], [1.6, 4e-4, 1.6], rtol=1e-9)
    assert lines[2].split()[8:11] == ["1.500000", "1.600000", "3.900000"]  # KITTI's usual form


def test_an_occlusion_that_is_not_a_kitti_level_is_refused_on_read_and_write(tmp_path):
    from drcpo.datasets.kitti import read_labels
    from drcpo.datasets.kitti_writer import label_lines, reference_calibration

    path = tmp_path / "000000.txt"
    path.write_text(
        "Car 0.00 300 1.85 387.63 181.54 423.81 203.12 1.67 1.87 3.69 -16.53 2.39 58.49 1.57\n"
    )
    with pytest.raises(DataError, match=r"000000\.txt:1: Car has occlusion '300'; KITTI's levels"):
        read_labels(path)
    path.write_text(
        "Car 0.00 1.5 1.85 387.63 181.54 423.81 203.12 1.67 1.87 3.69 -16.53 2.39 58.49 1.57\n"
    )
    with pytest.raises(DataError, match="has occlusion '1.5'"):
        read_labels(path)
    box = np.array([[10.0, 0.0, -1.0, 3.9, 1.6, 1.5, 0.0]])
    with pytest.raises(DataError, match="occlusion levels must be"):
        label_lines(box, ["Car"], reference_calibration(), occlusion=np.array([44]))


def test_overwrite_removes_only_what_drcpo_wrote_naming_anything_else(tmp_path):
    from drcpo.index import IndexConfig
    from drcpo.index_build import build_index
    from drcpo.synth import write_synthetic_kitti

    db = _database(tmp_path / "db")
    build_index(GroundTruthDatabase.open(db), IndexConfig(k=2)).save(db)
    # a database with its index/ is all drcpo's: --overwrite replaces it
    GroundTruthDatabase.open(db).save(db, overwrite=True)
    GroundTruthDatabase.open(db).save(tmp_path / "db2")
    (tmp_path / "db2" / "NOTES.txt").write_text("mine")
    with pytest.raises(OutputError, match=r"holds .*db2/NOTES\.txt, which drcpo did not write"):
        GroundTruthDatabase.open(tmp_path / "db2").save(tmp_path / "db2", overwrite=True)
    assert (tmp_path / "db2" / "NOTES.txt").read_text() == "mine"
    root = tmp_path / "synthetic"
    write_synthetic_kitti(root, 1, seed=0)
    GroundTruthDatabase.open(db).save(root / "my_db")  # a database kept inside the data set
    with pytest.raises(OutputError, match=r"holds .*synthetic/my_db, which drcpo did not write"):
        write_synthetic_kitti(root, 1, seed=1, overwrite=True)
    GroundTruthDatabase.open(root / "my_db").verify()  # still there, whole


def test_an_array_header_promising_too_much_memory_names_the_file(tmp_path):
    db = _database(tmp_path / "db")
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': (4000000000000, 7), }"
    header = header + " " * (117 - len(header)) + "\n"
    (db / "boxes.npy").write_bytes(
        b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode()
    )
    with pytest.raises(DataError, match=r"boxes\.npy: unreadable array \(its header asks"):
        GroundTruthDatabase.open(db)


def test_a_vertical_road_plane_names_its_file_in_plain_numbers(tmp_path):
    from drcpo.datasets.kitti import read_plane

    path = tmp_path / "000000.txt"
    path.write_text("# Plane\nWidth 4\nHeight 1\n1.0 0.0 0.0 1.65\n")
    with pytest.raises(
        DataError, match=r"000000\.txt:4: the road plane '1.0 0.0 0.0 1.65' is vertical"
    ) as caught:
        read_plane(path)
    assert "array(" not in str(caught.value)


def test_a_file_size_limit_while_saving_names_the_file(tmp_path):
    """Under ``ulimit -f`` (Python ignores SIGXFSZ, so writes fail short) the error names the
    array being written and why, and nothing is left behind."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent(
        """
        import resource, sys
        import numpy as np
        from drcpo.database import GroundTruthDatabase
        from drcpo.errors import OutputError
        resource.setrlimit(resource.RLIMIT_FSIZE, (50_000, 50_000))
        points = np.zeros((20_000, 4), np.float32)
        offsets = np.array([0, 10_000, 20_000])
        boxes = np.array([[0, 0, 0, 4, 2, 1.5, 0]] * 2, float)
        db = GroundTruthDatabase.from_arrays(points, offsets, ["Car", "Car"], boxes)
        try:
            db.save(sys.argv[1])
        except OutputError as exc:
            print(exc)
        """
    )
    out = tmp_path / "db"
    done = subprocess.run([sys.executable, "-c", script, str(out)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "points.npy" in done.stdout and "file-size limit" in done.stdout, done.stdout
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == []
