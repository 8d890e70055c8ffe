"""``drcpo augment --workers N`` without Ray (drcpo.distributed.local): N local processes give the
same bytes as one, a stopped run resumes on either, a worker's error comes back as itself."""

from __future__ import annotations

import multiprocessing
import os
import shutil
import signal

import pytest
from export_support import random_transform, small_kitti, tree_bytes

from drcpo.datasets.export import augment_kitti
from drcpo.distributed.local import augment_kitti_processes
from drcpo.errors import DataError, DrcpoError
from drcpo.staging import staging_path


@pytest.fixture(scope="module")
def kitti(tmp_path_factory):
    return small_kitti(tmp_path_factory.mktemp("kitti") / "root", frames=8)


@pytest.fixture(scope="module")
def database(kitti, tmp_path_factory):
    from drcpo.database.build import build_database
    from drcpo.index_build import build_index

    path = tmp_path_factory.mktemp("db") / "db"
    db = build_database(kitti, "train", path, ["Car"])
    build_index(db).save(path)
    return path


def drcpo_pipeline(database):
    from drcpo.database import GroundTruthDatabase
    from drcpo.pipeline import build_pipeline

    return build_pipeline("default", GroundTruthDatabase.open(database))


@pytest.fixture(scope="module")
def reference(kitti, database, tmp_path_factory):
    base = tmp_path_factory.mktemp("reference")
    augment_kitti(kitti, "train", random_transform(), base / "global", seed=9)
    augment_kitti(kitti, "train", drcpo_pipeline(database), base / "drcpo", seed=9)
    return base


@pytest.mark.parametrize("kind", ["global", "drcpo"])
def test_worker_processes_write_the_bytes_of_one_process(
    kitti, database, reference, tmp_path, kind
):
    transform = random_transform() if kind == "global" else drcpo_pipeline(database)
    seen = []
    summary = augment_kitti_processes(
        kitti, "train", transform, tmp_path / "out", seed=9, workers=2,
        progress=lambda done, total: seen.append((done, total)),
    )  # fmt: skip
    assert tree_bytes(tmp_path / "out") == tree_bytes(reference / kind)
    assert summary["frames"] == 8 and seen[-1] == (8, 8)
    report = summary["processes"]
    assert report["startup_s"] > 0 and len({w["pid"] for w in report["workers"]}) == 2
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_stopped_run_resumes_on_either_engine(kitti, reference, tmp_path):
    def stop_after(k: int):
        def progress(done: int, total: int) -> None:
            if done >= k:
                raise KeyboardInterrupt

        return progress

    for name, resume in (("processes", augment_kitti_processes), ("one", augment_kitti)):
        out = tmp_path / name
        with pytest.raises(KeyboardInterrupt):
            augment_kitti_processes(
                kitti, "train", random_transform(), out, seed=9, progress=stop_after(3)
            )
        frames = staging_path(out) / "frames"
        done = sorted(p.name for p in frames.iterdir())
        assert 3 <= len(done) < 8 and not out.exists()
        assert not [n for n in done if n.startswith(".")]  # no frame cut off half-way
        summary = resume(kitti, "train", random_transform(), out, seed=9)
        assert summary["resumed"] >= 3
        assert tree_bytes(out) == tree_bytes(reference / "global")


def test_a_bad_frame_in_a_worker_raises_its_own_error(kitti, tmp_path):
    root = tmp_path / "kitti"
    shutil.copytree(kitti, root)
    (root / "training" / "velodyne" / "000005.bin").write_bytes(b"12345")  # not N x 4 float32
    with pytest.raises(DataError, match="000005.bin"):
        augment_kitti_processes(root, "train", random_transform(), tmp_path / "out", workers=2)
    assert not (tmp_path / "out").exists()


def test_a_worker_that_cannot_start_raises_its_error_before_any_frame(kitti, database, tmp_path):
    def hung(signum, frame):
        raise TimeoutError("the run hung: a pool restarts a worker whose start-up raised")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(120)
    try:
        with pytest.raises(DataError, match="no candidate index") as raised:
            augment_kitti_processes(
                kitti, "train", drcpo_pipeline(database), tmp_path / "out", workers=2,
                index_path=tmp_path / "no-index",
            )  # fmt: skip
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    assert any("in worker process" in note for note in raised.value.__notes__)
    assert not (tmp_path / "out").exists()


def test_a_worker_killed_mid_run_stops_it_with_a_clear_error(kitti, reference, tmp_path):
    # A worker killed outright (the kernel's out-of-memory killer, a user's kill -9) sends
    # nothing back: the run must say so rather than wait for its frames for ever.
    def hung(signum, frame):
        raise TimeoutError("the run hung on a dead worker")

    def kill_one(done: int, total: int) -> None:
        if done == 1:
            os.kill(multiprocessing.active_children()[0].pid, signal.SIGKILL)

    out = tmp_path / "out"
    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(120)
    try:
        with pytest.raises(DrcpoError, match="a worker process died while augmenting frame"):
            augment_kitti_processes(
                kitti, "train", random_transform(), out, seed=9, workers=2, progress=kill_one
            )
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    assert not out.exists() and not multiprocessing.active_children()
    # what was written is kept, and the next run finishes the same bytes
    augment_kitti_processes(kitti, "train", random_transform(), out, seed=9, workers=2)
    assert tree_bytes(out) == tree_bytes(reference / "global")


def test_cli_augment_with_worker_processes(kitti, database, reference, tmp_path):
    from typer.testing import CliRunner

    from drcpo.cli import app

    out = tmp_path / "out"
    args = ["augment", "--kitti", str(kitti), "--db", str(database), "--out", str(out)]
    result = CliRunner().invoke(app, [*args, "--seed", "9", "--workers", "2"])
    assert result.exit_code == 0, result.output
    assert "worker processes" in result.output
    assert tree_bytes(out) == tree_bytes(reference / "drcpo")
