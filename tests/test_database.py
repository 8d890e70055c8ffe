import json

import numpy as np
import pytest

from drcpo.database import DATABASE_OUTPUT, GroundTruthDatabase, ObjectRecord
from drcpo.errors import DataError
from drcpo.outputs import write_directory


def _records(rng, n=6):
    names = ["Car", "Pedestrian", "Cyclist"]
    return [
        ObjectRecord(
            points=rng.normal(size=(int(rng.integers(0, 40)), 4)).astype(np.float32),
            name=names[i % 3],
            box=rng.normal(size=7),
            frame_id=f"{i // 2:06d}",
            index_in_frame=i % 2,
            difficulty=i % 3 - 1,
            occlusion=i % 4 - 1,
            truncation=0.1 * i,
        )
        for i in range(n)
    ]


def test_save_open_round_trip(tmp_path, rng):
    records = _records(rng)
    db = GroundTruthDatabase.from_records(records)
    db.save(tmp_path / "db")
    opened = GroundTruthDatabase.open(tmp_path / "db")
    assert len(opened) == len(records)
    assert opened.checksum == db.compute_checksum() == opened.compute_checksum()
    for i, record in enumerate(records):
        np.testing.assert_array_equal(opened.object_points(i), record.points)
        np.testing.assert_array_equal(opened.boxes[i], record.box)
        assert opened.names[i] == record.name
        assert opened.frame_ids[i] == record.frame_id
    assert isinstance(opened.points, np.memmap)
    opened.verify()


def test_summary_counts(rng):
    db = GroundTruthDatabase.from_records(_records(rng, 9))
    summary = db.summary()
    assert sum(v["objects"] for v in summary.values()) == 9
    assert sum(v["points"] for v in summary.values()) == len(db.points)


def test_corrupted_database_is_detected(tmp_path, rng):
    GroundTruthDatabase.from_records(_records(rng)).save(tmp_path / "db")
    points = np.load(tmp_path / "db" / "points.npy")
    points[0, 0] += 1
    np.save(tmp_path / "db" / "points.npy", points)
    with pytest.raises(DataError, match="checksum"):
        GroundTruthDatabase.open(tmp_path / "db").verify()


def test_open_rejects_missing_and_foreign_directories(tmp_path, rng):
    with pytest.raises(DataError, match="manifest.json"):
        GroundTruthDatabase.open(tmp_path)
    GroundTruthDatabase.from_records(_records(rng)).save(tmp_path / "db")
    manifest = json.loads((tmp_path / "db" / "manifest.json").read_text())
    manifest["format_version"] = 999
    (tmp_path / "db" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DataError, match="format_version"):
        GroundTruthDatabase.open(tmp_path / "db")
    (tmp_path / "db" / "offsets.npy").unlink()
    manifest["format_version"] = 1
    (tmp_path / "db" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DataError, match="offsets.npy"):
        GroundTruthDatabase.open(tmp_path / "db")


def test_interrupted_write_leaves_nothing(tmp_path):
    def write(tmp):
        (tmp / "partial.npy").write_bytes(b"x")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_directory(tmp_path / "db", write, DATABASE_OUTPUT)
    assert list(tmp_path.iterdir()) == []


def test_object_points_bounds(rng):
    db = GroundTruthDatabase.from_records(_records(rng, 3))
    with pytest.raises(IndexError):
        db.object_points(3)


@pytest.mark.parametrize("column", ["names", "frame_ids"])
def test_open_rejects_text_columns_that_are_not_strings(tmp_path, rng, column):
    # A database written by another tool, consistent (checksum included) but with integer
    # class ids in names.npy: before, it opened and `drcpo index` failed while rendering.
    db = GroundTruthDatabase.from_records(_records(rng))
    columns = {name: getattr(db, name) for name in ("boxes", "names", "frame_ids")}
    columns.update(
        index_in_frame=db.index_in_frame,
        num_points=db.num_points,
        difficulty=db.difficulty,
        occlusion=db.occlusion,
        truncation=db.truncation,
    )
    columns[column] = np.arange(len(db), dtype=np.int64)
    GroundTruthDatabase(db.points, db.offsets, columns).save(tmp_path / "db")
    with pytest.raises(DataError, match=rf"db/{column}\.npy: .*must be strings, got int64"):
        GroundTruthDatabase.open(tmp_path / "db")
