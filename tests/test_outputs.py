"""Output safety (drcpo.outputs): what --overwrite may replace, one writer at a time, a replace
that a kill cannot turn into nothing, temporaries of dead runs, SIGTERM, OS errors."""

from __future__ import annotations

import ctypes
import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from drcpo import outputs
from drcpo.database import DATABASE_OUTPUT, GroundTruthDatabase, ObjectRecord
from drcpo.errors import DataError, OutputError, OutputExistsError
from drcpo.outputs import Interrupted, OutputKind, check_output, write_directory

KIND = OutputKind("test output", "marker.json", "drcpo-test")
SRC = str(Path(__file__).resolve().parents[1] / "src")


def fill(text: str):
    """A ``write`` callback: a payload file, then the marker (last, as real writers do)."""

    def write(tmp: Path) -> None:
        (tmp / "payload.txt").write_text(text)
        (tmp / KIND.marker).write_text(json.dumps({"format": KIND.format}))

    return write


def payload(path: Path) -> str:
    assert KIND.owns(path), f"{path} is not a complete output"
    return (path / "payload.txt").read_text()


def hidden(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name.startswith("."))


def small_database(seed: int = 0, n: int = 3) -> GroundTruthDatabase:
    rng = np.random.default_rng(seed)
    records = [
        ObjectRecord(
            rng.normal(size=(5, 4)).astype(np.float32),
            "Car",
            np.r_[rng.normal(size=3), 4, 2, 1.5, 0],
        )
        for _ in range(n)
    ]
    return GroundTruthDatabase.from_records(records)


def small_kitti(root: Path, frames: int = 3) -> Path:
    """A tiny KITTI root written with drcpo's writer: ``frames`` frames of split train."""
    from drcpo.datasets.kitti_writer import reference_calibration, write_frame, write_image_sets

    rng = np.random.default_rng(7)
    ids = [f"{i:06d}" for i in range(frames)]
    for frame_id in ids:
        points = np.column_stack(
            [rng.uniform(5, 40, 500), rng.uniform(-10, 10, 500), rng.uniform(-1.5, 1, 500)]
        )
        points = np.column_stack([points, rng.uniform(0, 1, 500)]).astype(np.float32)
        box = np.array([[15.0, 0.0, -0.8, 4.0, 1.7, 1.5, 0.3]])
        write_frame(root, frame_id, points, box, ["Car"], reference_calibration())
    write_image_sets(root, {"train": ids})
    return root


def run_script(code: str, *args: str, **kwargs) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": SRC}
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code), *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
        **kwargs,
    )


# Defect 5: --overwrite replaces only drcpo's own outputs, never an input ---------------------
def test_overwrite_refuses_a_directory_drcpo_did_not_write(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "holiday.jpg").write_bytes(b"\xff\xd8 not a database")
    with pytest.raises(OutputError, match=r"photos is not a drcpo database \(it has no manifest"):
        small_database().save(photos, overwrite=True)
    with pytest.raises(OutputError, match="not a test output"):
        write_directory(photos, fill("new"), KIND, overwrite=True)
    assert [p.name for p in photos.iterdir()] == ["holiday.jpg"]
    assert hidden(tmp_path) == []


def test_overwrite_refuses_another_kind_of_drcpo_output_and_a_file(tmp_path):
    from drcpo.index import INDEX_OUTPUT

    small_database().save(tmp_path / "db")
    with pytest.raises(OutputError, match="has no marker.json"):
        write_directory(tmp_path / "db", fill("new"), KIND, overwrite=True)
    expected = "format 'drcpo-gt-database', not 'drcpo-candidate-index'"
    with pytest.raises(OutputError, match=expected):
        write_directory(tmp_path / "db", fill("new"), INDEX_OUTPUT, overwrite=True)
    GroundTruthDatabase.open(tmp_path / "db").verify()
    (tmp_path / "notes.txt").write_text("keep")
    with pytest.raises(OutputError, match="is not a directory"):
        write_directory(tmp_path / "notes.txt", fill("new"), KIND, overwrite=True)
    assert (tmp_path / "notes.txt").read_text() == "keep"


