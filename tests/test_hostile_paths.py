"""Every writing command against hostile paths: outputs, locks and staging entries that are
symbolic links, absolute and ``..`` names, outputs nested in inputs. Whatever each command
answers, no file outside its output may change: a snapshot of the whole tree (file bytes and
link targets) before and after is compared."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from export_support import small_kitti
from typer.testing import CliRunner

from drcpo.cli import app

runner = CliRunner()


def snapshot(root: Path, skip: Path | None = None) -> dict[str, object]:
    """Every entry under ``root`` but ``skip`` (the output): bytes of files, targets of links."""
    out: dict[str, object] = {}
    for directory, subdirectories, files in os.walk(root):
        for name in [*subdirectories, *files]:
            path = Path(directory) / name
            if skip is not None and (path == skip or skip in path.parents):
                continue
            key = str(path.relative_to(root))
            if path.is_symlink():
                out[key] = ("link", os.readlink(path))
            elif path.is_file():
                out[key] = path.read_bytes()
            else:
                out[key] = "dir"
    return out


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A KITTI root, its database and index, and a directory of someone else's files."""
    base = tmp_path_factory.mktemp("hostile")
    kitti = small_kitti(base / "kitti", frames=3, points=800)
    result = runner.invoke(app, ["build-db", "--kitti", str(kitti), "--out", str(base / "db")])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["index", str(base / "db"), "--k", "4"])
    assert result.exit_code == 0, result.output
    return base


@pytest.fixture
def sandbox(world, tmp_path):
    """A fresh copy of the world, with ``elsewhere/`` holding files that are not drcpo's."""
    for name in ("kitti", "db"):
        shutil.copytree(world / name, tmp_path / name, symlinks=True)
    elsewhere = tmp_path / "elsewhere"
    (elsewhere / "real").mkdir(parents=True)
    (elsewhere / "precious.txt").write_text("not drcpo's")
    (elsewhere / "real" / "notes.txt").write_text("mine")
    return tmp_path


def commands(box: Path, out: Path) -> dict[str, list[str]]:
    kitti, db = box / "kitti", box / "db"
    return {
        "synth": ["synth", "--out", str(out), "--frames", "1"],
        "build-db": ["build-db", "--kitti", str(kitti), "--out", str(out)],
        "augment": ["augment", "--kitti", str(kitti), "--db", str(db), "--out", str(out),
                    "--pipeline", "cda"],
        "demo": ["demo", "--out", str(out), "--frames", "1", "--augment-frames", "1"],
    }  # fmt: skip


WRITERS = ["synth", "build-db", "augment"]


def run(args: list[str]):
    return runner.invoke(app, args)


@pytest.mark.parametrize("command", [*WRITERS, "demo"])
@pytest.mark.parametrize("target", ["existing directory", "dangling", "file"])
def test_an_output_that_is_a_symbolic_link_is_refused(sandbox, command, target):
    out = sandbox / "out"
    pointed = {
        "existing directory": sandbox / "elsewhere" / "real",
        "dangling": sandbox / "elsewhere" / "new",
        "file": sandbox / "elsewhere" / "precious.txt",
    }[target]
    out.symlink_to(pointed)
    before = snapshot(sandbox)
    result = run(commands(sandbox, out)[command])
    assert result.exit_code != 0
    assert "symbolic link" in result.output and "Traceback" not in result.output
    assert snapshot(sandbox) == before  # the link itself included


@pytest.mark.parametrize("command", [*WRITERS, "index"])
def test_a_lock_that_is_a_symbolic_link_is_refused(sandbox, command):
    out = sandbox / "out"
    argv = commands(sandbox, out).get(command)
    lock = sandbox / ".out.lock"
    if command == "index":  # the index is written inside its database
        argv, lock = ["index", str(sandbox / "db"), "--overwrite"], sandbox / "db" / ".index.lock"
    lock.symlink_to(sandbox / "elsewhere" / "precious.txt")
    before = snapshot(sandbox)
    result = run(argv)
    assert result.exit_code != 0 and "is a symbolic link" in result.output
    assert snapshot(sandbox) == before


