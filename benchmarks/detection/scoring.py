"""Scoring detections: KITTI AP through :mod:`drcpo.evaluation`, and the heading error."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from drcpo.datasets.kitti_writer import write_labels
from drcpo.evaluation import DIFFICULTIES, METRICS, evaluate_kitti_split
from drcpo.frame import Frame
from drcpo.geometry import wrap_angle

from .heads import CLASSES, Detections

#: BEV centre distance (metres) within which a detection is matched to an object for the heading
#: error: about half the object's width.
MATCH_DISTANCE = {"Car": 1.0, "Pedestrian": 0.4, "Cyclist": 0.4}
MATCH_SCORE = 0.3  # detections below it are not matched for the heading error


def write_results(directory: str | Path, frame_ids: Sequence[str], lines: Sequence[list[str]]):
    """Write one KITTI result file per frame (``directory/<id>.txt``, empty when nothing)."""
    for frame_id, rows in zip(frame_ids, lines, strict=True):
        write_labels(Path(directory) / f"{frame_id}.txt", rows)


def kitti_ap(
    root: str | Path, split: str, results: str | Path, difficulty: str = "moderate"
) -> dict[str, dict[str, float]]:
    """AP_R40 at KITTI's strict overlaps of the result files in ``results`` against the split's
    labels, evaluated by :func:`drcpo.evaluation.evaluate_kitti_split`:
    ``{metric: {class: AP, ..., "mean": mean over classes}}`` for the BEV and 3D metrics."""
    evaluation = evaluate_kitti_split(root, split, results, classes=CLASSES, overlaps="strict")
    level = DIFFICULTIES.index(difficulty)
    out: dict[str, dict[str, float]] = {}
    for metric in ("bev", "3d"):
        table = evaluation.ap_r40[METRICS.index(metric)]
        per_class = {name: float(table[c, level]) for c, name in enumerate(evaluation.classes)}
        per_class["mean"] = float(np.mean(list(per_class.values())))
        out[metric] = per_class
    return out


def heading_errors(
    frames: Sequence[Frame], detections: Sequence[Detections]
) -> dict[str, dict[str, Any]]:
    """Per class, the heading error (degrees, modulo 180: a box's overlap does not see its
    direction) of the best-scoring detection of the class (score >= :data:`MATCH_SCORE`)
    within :data:`MATCH_DISTANCE` of each labelled object: mean, median and matched count."""
    errors: dict[str, list[np.ndarray]] = {name: [] for name in CLASSES}
    for frame, found in zip(frames, detections, strict=True):
        names = found.names()
        for name in CLASSES:
            truth = frame.boxes[frame.names == name]
            picked = np.array([n == name for n in names], dtype=bool) & (
                found.scores >= MATCH_SCORE
            )
            boxes = found.boxes[picked]  # by decreasing score
            if not len(truth) or not len(boxes):
                continue
            distance = np.linalg.norm(truth[:, None, :2] - boxes[None, :, :2], axis=2)
            near = distance < MATCH_DISTANCE[name]
            has = near.any(axis=1)
            best = np.argmax(near, axis=1)[has]  # the first (best-scoring) detection near
            delta = wrap_angle(2 * (boxes[best, 6] - truth[has, 6])) / 2
            errors[name].append(np.degrees(np.abs(delta)))
    summary: dict[str, dict[str, Any]] = {}
    for name, parts in errors.items():
        values = np.concatenate(parts) if parts else np.zeros(0)
        summary[name] = {
            "matched": len(values),
            "mean_deg": float(values.mean()) if len(values) else None,
            "median_deg": float(np.median(values)) if len(values) else None,
        }
    return summary


def mean_and_spread(values: Sequence[float]) -> Mapping[str, float]:
    """Mean and sample standard deviation (0 for one value) of per-seed results."""
    array = np.asarray(values, dtype=np.float64)
    spread = float(array.std(ddof=1)) if len(array) > 1 else 0.0
    return {"mean": round(float(array.mean()), 2), "sd": round(spread, 2)}
