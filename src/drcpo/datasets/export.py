"""Offline generation: a KITTI split augmented by a transform, written in KITTI layout.

Resumable: every frame's files are written atomically into a staging directory beside the output
(:func:`drcpo.staging.write_staged`), so a run that fails or is killed keeps the frames it
finished and the same command run again augments only the others. The output is the same bytes
however often a run was interrupted and whichever processes augmented which frames (each frame
uses its own generator, :func:`frame_seed`): only ``timings.jsonl`` (how long each frame took)
differs between runs.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import stat
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from drcpo.datasets import kitti_writer
from drcpo.datasets.kitti import KittiDataset
from drcpo.datasets.kitti_coordinates import fov_mask
from drcpo.errors import OutputError
from drcpo.frame import Frame
from drcpo.outputs import OutputKind, atomic_write_bytes
from drcpo.staging import write_staged
from drcpo.transforms.base import STATS_KEY, Transform, without_timings

__all__ = [
    "AUGMENT_OUTPUT",
    "TIMINGS_FILE",
    "MapFrames",
    "augment_frame",
    "augment_kitti",
    "frame_seed",
    "run_parameters",
]

#: What :func:`augment_kitti` writes; ``augment.json`` (written last) marks it as drcpo's.
AUGMENT_OUTPUT = OutputKind(
    "drcpo augment output",
    "augment.json",
    "drcpo-augmented-kitti",
    ("training", "ImageSets", "stats.jsonl", "timings.jsonl"),
)
#: The output's one file that differs between runs: per frame, the milliseconds it took.
TIMINGS_FILE = "timings.jsonl"
_FRAMES = "frames"  # staging subdirectory: one record per finished frame, written last
_OUTPUT = "output"  # staging subdirectory that becomes the output

#: ``map_frames(staging, numbers)``: augment frames ``numbers`` (positions in the run's frame
#: list) with :func:`augment_frame` into ``staging``, yielding each number once it is written.
MapFrames = Callable[[Path, list[int]], Iterable[int]]


def _known_occlusion(frame: Frame) -> np.ndarray:
    """KITTI occlusion levels of the frame's boxes: known levels kept, unknown ones 3."""
    levels = np.asarray(frame.metadata.get("occlusion", ()), dtype=np.int64)
    if levels.shape != (len(frame.boxes),):
        levels = np.full(len(frame.boxes), 3)
    return np.where((levels >= 0) & (levels <= 3), levels, 3)


