"""Offline generation (drcpo.datasets.export): resumable per-frame writes. A run stopped at
frame k (an exception, Ctrl-C, a killed writer's temporaries) resumes with the frames it wrote and
ends with the same bytes as a run never stopped; a staging directory of another run is refused."""

from __future__ import annotations

import json

import pytest
from export_support import random_transform, small_kitti, tree_bytes

from drcpo.datasets.export import TIMINGS_FILE, augment_kitti
from drcpo.errors import DataError, OutputError
from drcpo.outputs import Interrupted
from drcpo.staging import staging_path
from drcpo.transforms import GlobalFlip


@pytest.fixture(scope="module")
def kitti(tmp_path_factory):
    return small_kitti(tmp_path_factory.mktemp("kitti") / "root")


@pytest.fixture(scope="module")
def reference(kitti, tmp_path_factory):
    """The uninterrupted run every other run must equal."""
    out = tmp_path_factory.mktemp("reference") / "out"
    summary = augment_kitti(kitti, "train", random_transform(), out, seed=5)
    assert summary["resumed"] == 0 and summary["frames"] == 6
    return out


def stop_after(k: int, exc: BaseException):
    """A progress callback raising ``exc`` once ``k`` frames are done."""

    def progress(done: int, total: int) -> None:
        if done >= k:
            raise exc

    return progress


def records_in(out):
    return sorted(p.name for p in (staging_path(out) / "frames").iterdir())