@pytest.mark.parametrize("command", WRITERS)
def test_a_staging_or_temporary_name_that_is_a_link_writes_nothing_through_it(sandbox, command):
    out = sandbox / "out"
    (sandbox / ".out.staging").symlink_to(sandbox / "elsewhere" / "real", True)
    before = snapshot(sandbox, skip=out)
    result = run(commands(sandbox, out)[command])
    # augment's staging directory is in the way (not drcpo's): refused; the others do not
    # stage, and write beside it
    assert "Traceback" not in result.output
    assert snapshot(sandbox, skip=out) == before
    assert (sandbox / "elsewhere" / "real" / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize(
    "argv",
    [
        ["augment", "--split", "{elsewhere}/x", "--frames", "1"],
        ["augment", "--split", "../../elsewhere/x", "--frames", "1"],
        ["build-db", "--split", "../elsewhere/x"],
        ["synth", "--layout", "nuscenes", "--version", "{elsewhere}/v1.0"],
        ["synth", "--layout", "nuscenes", "--version", "../elsewhere"],
    ],
    ids=lambda a: " ".join(a[:3]),
)
def test_absolute_and_dotdot_names_are_refused(sandbox, argv):
    out = sandbox / "out"
    argv = [a.format(elsewhere=sandbox / "elsewhere") for a in argv]
    base = commands(sandbox, out)[argv[0]]
    before = snapshot(sandbox)
    result = run([*base, *argv[1:]])
    assert result.exit_code == 1 and "Traceback" not in result.output
    assert snapshot(sandbox) == before


@pytest.mark.parametrize(
    ("command", "inside"),
    [("augment", "db"), ("augment", "kitti"), ("build-db", "kitti")],
)
def test_outputs_nested_in_inputs_are_refused(sandbox, command, inside):
    out = sandbox / inside / "nested"
    before = snapshot(sandbox)
    result = run(commands(sandbox, out)[command])
    assert result.exit_code == 1 and "lies inside the input" in result.output
    assert snapshot(sandbox) == before


@pytest.mark.parametrize("command", ["synth", "build-db"])
def test_overwrite_of_an_output_holding_foreign_files_is_refused(sandbox, command):
    out = sandbox / "out"
    assert run(commands(sandbox, out)[command]).exit_code == 0
    (out / "NOTES.txt").write_text("mine")
    before = snapshot(sandbox)
    result = run([*commands(sandbox, out)[command], "--overwrite"])
    assert result.exit_code == 1 and "NOTES.txt, which drcpo did not write" in result.output
    assert snapshot(sandbox) == before


def test_evaluate_writes_nothing(sandbox):
    kitti = sandbox / "kitti"
    before = snapshot(sandbox)
    labels = kitti / "training" / "label_2"
    result = run(["evaluate", "--gt", str(kitti), "--pred", str(labels), "--split", "train"])
    assert "Traceback" not in result.output
    assert snapshot(sandbox) == before


@pytest.mark.parametrize("command", ["import-openpcdet", "import-mmdet3d"])
def test_imports_refuse_a_symbolic_link_output_and_an_output_inside_their_data(
    kitti_sample, tmp_path, command
):
    root = tmp_path / "openpcdet"
    shutil.copytree(kitti_sample / "gt_database", root / "gt_database")
    shutil.copy(kitti_sample / "kitti_dbinfos_train.pkl", root / "kitti_dbinfos_train.pkl")
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "out").symlink_to(tmp_path / "elsewhere" / "db")
    pkl = str(root / "kitti_dbinfos_train.pkl")
    before = snapshot(tmp_path)
    for out in (tmp_path / "out", root / "db"):
        result = run([command, pkl, "--out", str(out)])
        assert result.exit_code == 1 and "Traceback" not in result.output
        assert "symbolic link" in result.output or "lies inside the input" in result.output
    assert snapshot(tmp_path) == before
