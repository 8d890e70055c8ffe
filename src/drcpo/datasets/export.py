"""Offline generation: a KITTI split augmented by a transform, written in KITTI layout."""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from drcpo.datasets import kitti_writer
from drcpo.datasets.kitti import KittiDataset, fov_mask
from drcpo.frame import Frame
from drcpo.outputs import OutputKind, write_directory
from drcpo.transforms.base import STATS_KEY, Transform

__all__ = ["AUGMENT_OUTPUT", "augment_kitti", "frame_seed"]

#: What :func:`augment_kitti` writes; ``augment.json`` (written last) marks it as drcpo's.
AUGMENT_OUTPUT = OutputKind("drcpo augment output", "augment.json", "drcpo-augmented-kitti")


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
) -> dict[str, Any]:
    """Augment frames of a KITTI split and write them in KITTI layout under ``out``.

    Writes ``training/velodyne/*.bin`` (float32, the frame's point columns),
    ``training/label_2/*.txt`` (:func:`drcpo.datasets.kitti_writer.label_lines` through the
    frame's calibration; truncation and 2D boxes from the projection of the augmented boxes,
    occlusion levels of original boxes kept, 3 "unknown" for inserted ones),
    ``training/calib/*.txt`` (copied),
    ``ImageSets/<split>.txt`` and ``stats.jsonl`` (one JSON object per frame: ``frame_id``,
    ``points``, ``boxes`` per class and the transform's statistics), and last ``augment.json``
    (:data:`AUGMENT_OUTPUT`'s marker: the source, split, frames, seed). Everything is written to
    a temporary directory renamed to ``out`` at the end (:func:`drcpo.outputs.write_directory`),
    so an interrupted run leaves nothing; ``overwrite`` replaces only an earlier augment output.

    Args:
        root: KITTI root; split: split name; transform: the augmentation.
        frames: augment the first ``frames`` frames of the split (``None``: all).
        seed: frame i uses :func:`frame_seed` ``(seed, i)``.
        fov_only: cut frames to the camera's field of view first (as OpenPCDet trains KITTI);
            frames then carry ``metadata["fov_only"] = True``.
        progress: ``progress(done, total)`` after each frame.
        inputs: other paths the transform reads (the database): ``out`` may not be or contain
            them, nor ``root``.

    Returns a summary: frames written, points and boxes per class over all frames, mean ms.
    """
    dataset = KittiDataset(root, split)
    ids = dataset.frame_ids if frames is None else dataset.frame_ids[: max(0, int(frames))]
    summary: dict[str, Any] = {"frames": len(ids), "points": 0, "boxes": {}, "ms": []}

    def write(tmp: Path) -> None:
        base = tmp / "training"
        for sub in ("velodyne", "label_2", "calib"):
            (base / sub).mkdir(parents=True)
        (tmp / "ImageSets").mkdir()
        (tmp / "ImageSets" / f"{split}.txt").write_text("".join(f"{i}\n" for i in ids))
        with (tmp / "stats.jsonl").open("w") as stats_file:
            for number, frame_id in enumerate(ids):
                frame = dataset.frame(frame_id)
                if fov_only:
                    keep = fov_mask(
                        frame.points, frame.metadata["calib"], dataset.image_shape(frame_id)
                    )
                    frame = frame.replace(
                        points=frame.points[keep], metadata={**frame.metadata, "fov_only": True}
                    )
                start = time.perf_counter()
                result = transform(frame, frame_seed(seed, number))
                elapsed = (time.perf_counter() - start) * 1000.0
                kitti_writer.write_points(base / "velodyne" / f"{frame_id}.bin", result.points)
                lines = kitti_writer.label_lines(
                    result.boxes,
                    result.names,
                    result.metadata["calib"],
                    occlusion=_known_occlusion(result),
                    image_shape=dataset.image_shape(frame_id),
                )
                kitti_writer.write_labels(base / "label_2" / f"{frame_id}.txt", lines)
                shutil.copyfile(dataset.path("calib", frame_id), base / "calib" / f"{frame_id}.txt")
                names, counts = np.unique(result.names, return_counts=True)
                per_class = {str(n): int(c) for n, c in zip(names, counts, strict=True)}
                record = {
                    "frame_id": frame_id,
                    "seed": [int(seed), number],
                    "points_in": len(frame),
                    "points": len(result),
                    "boxes": per_class,
                    "ms": elapsed,
                    **result.metadata.get(STATS_KEY, {}),
                }
                stats_file.write(json.dumps(record) + "\n")
                summary["points"] += len(result)
                for name, count in per_class.items():
                    summary["boxes"][name] = summary["boxes"].get(name, 0) + count
                summary["ms"].append(elapsed)
                if progress is not None:
                    progress(number + 1, len(ids))
        marker = {
            "format": AUGMENT_OUTPUT.format,
            "format_version": 1,
            "source": str(Path(root).resolve()),
            "split": split,
            "frames": len(ids),
            "seed": int(seed),
            "fov_only": bool(fov_only),
        }
        (tmp / AUGMENT_OUTPUT.marker).write_text(json.dumps(marker, indent=2) + "\n")

    write_directory(out, write, AUGMENT_OUTPUT, overwrite, [root, *inputs])
    summary["mean_ms"] = float(np.mean(summary["ms"])) if summary["ms"] else 0.0
    summary["median_ms"] = float(np.median(summary["ms"])) if summary["ms"] else 0.0
    del summary["ms"]
    return summary
