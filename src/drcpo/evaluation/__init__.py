"""Detection evaluation: KITTI's 2D, bird's-eye-view and 3D AP (:mod:`.kitti`).

``evaluate_kitti_split(root, split, predictions)`` reads a KITTI split's labels and a directory
of result files and evaluates them; :func:`evaluate_kitti` works on objects already read.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

from drcpo.datasets.kitti import read_split, split_directory
from drcpo.evaluation.files import KittiObjects, read_frames, read_kitti_objects
from drcpo.evaluation.kitti import (
    DEFAULT_CLASSES,
    DIFFICULTIES,
    LOOSE_OVERLAPS,
    METRICS,
    STRICT_OVERLAPS,
    KittiEvaluation,
    evaluate_kitti,
)


def evaluate_kitti_split(
    root: str | os.PathLike,
    split: str,
    predictions: str | os.PathLike,
    classes: Sequence[str] = DEFAULT_CLASSES,
    overlaps: str | Mapping[str, Sequence[float]] = "strict",
    missing_as_empty: bool = False,
) -> KittiEvaluation:
    """Evaluate ``predictions/<id>.txt`` against ``root``'s labels of ``ImageSets/<split>.txt``.

    Raises :class:`~drcpo.errors.DataError` naming the file (and line) for a missing split,
    label or result file (see :func:`~drcpo.evaluation.files.read_frames` for
    ``missing_as_empty``) or a malformed line.
    """
    frame_ids = read_split(root, split)
    labels = split_directory(root, split) / "label_2"
    ground_truth = read_frames(labels, frame_ids)
    detections = read_frames(
        predictions, frame_ids, results=True, missing_as_empty=missing_as_empty
    )
    return evaluate_kitti(ground_truth, detections, classes, overlaps)


__all__ = [
    "DEFAULT_CLASSES",
    "DIFFICULTIES",
    "LOOSE_OVERLAPS",
    "METRICS",
    "STRICT_OVERLAPS",
    "KittiEvaluation",
    "KittiObjects",
    "evaluate_kitti",
    "evaluate_kitti_split",
    "read_frames",
    "read_kitti_objects",
]
