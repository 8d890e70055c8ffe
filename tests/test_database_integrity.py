"""A database's data is checked against its manifest checksum (and for NaN/inf) on open, and
an index is never built for (or re-blessed on) a modified database."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_index import random_database
from typer.testing import CliRunner

from drcpo.cli import app
from drcpo.database import GroundTruthDatabase
from drcpo.errors import DataError
from drcpo.index import INDEX_DIRNAME, IndexConfig, load_index
from drcpo.index_build import build_index


@pytest.fixture
def db_dir(tmp_path) -> Path:
    db = random_database(np.random.default_rng(21), 80, classes=("Car", "Pedestrian"))
    db.save(tmp_path / "db")
    build_index(GroundTruthDatabase.open(tmp_path / "db"), IndexConfig(k=4)).save(tmp_path / "db")
    return tmp_path / "db"


def _flip_bit(db_dir: Path) -> None:
    path = db_dir / "points.npy"
    raw = bytearray(path.read_bytes())
    raw[-5] ^= 0x04  # one bit of the last point's z
    path.write_bytes(bytes(raw))


def _nan_point(db_dir: Path, row: int = 17) -> None:
    points = np.load(db_dir / "points.npy")
    points[row, 1] = np.nan
    np.save(db_dir / "points.npy", points)


def _relabel(db_dir: Path) -> None:
    names = np.load(db_dir / "names.npy")
    assert (names == "Pedestrian").any()
    np.save(db_dir / "names.npy", np.where(names == "Pedestrian", "Car", names))


def _bless(db_dir: Path) -> None:
    """Write the tampered data's checksum into the manifest (as a careless fix would)."""
    manifest = json.loads((db_dir / "manifest.json").read_text())
    manifest["checksum"] = GroundTruthDatabase.open(db_dir, verify=False).compute_checksum()
    (db_dir / "manifest.json").write_text(json.dumps(manifest))


TAMPERS = {"flipped_bit": _flip_bit, "relabelled": _relabel}


@pytest.mark.parametrize("tamper", list(TAMPERS))
def test_open_detects_modified_data(db_dir, tamper):
    TAMPERS[tamper](db_dir)
    with pytest.raises(DataError, match=rf"database {db_dir}: .*do not match the checksum"):
        GroundTruthDatabase.open(db_dir)
    opened = GroundTruthDatabase.open(db_dir, verify=False)  # the escape hatch
    assert not opened.verified
    # an index is never built for it, even from a database opened without verification
    with pytest.raises(DataError, match="do not match the checksum"):
        build_index(opened, IndexConfig(k=4))


def test_nan_in_points_names_the_database_file_and_row(db_dir):
    _nan_point(db_dir)
    _bless(db_dir)  # consistent checksum: the value itself is refused
    message = (
        rf"{db_dir / 'points.npy'}: row 17 \(object \d+, \w+\) of database {db_dir} holds a NaN"
    )
    with pytest.raises(DataError, match=message):
        GroundTruthDatabase.open(db_dir)
    _nan_point(db_dir)  # and without the checksum fixed up, the value is what is reported
    with pytest.raises(DataError, match=message):
        GroundTruthDatabase.open(db_dir)


def test_nan_box_is_refused(db_dir):
    boxes = np.load(db_dir / "boxes.npy")
    boxes[5, 0] = np.inf
    np.save(db_dir / "boxes.npy", boxes)
    with pytest.raises(DataError, match=r"boxes\.npy: row 5 \(object 5, \w+\) of database"):
        GroundTruthDatabase.open(db_dir)


def test_verified_database_and_old_checksums(db_dir):
    opened = GroundTruthDatabase.open(db_dir)
    assert opened.verified
    assert opened.verified_checksum() == opened.checksum == opened.compute_checksum()
    assert load_index(opened).database_checksum == opened.checksum
    memory = random_database(np.random.default_rng(3), 10)
    assert memory.verified_checksum() == memory.compute_checksum()


def _cli(*args: str):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.mark.parametrize("tamper", [*TAMPERS, "nan"])
def test_cli_refuses_a_modified_database(db_dir, tmp_path, tamper):
    {**TAMPERS, "nan": _nan_point}[tamper](db_dir)
    index_manifest = (db_dir / INDEX_DIRNAME / "manifest.json").read_text()
    for args in (
        ("info", db_dir),
        ("info", db_dir, "--json"),
        ("index", db_dir, "--k", "4", "--overwrite"),
        # (the database is opened before the KITTI root is read)
        ("augment", "--kitti", tmp_path / "kitti", "--db", db_dir, "--out", tmp_path / "out"),
    ):
        result = _cli(*args)
        assert result.exit_code == 1, (args, result.output)
        assert f"database {db_dir}" in result.output, (args, result.output)
        assert "Traceback" not in result.output
    # the old index was neither rewritten nor "fixed" to the modified data
    assert (db_dir / INDEX_DIRNAME / "manifest.json").read_text() == index_manifest
    assert not (tmp_path / "out").exists()
    # --no-verify opens it (huge databases verified once); the index command still refuses
    assert _cli("info", db_dir, "--no-verify").exit_code == 0
    assert _cli("index", db_dir, "--k", "4", "--overwrite").exit_code == 1


def test_cli_index_overwrite_does_not_bless_a_changed_manifest(db_dir):
    manifest = json.loads((db_dir / "manifest.json").read_text())
    manifest["checksum"] = "sha256:" + "0" * 64  # the manifest changed, the data did not
    (db_dir / "manifest.json").write_text(json.dumps(manifest))
    result = _cli("index", db_dir, "--k", "4", "--overwrite")
    assert result.exit_code == 1 and "do not match the checksum" in result.output
    index_manifest = json.loads((db_dir / INDEX_DIRNAME / "manifest.json").read_text())
    assert index_manifest["database_checksum"] != manifest["checksum"]


def test_cli_info_reports_verification(db_dir):
    verified = json.loads(_cli("info", db_dir, "--json").stdout)
    assert verified["verified"] is True
    assert json.loads(_cli("info", db_dir, "--json", "--no-verify").stdout)["verified"] is False
