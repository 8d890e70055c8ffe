"""The command line on bad input: one line naming the culprit, a non-zero exit, no traceback."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import drcpo.cli
from drcpo.cli import app
from drcpo.database import GroundTruthDatabase
from drcpo.errors import DataError

CALIB_TEXT = (
    "P2: 7.215377e+02 0 6.095593e+02 4.485728e+01 0 7.215377e+02 1.72854e+02 2.163791e-01 "
    "0 0 1 2.745884e-03\n"
    "R0_rect: 9.999239e-01 9.83776e-03 -7.445048e-03 -9.869795e-03 9.999421e-01 -4.278459e-03 "
    "7.402527e-03 4.351614e-03 9.999631e-01\n"
    "Tr_velo_to_cam: 7.533745e-03 -9.999714e-01 -6.16602e-04 -4.069766e-03 1.480249e-02 "
    "7.280733e-04 -9.998902e-01 -7.631618e-02 9.998621e-01 7.52379e-03 1.480755e-02 "
    "-2.717806e-01\n"
)
ZERO_R0 = "R0_rect: " + " ".join(["0"] * 9) + "\n"
LABEL = "Car 0.00 0 1.85 387.63 181.54 423.81 203.12 1.67 1.87 3.69 -16.53 2.39 58.49 1.57\n"


def _one_line_error(result, *words: str) -> str:
    """The message of a failed run: one line (after any progress bar), no traceback."""
    text = result.output.strip()
    assert "Traceback" not in text, text
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    messages = [line for line in text.splitlines() if line.startswith(("error:", "interrupted"))]
    assert len(messages) == 1 and text.endswith(messages[0]), text
    for word in words:
        assert word in messages[0], text
    return messages[0]


def _database(path: Path, names=("Car", "Car", "Pedestrian", "Car")) -> Path:
    rng = np.random.default_rng(0)
    sizes = np.array([6, 8, 5, 7])
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    points = rng.uniform(-0.5, 0.5, (offsets[-1], 4)).astype(np.float32)
    boxes = np.column_stack([rng.normal(size=(4, 3)), [[3.9, 1.6, 1.5]] * 4, np.zeros(4)])
    GroundTruthDatabase.from_arrays(points, offsets, list(names), boxes).save(path)
    return path


def _kitti(root: Path, calib: str = CALIB_TEXT) -> Path:
    (root / "ImageSets").mkdir(parents=True)
    (root / "ImageSets" / "train.txt").write_text("000000\n")
    base = root / "training"
    for sub in ("velodyne", "label_2", "calib"):
        (base / sub).mkdir(parents=True)
    points = np.array([[10.0, 0.0, -1.0, 0.5], [20.0, 1.0, -1.5, 0.1]], np.float32)
    points.tofile(base / "velodyne" / "000000.bin")
    (base / "label_2" / "000000.txt").write_text(LABEL)
    (base / "calib" / "000000.txt").write_text(calib)
    return root


runner = CliRunner()


# Defect 9: ordinary bad input -------------------------------------------------------------
@pytest.mark.parametrize("command", ["augment", "synth", "demo"])
def test_negative_seed_is_refused_at_the_command_line(tmp_path, command):
    required = {
        "augment": ["--kitti", str(tmp_path), "--db", str(tmp_path), "--out", str(tmp_path / "o")],
        "synth": ["--out", str(tmp_path / "o")],
        "demo": ["--out", str(tmp_path / "o")],
    }[command]
    result = runner.invoke(app, [command, *required, "--seed", "-1"])
    assert result.exit_code == 2  # a usage error, before any work
    assert "Invalid value for '--seed'" in result.output
    # typer's wording varies with its version
    assert "greater than or equal to 0" in result.output or "x>=0" in result.output
    assert "Traceback" not in result.output and not (tmp_path / "o").exists()


def test_build_db_with_a_singular_calibration_names_the_file(tmp_path):
    kitti = _kitti(
        tmp_path / "kitti", CALIB_TEXT.replace(CALIB_TEXT.splitlines()[1] + "\n", ZERO_R0)
    )
    result = runner.invoke(app, ["build-db", "--kitti", str(kitti), "--out", str(tmp_path / "db")])
    assert result.exit_code == 1
    _one_line_error(result, "calib/000000.txt:2: R0_rect is singular")
    assert not (tmp_path / "db").exists()


def test_augment_with_a_singular_calibration_names_the_file(tmp_path):
    zero_tr = "Tr_velo_to_cam: " + " ".join(["0"] * 12) + "\n"
    kitti = _kitti(
        tmp_path / "kitti", CALIB_TEXT.replace(CALIB_TEXT.splitlines()[2] + "\n", zero_tr)
    )
    db = _database(tmp_path / "db")
    args = ["--kitti", str(kitti), "--db", str(db), "--out", str(tmp_path / "out")]
    result = runner.invoke(app, ["augment", *args, "--pipeline", "cda"])
    assert result.exit_code == 1
    _one_line_error(result, "calib/000000.txt:3: Tr_velo_to_cam is singular")
    assert not (tmp_path / "out").exists()


def test_augment_with_a_non_utf8_config_names_the_file(tmp_path):
    config = tmp_path / "latin1.yaml"
    config.write_bytes("# Fußgänger\n".encode("latin-1"))
    args = ["--kitti", str(tmp_path), "--db", str(tmp_path), "--out", str(tmp_path / "out")]
    result = runner.invoke(app, ["augment", *args, "--config", str(config)])
    assert result.exit_code == 1
    _one_line_error(result, "latin1.yaml: not UTF-8 text")


def test_augment_with_a_misspelt_class_names_the_key(tmp_path):
    config = tmp_path / "typo.yaml"
    config.write_text("drcpo:\n  sample: {Pedestrain: 10}\n")
    args = ["--kitti", str(tmp_path), "--db", str(tmp_path), "--out", str(tmp_path / "out")]
    result = runner.invoke(app, ["augment", *args, "--config", str(config)])
    assert result.exit_code == 1
    _one_line_error(result, "typo.yaml", "drcpo.sample.Pedestrain", "did you mean 'Pedestrian'")


def test_index_with_an_absurd_k_is_refused_before_allocating(tmp_path):
    db = _database(tmp_path / "db")
    result = runner.invoke(app, ["index", str(db), "--k", str(10**12)])
    assert result.exit_code == 1
    _one_line_error(result, "'index.k' = 1000000000000 is out of range; allowed range: [1, 100000]")
    assert not (db / "index").exists()


def test_index_of_a_database_with_integer_names_names_the_file(tmp_path):
    db = _database(tmp_path / "db")
    np.save(db / "names.npy", np.array([1, 1, 2, 1]))
    result = runner.invoke(app, ["index", str(db)])
    assert result.exit_code == 1
    _one_line_error(result, "names.npy", "must be strings, got int64")


# The safety net around every command ------------------------------------------------------
def _failing_open(error: BaseException):
    def open_database(path, verify=True):
        raise error

    return open_database


@pytest.mark.parametrize(
    ("error", "code", "words"),
    [
        (DataError("db/manifest.json: bad"), 1, ["error:", "db/manifest.json: bad"]),
        (KeyboardInterrupt(), 130, ["interrupted"]),
        (
            MemoryError("Unable to allocate 29.1 TiB for an array with shape (8, 10**12)"),
            1,
            ["error: out of memory", "29.1 TiB"],
        ),
        (
            PermissionError(errno.EACCES, "Permission denied", "/data/db/points.npy"),
            1,
            ["error: /data/db/points.npy: Permission denied"],
        ),
        (
            OSError(errno.ENOSPC, "No space left on device", "/out/.db.tmp-1/points.npy"),
            1,
            ["error: /out/.db.tmp-1/points.npy: No space left on device"],
        ),
        (
            OSError(errno.EXDEV, "Invalid cross-device link", "/a/tmp", None, "/b/db"),
            1,
            ["error: /a/tmp -> /b/db: Invalid cross-device link"],
        ),
        (OSError("device gone"), 1, ["error: device gone"]),
    ],
    ids=lambda x: type(x).__name__ if isinstance(x, BaseException) else None,
)
def test_errors_a_user_can_meet_are_one_line_and_an_exit_status(
    tmp_path, monkeypatch, error, code, words
):
    monkeypatch.delenv("DRCPO_DEBUG", raising=False)
    monkeypatch.setattr(GroundTruthDatabase, "open", staticmethod(_failing_open(error)))
    result = runner.invoke(app, ["info", str(tmp_path)])
    assert result.exit_code == code
    _one_line_error(result, *words)


def test_main_is_the_same_safety_net(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("DRCPO_DEBUG", raising=False)
    monkeypatch.setattr(GroundTruthDatabase, "open", staticmethod(_failing_open(MemoryError())))
    monkeypatch.setattr(sys, "argv", ["drcpo", "info", str(tmp_path)])
    with pytest.raises(SystemExit) as info:
        drcpo.cli.main()
    assert info.value.code == 1
    assert capsys.readouterr().err.strip() == "error: out of memory"


def test_debug_env_var_lets_the_exception_through(tmp_path, monkeypatch):
    monkeypatch.setenv("DRCPO_DEBUG", "1")
    error = PermissionError(errno.EACCES, "Permission denied", "/data/db")
    monkeypatch.setattr(GroundTruthDatabase, "open", staticmethod(_failing_open(error)))
    result = runner.invoke(app, ["info", str(tmp_path)])
    assert result.exception is error


def test_programming_errors_keep_their_traceback(tmp_path, monkeypatch):
    monkeypatch.delenv("DRCPO_DEBUG", raising=False)
    error = TypeError("a bug")
    monkeypatch.setattr(GroundTruthDatabase, "open", staticmethod(_failing_open(error)))
    assert runner.invoke(app, ["info", str(tmp_path)]).exception is error


def test_installed_entry_point_prints_one_line_and_exits_1(tmp_path):
    # End to end, as a user runs it: a fresh interpreter through drcpo.cli:main.
    db = _database(tmp_path / "db")
    np.save(db / "names.npy", np.array([1, 1, 2, 1]))
    env = {k: v for k, v in os.environ.items() if k != "DRCPO_DEBUG"}
    code = (
        "import sys; from drcpo.cli import main; sys.argv = ['drcpo', 'info', sys.argv[1]]; main()"
    )
    done = subprocess.run(
        [sys.executable, "-c", code, str(db)], capture_output=True, text=True, env=env, timeout=120
    )
    assert done.returncode == 1
    assert done.stdout == ""
    assert done.stderr.strip().splitlines() == [
        f"error: {db / 'names.npy'}: names must be strings, got int64 "
        "(a drcpo database stores names as text, e.g. 'Car')"
    ]


def test_index_help_says_an_explicit_option_wins_over_the_config():
    result = runner.invoke(app, ["index", "--help"], env={"COLUMNS": "200"})
    assert result.exit_code == 0
    text = " ".join(result.output.split())
    assert "--config" in text and "an option given explicitly wins over the config" in text
    assert "default: index.k of --config, 400" in text


# Reliability: a split is a name, never a path; a frame listed twice is refused ----------------
def _tree(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


@pytest.mark.parametrize("command", ["augment", "build-db", "evaluate"])
def test_a_split_given_as_a_path_is_refused_and_nothing_is_written(tmp_path, command):
    kitti = _kitti(tmp_path / "kitti")
    (kitti / "ImageSets" / "train.txt").write_text("000000\n000001\n")
    db = _database(tmp_path / "db")
    before = _tree(tmp_path)
    split = str(kitti / "ImageSets" / "train")
    args = {
        "augment": ["augment", "--kitti", str(kitti), "--db", str(db), "--out",
                    str(tmp_path / "out"), "--pipeline", "cda", "--frames", "1"],
        "build-db": ["build-db", "--kitti", str(kitti), "--out", str(tmp_path / "out")],
        "evaluate": ["evaluate", "--gt", str(kitti), "--pred", str(kitti / "training" / "label_2")],
    }[command]  # fmt: skip
    for bad in (split, "../train", "ImageSets/train"):
        result = runner.invoke(app, [*args, "--split", bad])
        assert result.exit_code == 1, result.output
        _one_line_error(result, "is not a split name")
        assert _tree(tmp_path) == before  # the input's train.txt untouched, no output


def test_a_frame_listed_twice_in_a_split_is_refused_naming_both_lines(tmp_path):
    from drcpo.datasets.kitti import read_split
    from drcpo.datasets.kitti_writer import write_image_sets

    kitti = _kitti(tmp_path / "kitti")
    (kitti / "ImageSets" / "train.txt").write_text("000000\n000001\n\n000000\n")
    with pytest.raises(
        DataError, match=r"train\.txt:4: frame id '000000' listed twice \(first on line 1\)"
    ):
        read_split(kitti, "train")
    db = _database(tmp_path / "db")
    args = ["--kitti", str(kitti), "--db", str(db), "--out", str(tmp_path / "out")]
    result = runner.invoke(app, ["augment", *args, "--pipeline", "cda"])
    assert result.exit_code == 1
    _one_line_error(result, "listed twice")
    result = runner.invoke(app, ["build-db", "--kitti", str(kitti), "--out", str(tmp_path / "db2")])
    assert result.exit_code == 1
    _one_line_error(result, "listed twice")
    with pytest.raises(DataError, match="is not a split name"):
        write_image_sets(tmp_path / "x", {"../escape": ["000000"]})
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("version", ["/abs/v1.0", "../x", "v1.0/../../y", ""])
def test_synth_nuscenes_refuses_a_version_that_is_a_path(tmp_path, version):
    (tmp_path / "neighbour").mkdir()
    (tmp_path / "neighbour" / "scene.json").write_text("theirs")
    before = _tree(tmp_path)
    args = ["synth", "--layout", "nuscenes", "--out", str(tmp_path / "out"), "--frames", "1"]
    result = runner.invoke(app, [*args, "--version", version])
    assert result.exit_code == 1, result.output
    _one_line_error(result, "is not a plain name")
    assert _tree(tmp_path) == before and not (tmp_path / "out").exists()


def test_an_output_inside_an_input_is_refused(tmp_path):
    kitti = _kitti(tmp_path / "kitti")
    db = _database(tmp_path / "db")
    before = _tree(tmp_path)
    for out in (db / "augmented", kitti / "augmented"):
        args = ["--kitti", str(kitti), "--db", str(db), "--out", str(out), "--pipeline", "cda"]
        result = runner.invoke(app, ["augment", *args])
        assert result.exit_code == 1, result.output
        _one_line_error(result, "the output lies inside the input")
    result = runner.invoke(app, ["build-db", "--kitti", str(kitti), "--out", str(kitti / "db")])
    _one_line_error(result, "the output lies inside the input")
    assert _tree(tmp_path) == before


def test_demo_into_a_directory_of_the_users_is_refused(tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "demo.json").write_text('{"my": "notes"}')
    (mine / "bev.png").write_bytes(b"my picture")
    result = runner.invoke(app, ["demo", "--out", str(mine), "--frames", "1"])
    assert result.exit_code == 1
    _one_line_error(result, "is not a drcpo demo output")
    (mine / "demo.json").unlink()
    result = runner.invoke(app, ["demo", "--out", str(mine), "--frames", "1"])
    _one_line_error(result, "is not a drcpo demo output")
    assert (mine / "bev.png").read_bytes() == b"my picture"
    assert not (mine / "kitti").exists() and not (mine / "summary.json").exists()


def test_demo_marks_its_output_and_a_rerun_may_use_it(tmp_path):
    from drcpo.demo import DEMO_OUTPUT
    from drcpo.outputs import check_output

    out = tmp_path / "demo"
    out.mkdir()
    (out / "demo.json").write_text('{"format": "drcpo-demo"}')
    (out / "bev.png").write_bytes(b"an earlier demo's")
    (out / "summary.json").write_text("{}")
    assert check_output(out, DEMO_OUTPUT, overwrite=True) == out.resolve()
    (out / "NOTES.txt").write_text("mine")
    with pytest.raises(Exception, match=r"holds .*NOTES\.txt, which drcpo did not write"):
        check_output(out, DEMO_OUTPUT, overwrite=True)


@pytest.mark.parametrize("out", ["", ".", ".."])
def test_an_output_that_is_the_working_directory_is_refused(tmp_path, monkeypatch, out):
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    result = runner.invoke(app, ["synth", "--out", out, "--frames", "1", "--overwrite"])
    assert result.exit_code == 1, result.output
    _one_line_error(result, "working directory")
    assert list(tmp_path.iterdir()) == [work] and not any(work.iterdir())