def test_overwrite_replaces_its_own_kind_and_an_empty_directory(tmp_path):
    (tmp_path / "empty").mkdir()
    write_directory(tmp_path / "empty", fill("one"), KIND, overwrite=True)
    assert payload(tmp_path / "empty") == "one"
    with pytest.raises(OutputExistsError, match="already exists"):
        write_directory(tmp_path / "empty", fill("two"), KIND)
    write_directory(tmp_path / "empty", fill("two"), KIND, overwrite=True)
    assert payload(tmp_path / "empty") == "two"
    assert hidden(tmp_path) == []


def test_an_output_may_not_be_contain_or_lie_inside_an_input(tmp_path):
    data = tmp_path / "data"
    (data / "training").mkdir(parents=True)
    link = tmp_path / "link"
    link.symlink_to(data)
    with pytest.raises(OutputError, match="the output is the input"):
        check_output(data, KIND, True, inputs=[data])
    with pytest.raises(OutputError, match="the output is the input"):
        check_output(link, KIND, True, inputs=[data])  # through a symbolic link
    with pytest.raises(OutputError, match="the output contains the input"):
        check_output(tmp_path, KIND, True, inputs=[data / "training"])
    # inside an input, a later --overwrite of that input would take the output along
    with pytest.raises(OutputError, match="the output lies inside the input"):
        check_output(data / "db", KIND, inputs=[data])
    with pytest.raises(OutputError, match="the output lies inside the input"):
        check_output(link / "training" / "db", KIND, inputs=[data])
    assert check_output(tmp_path / "db", KIND, inputs=[data]) == (tmp_path / "db").resolve()