def test_output_layout_and_timings_kept_apart(kitti, reference):
    files = tree_bytes(reference, timings=True)
    for frame_id in (f"{i:06d}" for i in range(6)):
        for sub, ext in (("velodyne", "bin"), ("label_2", "txt"), ("calib", "txt")):
            assert f"training/{sub}/{frame_id}.{ext}" in files
    assert files["training/calib/000003.txt"] == (kitti / "training/calib/000003.txt").read_bytes()
    stats = [json.loads(line) for line in files["stats.jsonl"].decode().splitlines()]
    timings = [json.loads(line) for line in files[TIMINGS_FILE].decode().splitlines()]
    assert [s["frame_id"] for s in stats] == [t["frame_id"] for t in timings]
    assert [s["seed"] for s in stats] == [[5, i] for i in range(6)]
    assert "ms" not in files["stats.jsonl"].decode()  # timings only in timings.jsonl
    assert all(t["ms"] >= 0 and "global_flip" in t["stages"] for t in timings)
    assert {"augment.json", "ImageSets/train.txt"} <= set(files)
    assert not [p for p in reference.parent.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize("exc", [KeyboardInterrupt(), RuntimeError("power cut")])
def test_a_stopped_run_resumes_and_ends_identical(kitti, reference, tmp_path, exc):
    out = tmp_path / "out"
    with pytest.raises(type(exc)):
        augment_kitti(kitti, "train", random_transform(), out, seed=5, progress=stop_after(2, exc))
    assert not out.exists()
    assert records_in(out) == ["00000000.json", "00000001.json"]
    if isinstance(exc, KeyboardInterrupt):
        with pytest.raises(Interrupted, match=r"kept in .*\.out\.staging: the same command"):
            augment_kitti(
                kitti, "train", random_transform(), out, seed=5, progress=stop_after(3, exc)
            )
        assert len(records_in(out)) == 3
    seen = []
    summary = augment_kitti(
        kitti, "train", random_transform(), out, seed=5, progress=lambda d, t: seen.append(d)
    )
    resumed = 3 if isinstance(exc, KeyboardInterrupt) else 2
    assert summary["resumed"] == resumed and seen == list(range(resumed, 7))
    assert tree_bytes(out) == tree_bytes(reference)
    assert not staging_path(out).exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


class FailsAt(GlobalFlip):
    """GlobalFlip (the same config, so the same run) failing on one frame."""

    def __init__(self, frame_id: str) -> None:
        super().__init__(1.0)
        self.frame_id = frame_id

    def apply(self, frame, rng, stats):
        if frame.frame_id == self.frame_id:
            raise DataError(f"frame {self.frame_id}: broken")
        return super().apply(frame, rng, stats)

    def to_config(self):
        return {**super().to_config(), "type": "GlobalFlip"}


def test_a_failing_frame_keeps_the_frames_before_it(kitti, tmp_path):
    out = tmp_path / "out"
    with pytest.raises(DataError, match="000003"):
        augment_kitti(kitti, "train", FailsAt("000003"), out, seed=1)
    assert records_in(out) == [f"{i:08d}.json" for i in range(3)]
    staged = staging_path(out) / "output" / "training" / "velodyne"
    written = {p.name: p.stat().st_mtime_ns for p in staged.iterdir()}
    assert sorted(written) == ["000000.bin", "000001.bin", "000002.bin"]
    summary = augment_kitti(kitti, "train", GlobalFlip(1.0), out, seed=1)
    assert summary["resumed"] == 3
    for name, mtime in written.items():  # not written again
        assert (out / "training" / "velodyne" / name).stat().st_mtime_ns == mtime
    fresh = tmp_path / "fresh"
    augment_kitti(kitti, "train", GlobalFlip(1.0), fresh, seed=1)
    assert tree_bytes(out) == tree_bytes(fresh)


def test_a_killed_writers_temporaries_do_not_reach_the_output(kitti, reference, tmp_path):
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        augment_kitti(
            kitti,
            "train",
            random_transform(),
            out,
            seed=5,
            progress=stop_after(1, KeyboardInterrupt()),
        )
    velodyne = staging_path(out) / "output" / "training" / "velodyne"
    (velodyne / ".000004.bin.tmp-99999-0123abcd").write_bytes(b"half a frame")
    (velodyne / "000001.bin").write_bytes(b"a frame whose record was never written")
    augment_kitti(kitti, "train", random_transform(), out, seed=5)
    assert tree_bytes(out) == tree_bytes(reference)


def test_another_runs_staging_is_refused_or_discarded(kitti, tmp_path):
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        augment_kitti(
            kitti,
            "train",
            random_transform(),
            out,
            seed=5,
            progress=stop_after(1, KeyboardInterrupt()),
        )
    for change in ({"seed": 6}, {"frames": 4}, {"fov_only": False}):
        with pytest.raises(OutputError, match=f"unfinished run .*{next(iter(change))}"):
            augment_kitti(kitti, "train", random_transform(), out, **{"seed": 5, **change})
    with pytest.raises(OutputError, match="transform"):
        augment_kitti(kitti, "train", GlobalFlip(), out, seed=5)
    assert records_in(out) == ["00000000.json"]
    summary = augment_kitti(kitti, "train", random_transform(), out, seed=6, overwrite=True)
    assert summary["resumed"] == 0
    fresh = tmp_path / "fresh"
    augment_kitti(kitti, "train", random_transform(), fresh, seed=6)
    assert tree_bytes(out) == tree_bytes(fresh)


def test_a_staging_directory_drcpo_did_not_write_is_never_touched(kitti, tmp_path):
    out = tmp_path / "out"
    foreign = staging_path(out)
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    for overwrite in (False, True):
        with pytest.raises(OutputError, match="not drcpo's"):
            augment_kitti(kitti, "train", random_transform(), out, overwrite=overwrite)
    assert [p.name for p in foreign.iterdir()] == ["notes.txt"]
    assert not out.exists()


def test_an_existing_output_is_refused_before_any_staging(kitti, reference):
    with pytest.raises(OutputError, match="exists"):
        augment_kitti(kitti, "train", random_transform(), reference, seed=5)
    assert not staging_path(reference).exists()


def test_overwrite_replaces_the_output_resumably(kitti, reference, tmp_path):
    out = tmp_path / "out"
    augment_kitti(kitti, "train", GlobalFlip(1.0), out, seed=5)
    with pytest.raises(KeyboardInterrupt):
        augment_kitti(
            kitti,
            "train",
            random_transform(),
            out,
            seed=5,
            overwrite=True,
            progress=stop_after(3, KeyboardInterrupt()),
        )
    assert (out / "augment.json").is_file()  # the old output stays until the new one is done
    summary = augment_kitti(kitti, "train", random_transform(), out, seed=5, overwrite=True)
    assert summary["resumed"] == 3
    assert tree_bytes(out) == tree_bytes(reference)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


# Reliability: a resumed run equals a clean run or is refused ----------------------------------
def _stopped(kitti, out, k: int = 3):
    with pytest.raises(RuntimeError):
        augment_kitti(
            kitti, "train", random_transform(), out, seed=5,
            progress=stop_after(k, RuntimeError("power cut")),
        )  # fmt: skip
    return staging_path(out)


@pytest.mark.parametrize("damage", ["bin deleted", "label deleted", "label truncated", "record"])
def test_a_finished_frame_whose_files_are_damaged_is_done_again(kitti, reference, tmp_path, damage):
    out = tmp_path / "out"
    staging = _stopped(kitti, out)
    training = staging / "output" / "training"
    if damage == "bin deleted":
        (training / "velodyne" / "000001.bin").unlink()
    elif damage == "label deleted":
        (training / "label_2" / "000001.txt").unlink()
    elif damage == "label truncated":
        path = training / "label_2" / "000001.txt"
        path.write_bytes(path.read_bytes()[:5])
    else:
        (staging / "frames" / "00000001.json").write_text("{not json")
    summary = augment_kitti(kitti, "train", random_transform(), out, seed=5)
    assert summary["resumed"] == 2  # frames 0 and 2; frame 1 done again
    assert tree_bytes(out) == tree_bytes(reference)


def test_a_source_frame_edited_before_the_resume_is_done_again(kitti, tmp_path):
    import shutil

    source = tmp_path / "kitti"
    shutil.copytree(kitti, source)
    out = tmp_path / "out"
    _stopped(source, out)
    label = source / "training" / "label_2" / "000001.txt"
    label.write_text(label.read_text().replace("Car", "Van", 1))
    summary = augment_kitti(source, "train", random_transform(), out, seed=5)
    assert summary["resumed"] == 2
    fresh = tmp_path / "fresh"
    augment_kitti(source, "train", random_transform(), fresh, seed=5)
    assert tree_bytes(out) == tree_bytes(fresh)  # the edit is in, as a clean run has it


def test_a_symbolic_link_inside_the_staging_directory_is_refused(kitti, tmp_path):
    out = tmp_path / "out"
    staging = _stopped(kitti, out)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "000004.bin").write_bytes(b"mine")
    velodyne = staging / "output" / "training" / "velodyne"
    for path in velodyne.iterdir():
        path.rename(foreign / path.name)
    velodyne.rmdir()
    velodyne.symlink_to(foreign, target_is_directory=True)
    with pytest.raises(OutputError, match="velodyne is a symbolic link inside drcpo's staging"):
        augment_kitti(kitti, "train", random_transform(), out, seed=5)
    with pytest.raises(OutputError, match="is a symbolic link"):  # --overwrite resumes too
        augment_kitti(kitti, "train", random_transform(), out, seed=5, overwrite=True)
    assert (foreign / "000004.bin").read_bytes() == b"mine" and not out.exists()
    assert len(list(foreign.iterdir())) == 4
    velodyne.unlink()  # the user removes the link: the frames it held are done again
    summary = augment_kitti(kitti, "train", random_transform(), out, seed=5)
    assert summary["resumed"] == 0 and (foreign / "000004.bin").read_bytes() == b"mine"


def test_a_resume_with_another_candidate_index_is_refused(tmp_path):
    """The staging record names the index's checksum: after `drcpo index --overwrite` between
    a crash and the resume, frames of the old index are not mixed with the new one's."""
    from export_support import drcpo_world

    root, db, _ = drcpo_world(tmp_path)
    from drcpo.index import IndexConfig, load_index
    from drcpo.index_build import build_index
    from drcpo.pipeline import build_pipeline

    out = tmp_path / "out"
    pipeline = build_pipeline("default", db, load_index(db))
    with pytest.raises(RuntimeError):
        augment_kitti(root, "train", pipeline, out, progress=stop_after(1, RuntimeError("cut")))
    build_index(db, IndexConfig(k=3)).save(db.path, overwrite=True)
    pipeline = build_pipeline("default", db, load_index(db))
    with pytest.raises(OutputError, match="differing in: index"):
        augment_kitti(root, "train", pipeline, out)
