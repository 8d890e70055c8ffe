"""KITTI AP of any multiset of the evaluated frames, for bootstrap intervals over frames.

KITTI's matching is per frame and its thresholds come from the pooled true-positive scores, so
AP over frames drawn with replacement needs only each frame's part, found once:

* the scores of its true positives at no score threshold (which set the recall thresholds), and
  how many of its objects count;
* its true and false positives at each of its own detection scores taken as the threshold (a
  frame's counts only change there), kept as increments in descending score.

:meth:`FrameTables.ap_r40` then scores frame weights (how often each frame was drawn) in a few
sorted sums, where :func:`~drcpo.evaluation.evaluate_kitti` on the repeated frames would redo
every overlap and matching; both give the same AP (``tests/test_evaluation.py`` checks it).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from drcpo.errors import DataError
from drcpo.evaluation.files import KittiObjects
from drcpo.evaluation.kitti import (
    DEFAULT_CLASSES,
    DIFFICULTIES,
    METRICS,
    SAMPLE_POINTS,
    _average,
    _box_overlaps,
    _Candidates,
    _counts_at,
    _Detections,
    _dont_care_coverage,
    _frame_pairs,
    _ignore_flags,
    _matched_scores,
    _Objects,
    _overlap_table,
    _recall_thresholds,
    _running_max,
    _Stack,
)
from drcpo.evaluation.overlaps import image_iou

__all__ = ["FrameTables", "frame_tables"]


@dataclass(frozen=True)
class _ClassTable:
    """One metric and class: true-positive scores with their frames, counted objects per frame,
    and per-frame count increments (descending score within the table)."""

    tp_score: np.ndarray
    tp_frame: np.ndarray
    valid: np.ndarray
    step_score: np.ndarray
    step_frame: np.ndarray
    step_tp: np.ndarray
    step_fp: np.ndarray

    def ap_r40(self, weights: np.ndarray) -> float:
        scores = np.repeat(self.tp_score, weights[self.tp_frame])
        valid = int(weights @ self.valid)
        if not len(scores):
            return 0.0
        thresholds = _recall_thresholds(np.sort(scores)[::-1], valid)
        w = weights[self.step_frame]
        tp, fp = np.cumsum(w * self.step_tp), np.cumsum(w * self.step_fp)
        # entries with score >= threshold: step_score is descending
        upto = np.searchsorted(-self.step_score, -thresholds, side="right")
        tp = np.where(upto > 0, tp[np.maximum(upto - 1, 0)], 0.0)
        fp = np.where(upto > 0, fp[np.maximum(upto - 1, 0)], 0.0)
        precision = np.zeros(SAMPLE_POINTS)
        found = tp + fp
        np.divide(tp, found, out=precision[: len(tp)], where=found > 0)
        return _average(_running_max(precision))[1]


@dataclass(frozen=True)
class FrameTables:
    """Per-frame parts of a KITTI evaluation at one difficulty (see the module docstring).

    Attributes:
        classes: evaluated class names.
        frames: number of frames.
        tables: ``{(metric, class): table}`` for each of :data:`~drcpo.evaluation.METRICS`.
    """

    classes: tuple[str, ...]
    frames: int
    tables: Mapping[tuple[str, str], _ClassTable]

    def ap_r40(self, metric: str, name: str, weights: np.ndarray | None = None) -> float:
        """AP_R40 (percent) of one metric and class over the frames drawn ``weights[f]`` times
        each (``int (frames,)``; ``None``: every frame once)."""
        if weights is None:
            weights = np.ones(self.frames, dtype=np.int64)
        weights = np.asarray(weights, dtype=np.int64)
        if weights.shape != (self.frames,) or (weights < 0).any():
            raise DataError(f"weights must be {self.frames} counts >= 0, got shape {weights.shape}")
        return self.tables[(metric, name)].ap_r40(weights)


def frame_tables(
    ground_truth: Sequence[KittiObjects],
    detections: Sequence[KittiObjects],
    classes: Sequence[str] = DEFAULT_CLASSES,
    overlaps: str | Mapping[str, Sequence[float]] = "strict",
    difficulty: str = "moderate",
) -> FrameTables:
    """The per-frame parts of :func:`~drcpo.evaluation.evaluate_kitti` at one difficulty
    (same arguments and errors)."""
    if len(ground_truth) != len(detections):
        raise DataError(
            f"{len(ground_truth)} frames of ground truth but {len(detections)} of detections"
        )
    if difficulty not in DIFFICULTIES:
        raise DataError(f"difficulty must be one of {DIFFICULTIES}, got {difficulty!r}")
    level = DIFFICULTIES.index(difficulty)
    table = _overlap_table(classes, overlaps)
    frames = len(ground_truth)
    gt = _Stack.of(ground_truth, "objects")
    dc = _Stack.of(ground_truth, "dontcare")
    dt = _Stack.of(detections, "objects")
    gi, di = _frame_pairs(gt.frame, dt.frame, frames)
    pair_overlaps = (
        image_iou(dt.bbox[di], gt.bbox[gi]),
        *_box_overlaps(gt.boxes, dt.boxes, gi, di),
    )
    excused_by = _dont_care_coverage(dc, dt, frames)
    gt_bounds = np.searchsorted(gt.frame, np.arange(frames + 1))
    dt_bounds = np.searchsorted(dt.frame, np.arange(frames + 1))
    tables = {}
    for m, overlap in enumerate(pair_overlaps):
        for name, thresholds in table.items():
            excused = excused_by > thresholds[0] if m == 0 else np.zeros(len(dt.score), bool)
            gt_ignored, dt_ignored = _ignore_flags(gt, dt, name.lower(), level)
            keep = (
                (overlap > 0)
                & (gt_ignored[gi] >= 0)
                & (dt_ignored[di] >= 0)
                & (overlap > thresholds[m])
            )
            pairs = (gi[keep], di[keep], overlap[keep])
            tables[(METRICS[m], name)] = _class_table(
                gt, dt, pairs, gt_ignored, dt_ignored, excused, gt_bounds, dt_bounds
            )
    return FrameTables(classes=tuple(table), frames=frames, tables=tables)


def _class_table(gt, dt, pairs, gt_ignored, dt_ignored, excused, gt_bounds, dt_bounds):
    gi, di, overlap = pairs
    start = np.concatenate([[0], np.cumsum(np.bincount(gi, minlength=len(gt_ignored)))])
    tp_score, tp_frame, steps = [], [], []
    valid = np.zeros(len(gt_bounds) - 1, dtype=np.int64)
    for f in range(len(gt_bounds) - 1):
        g0, g1 = gt_bounds[f], gt_bounds[f + 1]
        d0, d1 = dt_bounds[f], dt_bounds[f + 1]
        counted = dt_ignored[d0:d1] >= 0
        if g0 == g1 and not counted.any():
            continue
        local_start = start[g0 : g1 + 1] - start[g0]
        candidates = di[start[g0] : start[g1]] - d0
        scores = dt.score[d0:d1]
        matched = _matched_scores(
            gt_ignored[g0:g1], local_start, candidates, dt_ignored[d0:d1], scores
        )
        tp_score.append(matched)
        tp_frame.append(np.full(len(matched), f))
        valid[f] = int((gt_ignored[g0:g1] == 0).sum())
        levels = np.unique(scores)[::-1]
        if not len(levels):
            continue
        counts = _counts_at(
            levels,
            _Objects(gt_ignored[g0:g1], gt.alpha[g0:g1]),
            _Candidates(local_start, candidates, overlap[start[g0] : start[g1]]),
            _Detections(dt_ignored[d0:d1], scores, dt.alpha[d0:d1], excused[d0:d1]),
        )
        rise = np.diff(counts[:, :2], axis=0, prepend=np.zeros((1, 2)))
        steps.append(np.column_stack([levels, np.full(len(levels), f), rise]))
    stacked = np.concatenate(steps) if steps else np.zeros((0, 4))
    order = np.argsort(-stacked[:, 0], kind="stable")
    stacked = stacked[order]
    return _ClassTable(
        tp_score=np.concatenate(tp_score) if tp_score else np.zeros(0),
        tp_frame=np.concatenate(tp_frame).astype(np.int64) if tp_frame else np.zeros(0, np.int64),
        valid=valid,
        step_score=stacked[:, 0],
        step_frame=stacked[:, 1].astype(np.int64),
        step_tp=stacked[:, 2],
        step_fp=stacked[:, 3],
    )