def test_build_db_overwrite_keeps_a_foreign_directory(tmp_path):
    from typer.testing import CliRunner

    from drcpo.cli import app

    root = small_kitti(tmp_path / "kitti")
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "holiday.jpg").write_bytes(b"jpeg")
    args = ["build-db", "--kitti", str(root), "--out", str(photos), "--overwrite"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 1
    assert "error:" in result.output and "not a drcpo database" in result.output
    assert "Traceback" not in result.output
    assert [p.name for p in photos.iterdir()] == ["holiday.jpg"]
    inside = CliRunner().invoke(app, [*args[:4], str(root), "--overwrite"])
    assert inside.exit_code == 1 and "the output is the input" in inside.output
    assert len(list((root / "training" / "velodyne").iterdir())) == 3


def test_augment_refuses_to_write_over_its_inputs(tmp_path):
    from drcpo.datasets.export import augment_kitti
    from drcpo.transforms import GlobalFlip

    root = small_kitti(tmp_path / "kitti")
    before = sorted(p.name for p in (root / "training" / "velodyne").iterdir())
    with pytest.raises(OutputError, match="the output is the input"):
        augment_kitti(root, "train", GlobalFlip(), root, frames=1, overwrite=True)
    assert sorted(p.name for p in (root / "training" / "velodyne").iterdir()) == before
    small_database().save(tmp_path / "db")
    with pytest.raises(OutputError, match="the output is the input"):
        augment_kitti(
            root, "train", GlobalFlip(), tmp_path / "db", overwrite=True, inputs=[tmp_path / "db"]
        )
    GroundTruthDatabase.open(tmp_path / "db").verify()
    # Its own output it replaces; augment.json marks it as drcpo's.
    augment_kitti(root, "train", GlobalFlip(), tmp_path / "aug", frames=2, seed=3)
    marker = json.loads((tmp_path / "aug" / "augment.json").read_text())
    assert marker["format"] == "drcpo-augmented-kitti" and marker["frames"] == 2
    first = (tmp_path / "aug" / "training" / "velodyne" / "000001.bin").read_bytes()
    augment_kitti(root, "train", GlobalFlip(), tmp_path / "aug", frames=2, seed=3, overwrite=True)
    assert (tmp_path / "aug" / "training" / "velodyne" / "000001.bin").read_bytes() == first
    assert hidden(tmp_path) == []


# Defect 6: one writer at a time ---------------------------------------------------------------
def test_concurrent_writer_threads_one_wins(tmp_path):
    out = tmp_path / "out"
    started, release = threading.Event(), threading.Event()
    results: dict[str, object] = {}

    def slow(tmp: Path) -> None:
        started.set()
        assert release.wait(30)
        fill("first")(tmp)

    def first() -> None:
        results["first"] = write_directory(out, slow, KIND)

    thread = threading.Thread(target=first)
    thread.start()
    assert started.wait(30)
    with pytest.raises(OutputError, match="another drcpo run is writing it"):
        write_directory(out, fill("second"), KIND, overwrite=True)
    release.set()
    thread.join(30)
    assert results["first"] == out and payload(out) == "first"
    with pytest.raises(OutputExistsError):  # the lock is gone, the output is there
        write_directory(out, fill("second"), KIND)
    assert hidden(tmp_path) == []


def test_concurrent_writer_processes_exactly_one_succeeds(tmp_path):
    script = """
        import sys, time, json
        from pathlib import Path
        from drcpo.outputs import OutputKind, write_directory
        from drcpo.errors import OutputError
        kind = OutputKind("test output", "marker.json", "drcpo-test")
        def write(tmp):
            time.sleep(1.0)
            (tmp / "payload.txt").write_text(sys.argv[2])
            (tmp / "marker.json").write_text(json.dumps({"format": "drcpo-test"}))
        try:
            write_directory(sys.argv[1], write, kind)
        except OutputError as exc:
            print(exc, file=sys.stderr)
            sys.exit(1)
    """
    env = {**os.environ, "PYTHONPATH": SRC}
    runs = [
        subprocess.Popen(
            [sys.executable, "-c", textwrap.dedent(script), str(tmp_path / "out"), name],
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        for name in ("a", "b")
    ]
    codes = [run.wait(60) for run in runs]
    messages = [run.stderr.read() for run in runs]
    assert sorted(codes) == [0, 1], messages
    loser = messages[codes.index(1)]
    assert "another drcpo run is writing it" in loser or "already exists" in loser
    assert payload(tmp_path / "out") == "ab"[codes.index(0)]
    assert hidden(tmp_path) == []


@pytest.mark.parametrize("renameat2", [True, False], ids=["renameat2", "fallback"])
def test_a_directory_appearing_meanwhile_is_not_replaced(tmp_path, monkeypatch, renameat2):
    if not renameat2:  # test seam: a system without renameat2
        monkeypatch.setattr(outputs, "_renameat2", lambda: None)
    out = tmp_path / "out"

    def write(tmp: Path) -> None:
        fill("ours")(tmp)
        out.mkdir()  # another program (not drcpo: it takes no lock) creates it meanwhile
        (out / "theirs.txt").write_text("theirs")

    with pytest.raises(OutputError, match="exists"):
        write_directory(out, write, KIND)
    assert [p.name for p in out.iterdir()] == ["theirs.txt"]
    assert hidden(tmp_path) == []


# Defect 7: a replace killed half-way leaves the old or the new output -------------------------
KILL_AT_RENAME = """
    import os, signal, sys
    import numpy as np
    from drcpo import outputs
    from drcpo.database import GroundTruthDatabase, ObjectRecord

    mode = sys.argv[2]
    # test seams: no renameat2, and a kill between the replace's steps
    if mode == "fallback":
        outputs._renameat2 = lambda: None
        renames = []
        real_rename = os.rename
        def rename(source, target):
            renames.append(target)
            if len(renames) == 2:  # the old output is moved away, the new one not yet in place
                os.kill(os.getpid(), signal.SIGKILL)
            real_rename(source, target)
        outputs.os.rename = rename
    else:
        real = outputs._rename2
        def rename2(source, target, flags):
            done = real(source, target, flags)
            os.kill(os.getpid(), signal.SIGKILL)  # swapped, the old one not yet removed
            return done
        outputs._rename2 = rename2
    records = [ObjectRecord(np.ones((7, 4), np.float32), "Van", np.r_[0, 0, 0, 4, 2, 1.5, 0])]
    GroundTruthDatabase.from_records(records).save(sys.argv[1], overwrite=True)
"""


@pytest.mark.parametrize("mode", ["exchange", "fallback"])
def test_replace_killed_between_its_steps_keeps_a_complete_output(tmp_path, mode):
    if mode == "exchange" and outputs._renameat2() is None:  # test seam: the system probe
        pytest.skip("renameat2 is not available on this system")
    old = small_database(1, n=3)
    old.save(tmp_path / "db")
    killed = run_script(KILL_AT_RENAME, str(tmp_path / "db"), mode)
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    if mode == "exchange":  # the path holds the new database at every instant
        GroundTruthDatabase.open(tmp_path / "db").verify()
        assert GroundTruthDatabase.open(tmp_path / "db").classes == ["Van"]
    else:  # documented window: nothing at the path until the next run puts the old one back
        assert not (tmp_path / "db").exists()
        assert any(".db.old-" in name for name in hidden(tmp_path))
    assert hidden(tmp_path)  # the killed run's temporaries are still there

    def fails(tmp: Path) -> None:
        raise DataError("this run fails too")

    with pytest.raises(DataError):  # the next run recovers before it even writes
        write_directory(tmp_path / "db", fails, DATABASE_OUTPUT, overwrite=True)
    recovered = GroundTruthDatabase.open(tmp_path / "db")
    recovered.verify()
    expected = ["Van"] if mode == "exchange" else ["Car"]
    assert recovered.classes == expected
    assert hidden(tmp_path) == []


@pytest.mark.parametrize("renameat2", [True, False], ids=["renameat2", "fallback"])
def test_a_signal_during_the_replace_waits_for_it(tmp_path, monkeypatch, renameat2):
    write_directory(tmp_path / "out", fill("old"), KIND)
    if not renameat2:  # test seam: a system without renameat2
        monkeypatch.setattr(outputs, "_renameat2", lambda: None)
    real = outputs._commit  # test seam: a signal just as the output is moved into place

    def commit(*args):
        signal.raise_signal(signal.SIGINT)  # Ctrl-C just as the output is moved into place
        real(*args)

    monkeypatch.setattr(outputs, "_commit", commit)
    with pytest.raises(Interrupted, match="after the output was complete") as caught:
        write_directory(tmp_path / "out", fill("new"), KIND, overwrite=True)
    assert caught.value.complete and caught.value.exit_status == 130
    assert payload(tmp_path / "out") == "new"
    assert hidden(tmp_path) == []


def test_a_signal_during_a_failed_replace_is_not_lost(tmp_path, monkeypatch):
    def commit(*args):
        signal.raise_signal(signal.SIGINT)  # Ctrl-C, then the move itself fails
        raise OSError(errno.ENOSPC, "No space left on device", str(args[1]))

    monkeypatch.setattr(outputs, "_commit", commit)  # test seam: the move fails
    with pytest.raises(KeyboardInterrupt):
        write_directory(tmp_path / "out", fill("new"), KIND)
    assert not (tmp_path / "out").exists()
    assert hidden(tmp_path) == []


# Defect 8: temporaries of dead runs, SIGTERM --------------------------------------------------
def test_stale_temporaries_of_dead_runs_are_removed(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    alive = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        names = [
            f".out.tmp-{dead.pid}-0123abcd",  # removed: its run is gone
            # Removed too: its PID lives, but no run of ours can own it while we hold the lock
            # (the PID was reused).
            f".out.tmp-{alive.pid}-0123abcd",
            ".out.tmp-0123abcd",  # kept: not a name drcpo gives
            f".other.tmp-{dead.pid}-0123abcd",  # kept: another output's
        ]
        for name in names:
            (tmp_path / name).mkdir()
            (tmp_path / name / "points.npy").write_bytes(bytes(1000))
        write_directory(tmp_path / "out", fill("new"), KIND)
        assert hidden(tmp_path) == sorted(names[2:])
    finally:
        alive.kill()
        alive.wait()


SLOW_WRITE = """
    import sys, time
    from drcpo.outputs import OutputKind, write_directory
    def write(tmp):
        (tmp / "partial.npy").write_bytes(bytes(1 << 20))
        print("writing", flush=True)
        time.sleep(60)
    write_directory(sys.argv[1], write, OutputKind("test output", "marker.json", "drcpo-test"))
"""


def test_sigterm_mid_write_removes_the_temporary(tmp_path):
    env = {**os.environ, "PYTHONPATH": SRC}
    run = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(SLOW_WRITE), str(tmp_path / "out")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    assert run.stdout.readline() == "writing\n"
    assert hidden(tmp_path)  # the temporary and the lock
    run.send_signal(signal.SIGTERM)
    _, stderr = run.communicate(timeout=30)
    assert run.returncode != 0
    assert "interrupted by SIGTERM; nothing was written there" in stderr
    assert list(tmp_path.iterdir()) == []


def test_cli_sigterm_mid_write_exits_with_one_line(tmp_path):
    out = tmp_path / "synthetic"
    env = {**os.environ, "PYTHONPATH": SRC}
    command = [sys.executable, "-m", "drcpo.cli", "synth", "--out", str(out), "--frames", "400"]
    run = subprocess.Popen(
        [*command, "--azimuth-step", "2"], stderr=subprocess.PIPE, text=True, env=env
    )
    try:
        for _ in range(6000):  # wait for the temporary (numba may compile first)
            if any(".synthetic.tmp-" in name for name in hidden(tmp_path)) or run.poll():
                break
            time.sleep(0.02)
        run.send_signal(signal.SIGTERM)
        _, stderr = run.communicate(timeout=60)
    finally:
        run.kill()
    assert run.returncode == 128 + signal.SIGTERM, stderr
    lines = [line for line in stderr.splitlines() if "interrupted" in line]
    assert lines == [f"interrupted: {out}: interrupted by SIGTERM; nothing was written there"]
    assert "Traceback" not in stderr
    assert list(tmp_path.iterdir()) == []


# Defect 9: OS errors become one-line OutputErrors naming the path -----------------------------
def test_disk_full_becomes_an_output_error_naming_the_file(tmp_path):
    def write(tmp: Path) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp / "points.npy"))

    with pytest.raises(OutputError) as caught:
        write_directory(tmp_path / "db", write, KIND)
    assert str(caught.value) == (
        f"cannot write {tmp_path / 'db'}: {tmp_path / 'db' / 'points.npy'}: No space left on device"
    )
    assert list(tmp_path.iterdir()) == []


def test_unwritable_output_location_becomes_an_output_error(tmp_path):
    (tmp_path / "file.txt").write_text("a file, not a directory")
    with pytest.raises(OutputError, match=r"cannot write .*file\.txt/db: .*file\.txt"):
        small_database().save(tmp_path / "file.txt" / "db")
    with pytest.raises(OutputError, match=r"cannot write .*file\.txt/fig\.png"):
        outputs.atomic_write_bytes(tmp_path / "file.txt" / "fig.png", b"png")


@pytest.mark.skipif(os.geteuid() == 0, reason="root is never denied permission")
def test_read_only_parent_becomes_an_output_error(tmp_path):
    parent = tmp_path / "read_only"
    parent.mkdir()
    parent.chmod(0o555)
    try:
        with pytest.raises(OutputError, match="Permission denied"):
            small_database().save(parent / "db")
    finally:
        parent.chmod(0o755)


def test_permission_denied_is_a_clear_cli_error(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from drcpo.cli import app

    small_database().save(tmp_path / "db")
    real_read_text = Path.read_text

    def read_text(self, *args, **kwargs):
        if self.name == "manifest.json":
            raise PermissionError(errno.EACCES, "Permission denied", str(self))
        return real_read_text(self, *args, **kwargs)

    monkeypatch.setattr(Path, "read_text", read_text)
    with pytest.raises(DataError, match=r"manifest\.json: cannot read the manifest"):
        GroundTruthDatabase.open(tmp_path / "db")
    result = CliRunner().invoke(app, ["index", str(tmp_path / "db")])
    assert result.exit_code == 1
    assert "manifest.json: cannot read the manifest (Permission denied)" in result.output
    monkeypatch.undo()

    real_open = os.open

    def open_denying_locks(path, *args, **kwargs):
        if str(path).endswith(".lock"):
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", open_denying_locks)
    result = CliRunner().invoke(app, ["synth", "--out", str(tmp_path / "out"), "--frames", "1"])
    assert result.exit_code == 1 and "Traceback" not in result.output
    message = f"cannot write {tmp_path / 'out'}: {tmp_path / '.out.lock'}: Permission denied"
    assert message in " ".join(result.output.split())


def test_interrupted_knows_its_exit_status():
    assert Interrupted("x", signal.SIGTERM).exit_status == 143
    assert "after the output was complete" in str(Interrupted("x", signal.SIGINT, complete=True))


def test_sigterm_whose_exception_is_swallowed_still_stops_the_write(tmp_path):
    # numba's compiler calls back into Python through ctypes, which prints and drops an
    # exception raised there: the SIGTERM must still stop the write before the move.
    def write(tmp: Path) -> None:
        (tmp / KIND.marker).write_text(json.dumps({"format": KIND.format}))
        try:
            signal.raise_signal(signal.SIGTERM)
        except KeyboardInterrupt:
            pass  # what a ctypes callback does with it
        (tmp / "b.txt").write_text("more")

    with pytest.raises(KeyboardInterrupt):
        write_directory(tmp_path / "db", write, KIND)
    assert list(tmp_path.iterdir()) == []
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL


def test_sigterm_in_a_c_callback_prints_no_traceback(tmp_path, capfd, monkeypatch):
    # numba compiling calls back into Python through ctypes: a SIGTERM landing there raises
    # in the callback, which reports the exception as "ignored" with a traceback. The write
    # stops all the same, and that report is left out (the CLI prints one line instead);
    # any other exception a callback drops still reaches the hook in place before.
    reported = []
    monkeypatch.setattr(sys, "unraisablehook", lambda info: reported.append(info.exc_type))
    before = sys.unraisablehook
    terminate = ctypes.CFUNCTYPE(None)(lambda: signal.raise_signal(signal.SIGTERM))
    fail = ctypes.CFUNCTYPE(None)(lambda: 1 / 0)

    def write(tmp: Path) -> None:
        (tmp / KIND.marker).write_text(json.dumps({"format": KIND.format}))
        fail()
        terminate()  # through C: the exception is dropped there
        (tmp / "b.txt").write_text("more")

    with pytest.raises(KeyboardInterrupt):
        write_directory(tmp_path / "db", write, KIND)
    assert list(tmp_path.iterdir()) == []
    assert reported == [ZeroDivisionError]
    assert sys.unraisablehook is before
    err = capfd.readouterr().err
    assert "Traceback" not in err and "Exception ignored" not in err


def test_a_lock_that_is_a_symbolic_link_is_refused_and_its_target_untouched(tmp_path):
    precious = tmp_path / "elsewhere" / "precious.txt"
    precious.parent.mkdir()
    precious.write_text("keep me")
    (tmp_path / ".out.lock").symlink_to(precious)
    with pytest.raises(OutputError, match=r"its lock .*\.out\.lock is a symbolic link"):
        write_directory(tmp_path / "out", fill("one"), KIND)
    assert precious.read_text() == "keep me" and not (tmp_path / "out").exists()
    dangling = tmp_path / ".out2.lock"
    dangling.symlink_to(tmp_path / "elsewhere" / "created.txt")
    with pytest.raises(OutputError, match="is a symbolic link"):
        write_directory(tmp_path / "out2", fill("one"), KIND)
    assert not (tmp_path / "elsewhere" / "created.txt").exists()