def frame_seed(seed: int, index: int) -> np.random.Generator:
    """The generator of frame ``index`` of a run seeded with ``seed``: independent per frame and
    independent of the order or the process frames are augmented in."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))


def augment_frame(
    dataset: KittiDataset,
    transform: Transform,
    staging: str | os.PathLike,
    number: int,
    seed: int,
    fov_only: bool,
) -> None:
    """Augment frame ``number`` of ``dataset``'s split with :func:`frame_seed` ``(seed, number)``
    and write its files into staging directory ``staging`` (of :func:`augment_kitti`), each
    atomically: ``output/training/{velodyne,label_2,calib}/<id>`` and, last, its record
    ``frames/<number>.json`` (its statistics and timings), which marks the frame done. Any
    process may call it; the bytes written depend only on the arguments."""
    staging = Path(staging)
    frame_id = dataset.frame_ids[number]
    source = source_fingerprint(dataset, frame_id)  # before reading: an edit meanwhile shows
    frame = dataset.frame(frame_id)
    if fov_only:
        keep = fov_mask(frame.points, frame.metadata["calib"], dataset.image_shape(frame_id))
        frame = frame.replace(
            points=frame.points[keep], metadata={**frame.metadata, "fov_only": True}
        )
    start = time.perf_counter()
    result = transform(frame, frame_seed(seed, number))
    elapsed = (time.perf_counter() - start) * 1000.0
    base = staging / _OUTPUT / "training"
    kitti_writer.write_points(base / "velodyne" / f"{frame_id}.bin", result.points)
    lines = kitti_writer.label_lines(
        result.boxes,
        result.names,
        result.metadata["calib"],
        occlusion=_known_occlusion(result),
        image_shape=dataset.image_shape(frame_id),
    )
    kitti_writer.write_labels(base / "label_2" / f"{frame_id}.txt", lines)
    calib = Path(dataset.path("calib", frame_id)).read_bytes()
    atomic_write_bytes(base / "calib" / f"{frame_id}.txt", calib)
    names, counts = np.unique(result.names, return_counts=True)
    stats = result.metadata.get(STATS_KEY, {})
    record = {
        "frame_id": frame_id,
        "seed": [int(seed), int(number)],
        "points_in": len(frame),
        "points": len(result),
        "boxes": {str(n): int(c) for n, c in zip(names, counts, strict=True)},
        **without_timings(stats),
    }
    timing = {"frame_id": frame_id, "ms": elapsed, "stages": _stage_ms(stats)}
    files = {name: (base / name).stat().st_size for name in _frame_files(frame_id)}
    payload = json.dumps({"stats": record, "timing": timing, "source": source, "files": files})
    atomic_write_bytes(_record_path(staging, number), payload.encode())


SOURCE_KINDS = ("velodyne", "label_2", "calib", "planes", "image_2")


def source_fingerprint(dataset: KittiDataset, frame_id: str) -> dict[str, list[int] | None]:
    """Size and modification time (ns) of each source file a frame is read from (``None``: no
    such file): a resumed run redoes a frame whose source changed since it was written."""
    out: dict[str, list[int] | None] = {}
    for kind in SOURCE_KINDS:
        try:
            info = os.stat(dataset.path(kind, frame_id))
        except FileNotFoundError:
            out[kind] = None
        else:
            out[kind] = [info.st_size, info.st_mtime_ns]
    return out


def _frame_files(frame_id: str) -> tuple[str, ...]:
    return (f"velodyne/{frame_id}.bin", f"label_2/{frame_id}.txt", f"calib/{frame_id}.txt")


def _finished(staging: Path, number: int, dataset: KittiDataset) -> dict[str, Any] | None:
    """Frame ``number``'s record when the frame is finished as a clean run would leave it: its
    record readable, each of its files a regular file of the size recorded, its source files
    unchanged since; else ``None`` (the frame is done again)."""
    try:
        record = json.loads(_record_path(staging, number).read_bytes())
    except FileNotFoundError:
        return None
    except (OSError, ValueError, RecursionError):
        return None  # a torn or foreign record: the frame is redone, the record replaced
    frame_id = dataset.frame_ids[number]
    if not isinstance(record, dict) or not isinstance(record.get("files"), dict):
        return None
    if record.get("stats", {}).get("frame_id") != frame_id:
        return None
    base = staging / _OUTPUT / "training"
    for name in _frame_files(frame_id):
        try:
            info = os.lstat(base / name)
        except OSError:
            return None
        if not stat.S_ISREG(info.st_mode) or info.st_size != record["files"].get(name):
            return None
    if record.get("source") != source_fingerprint(dataset, frame_id):
        return None
    return record


def _record_path(staging: Path, number: int) -> Path:
    return staging / _FRAMES / f"{number:08d}.json"


def _stage_ms(stats: dict[str, Any]) -> dict[str, float]:
    stages = stats.get("stages", {})
    return {name: r["ms"] for name, r in stages.items() if isinstance(r, dict) and "ms" in r}


def run_parameters(
    root: str | os.PathLike,
    split: str,
    ids: Sequence[str],
    transform: Transform,
    seed: int,
    fov_only: bool,
) -> dict[str, Any]:
    """What decides a run's output bytes, recorded in its staging directory: a rerun resumes
    only a staging directory of equal parameters. The transform counts by a hash of its config
    and the checksums of the database and of the candidate index it draws from."""
    config = json.dumps(transform.to_config(), sort_keys=True, default=str)
    database = _database_of(transform)
    return {
        "source": str(Path(root).resolve()),
        "split": split,
        "frames": len(ids),
        "frame_ids": hashlib.sha256("\n".join(ids).encode()).hexdigest()[:16],
        "seed": int(seed),
        "fov_only": bool(fov_only),
        "transform": hashlib.sha256(config.encode()).hexdigest()[:16],
        "database": None if database is None else database.checksum,
        "index": _index_checksum(transform),
    }


def _index_checksum(transform: Transform) -> str | None:
    """The checksum of the candidate index the transform draws from (DR.CPO's), if any."""
    for t in getattr(transform, "transforms", (transform,)):
        index = getattr(t, "index", None)
        if index is not None and hasattr(index, "checksum"):
            return index.checksum()
    return None


def _database_of(transform: Transform) -> Any:
    for t in getattr(transform, "transforms", (transform,)):
        if getattr(t, "database", None) is not None:
            return t.database
    return None


def augment_kitti(
    root: str | os.PathLike,
    split: str,
    transform: Transform,
    out: str | os.PathLike,
    frames: int | None = None,
    seed: int = 0,
    fov_only: bool = True,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    inputs: Sequence[str | os.PathLike] = (),
    map_frames: MapFrames | None = None,
) -> dict[str, Any]:
    """Augment frames of a KITTI split and write them in KITTI layout under ``out``, resumably.

    Writes ``training/velodyne/*.bin`` (float32, the frame's point columns),
    ``training/label_2/*.txt`` (:func:`drcpo.datasets.kitti_writer.label_lines` through the
    frame's calibration; truncation and 2D boxes from the projection of the augmented boxes,
    occlusion levels of original boxes kept, 3 "unknown" for inserted ones),
    ``training/calib/*.txt`` (copied), ``ImageSets/<split>.txt``, ``stats.jsonl`` (one JSON
    object per frame, in frame order: ``frame_id``, ``seed``, ``points_in``, ``points``,
    ``boxes`` per class and the transform's statistics, timings left out), ``timings.jsonl``
    (per frame: ``frame_id``, ``ms`` and each stage's ``stages`` ms; the one file that differs
    between runs) and last ``augment.json`` (:data:`AUGMENT_OUTPUT`'s marker: the source,
    split, frames, seed).

    Frames are written one by one, atomically, into the staging directory
    ``.<out name>.staging`` beside ``out`` (:func:`drcpo.staging.write_staged`), which becomes
    ``out`` once complete: ``out`` never holds a half-written output. A run that fails or is
    killed leaves the staging directory; the same call again skips the frames it holds (same
    source, split, frames, seed, ``fov_only``, transform config and database, else it is refused;
    ``overwrite`` discards it) and gives the same bytes as an uninterrupted run.
    ``overwrite`` replaces only an earlier augment output.

    Args:
        root: KITTI root; split: split name; transform: the augmentation.
        frames: augment the first ``frames`` frames of the split (``None``: all).
        seed: frame i uses :func:`frame_seed` ``(seed, i)``.
        fov_only: cut frames to the camera's field of view first (as OpenPCDet trains KITTI);
            frames then carry ``metadata["fov_only"] = True``.
        progress: ``progress(done, total)`` after each frame (frames found done count).
        inputs: other paths the transform reads (the database): ``out`` may not be or contain
            them, nor ``root``.
        map_frames: who augments the frames (:data:`MapFrames`; e.g. workers of a cluster,
            :mod:`drcpo.distributed`); default: this process, in order.

    Returns a summary: frames written, ``resumed`` (frames an earlier run had written), points
    and boxes per class over all frames, mean and median ms.
    """
    dataset = KittiDataset(root, split)
    ids = dataset.frame_ids if frames is None else dataset.frame_ids[: max(0, int(frames))]
    run = run_parameters(root, split, ids, transform, seed, fov_only)
    summary: dict[str, Any] = {"frames": len(ids)}

    def local(staging: Path, numbers: list[int]) -> Iterator[int]:
        for number in numbers:
            augment_frame(dataset, transform, staging, number, seed, fov_only)
            yield number

    def write(staging: Path) -> None:
        todo = _prepare_staging(staging, dataset, len(ids))
        summary["resumed"] = done = len(ids) - len(todo)
        if progress is not None and done:
            progress(done, len(ids))
        for _ in (map_frames or local)(staging, todo):
            done += 1
            if progress is not None:
                progress(done, len(ids))
        records = [_finished(staging, n, dataset) for n in range(len(ids))]
        missing = [n for n, record in enumerate(records) if record is None]
        if missing:
            raise RuntimeError(f"drcpo bug: frames {missing[:5]} were not written")
        summary.update(_assemble(staging, split, ids, seed, fov_only, run["source"], records))

    write_staged(out, write, AUGMENT_OUTPUT, run, overwrite, [root, *inputs])
    return summary


def _prepare_staging(staging: Path, dataset: KittiDataset, total: int) -> list[int]:
    """Make the staging layout; the numbers of the frames still to do, in order (those not
    :func:`_finished`). A symbolic link anywhere in the staging directory is refused: drcpo
    made every entry there, and never writes through a link."""
    for directory, subdirectories, files in os.walk(staging):
        for name in [*subdirectories, *files]:
            if os.path.islink(os.path.join(directory, name)):
                raise OutputError(
                    f"{os.path.join(directory, name)} is a symbolic link inside drcpo's staging "
                    f"directory; drcpo never writes through one (remove it, or remove {staging} "
                    "to start the run over)"
                )
    output = staging / _OUTPUT
    if not output.is_dir():  # new, or an earlier run moved it into place: nothing is done
        shutil.rmtree(staging / _FRAMES, ignore_errors=True)
    for sub in ("velodyne", "label_2", "calib"):
        (output / "training" / sub).mkdir(parents=True, exist_ok=True)
    (staging / _FRAMES).mkdir(exist_ok=True)
    return [n for n in range(total) if _finished(staging, n, dataset) is None]


def _assemble(
    staging: Path,
    split: str,
    ids: Sequence[str],
    seed: int,
    fov_only: bool,
    source: str,
    records: Sequence[dict[str, Any]],
) -> dict[str, Any]:
    """Write the run-wide files from the frames' records, in frame order, the marker last;
    returns the summary's totals."""
    output = staging / _OUTPUT
    lines = "".join(f"{i}\n" for i in ids)
    atomic_write_bytes(output / "ImageSets" / f"{split}.txt", lines.encode())
    stats = "".join(json.dumps(r["stats"]) + "\n" for r in records)
    atomic_write_bytes(output / "stats.jsonl", stats.encode())
    timings = "".join(json.dumps(r["timing"]) + "\n" for r in records)
    atomic_write_bytes(output / TIMINGS_FILE, timings.encode())
    marker = {
        "format": AUGMENT_OUTPUT.format,
        "format_version": 1,
        "source": source,
        "split": split,
        "frames": len(ids),
        "seed": int(seed),
        "fov_only": bool(fov_only),
    }
    atomic_write_bytes(
        output / AUGMENT_OUTPUT.marker, (json.dumps(marker, indent=2) + "\n").encode()
    )
    boxes: dict[str, int] = {}
    for record in records:
        for name, count in record["stats"]["boxes"].items():
            boxes[name] = boxes.get(name, 0) + count
    ms = [r["timing"]["ms"] for r in records]
    return {
        "points": sum(r["stats"]["points"] for r in records),
        "boxes": boxes,
        "mean_ms": float(np.mean(ms)) if ms else 0.0,
        "median_ms": float(np.median(ms)) if ms else 0.0,
    }
