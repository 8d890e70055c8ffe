"""KITTI object detection evaluation: 2D, bird's-eye-view and 3D AP (and AOS), R11 and R40.

The rules are the KITTI devkit's, in the form OpenPCDet's ``kitti_object_eval_python`` applies
them (our results match it within 0.01 AP; ``tests/test_evaluation.py`` checks this):

* **Difficulty** ``easy / moderate / hard``: an object counts when its 2D box is taller than
  40 / 25 / 25 pixels, its occlusion is at most 0 / 1 / 2 and its truncation at most
  0.15 / 0.3 / 0.5; other objects of the class are *ignored* (a detection matched to one is
  neither a true nor a false positive).
* **Neighbouring classes**: ``Van`` objects are ignored for ``Car``, ``Person_sitting`` for
  ``Pedestrian``; other classes do not take part.
* **Small detections**: a detection whose 2D box is lower than the difficulty's minimum height
  is ignored, whatever its class (it may absorb an object, never counts as a false positive).
* **DontCare**: in the 2D evaluation, a detection left unmatched that lies inside a
  ``DontCare`` region (share of its box covered above the class's overlap threshold) is not a
  false positive. (The devkit applies this to every metric; OpenPCDet to 2D only, as here.)
* **Matching**, per frame, objects in file order: first, at no score threshold, each object
  takes the highest-scoring free detection overlapping it above the class's threshold; the
  scores of the true positives give the score thresholds nearest the 41 recall points
  0, 1/40, ..., 1. Then, at each threshold, each object takes the free detection with the
  largest overlap (an ignored detection only if there is no other), and precision is counted.
* **AP**: precision made non-increasing in recall, averaged over recall points 0, 0.1, ..., 1
  (R11) or 1/40, 2/40, ..., 1 (R40), in percent.

Overlaps (:mod:`drcpo.evaluation.overlaps`) are computed only between objects and detections
of the same frame; the matching runs in compiled loops (numba), all frames per call.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numba as nb
import numpy as np

from drcpo.errors import ConfigError, DataError
from drcpo.evaluation.files import KittiObjects
from drcpo.evaluation.overlaps import bev_iou, image_coverage, image_iou, iou3d

__all__ = [
    "DEFAULT_CLASSES",
    "DIFFICULTIES",
    "LOOSE_OVERLAPS",
    "METRICS",
    "SAMPLE_POINTS",
    "STRICT_OVERLAPS",
    "KittiEvaluation",
    "evaluate_kitti",
]

METRICS = ("2d", "bev", "3d")
DIFFICULTIES = ("easy", "moderate", "hard")
DEFAULT_CLASSES = ("Car", "Pedestrian", "Cyclist")
SAMPLE_POINTS = 41  # recall points 0, 1/40, ..., 1; R11 uses every fourth

_MIN_HEIGHT = (40.0, 25.0, 25.0)  # pixels, per difficulty
_MAX_OCCLUSION = (0, 1, 2)
_MAX_TRUNCATION = (0.15, 0.3, 0.5)
_NEIGHBOUR = {"car": "van", "pedestrian": "person_sitting"}

#: Overlap thresholds (2D, BEV, 3D) per class: KITTI's official ones.
STRICT_OVERLAPS: dict[str, tuple[float, float, float]] = {
    "Car": (0.7, 0.7, 0.7),
    "Pedestrian": (0.5, 0.5, 0.5),
    "Cyclist": (0.5, 0.5, 0.5),
    "Van": (0.7, 0.7, 0.7),
    "Person_sitting": (0.5, 0.5, 0.5),
    "Truck": (0.7, 0.7, 0.7),
}
#: The looser thresholds the devkit also reports (BEV and 3D halved for Car, Pedestrian, ...).
LOOSE_OVERLAPS: dict[str, tuple[float, float, float]] = {
    "Car": (0.7, 0.5, 0.5),
    "Pedestrian": (0.5, 0.25, 0.25),
    "Cyclist": (0.5, 0.25, 0.25),
    "Van": (0.7, 0.5, 0.5),
    "Person_sitting": (0.5, 0.25, 0.25),
    "Truck": (0.5, 0.5, 0.5),
}


@dataclass(frozen=True)
class KittiEvaluation:
    """APs in percent.

    Attributes:
        classes: evaluated class names, ``C`` of them.
        min_overlaps: ``(C, 3)`` overlap thresholds per class for 2D, BEV, 3D.
        ap_r11, ap_r40: ``(3, C, 3)`` AP per metric (:data:`METRICS`), class and difficulty.
        aos_r11, aos_r40: ``(C, 3)`` average orientation similarity (2D), or ``None`` when a
            detection carries no observation angle (alpha -10, KITTI's "unknown").
        frames: number of frames evaluated.
    """

    classes: tuple[str, ...]
    min_overlaps: np.ndarray
    ap_r11: np.ndarray
    ap_r40: np.ndarray
    aos_r11: np.ndarray | None
    aos_r40: np.ndarray | None
    frames: int

    def ap(self, metric: str, name: str, recall: str = "R40") -> np.ndarray:
        """``(3,)`` easy, moderate, hard AP of one metric and class; ``recall`` R40 or R11."""
        table = {"R40": self.ap_r40, "R11": self.ap_r11}[recall]
        return table[METRICS.index(metric), self.classes.index(name)]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: ``{"frames", "classes": {name: {"min_overlap": {metric: t},
        "AP_R40"|"AP_R11": {metric: {difficulty: AP}}, ...}}}``."""
        classes = {}
        for c, name in enumerate(self.classes):
            entry: dict[str, Any] = {
                "min_overlap": dict(zip(METRICS, self.min_overlaps[c].tolist(), strict=True))
            }
            for key, table in (("AP_R40", self.ap_r40), ("AP_R11", self.ap_r11)):
                entry[key] = {m: _by_difficulty(table[i, c]) for i, m in enumerate(METRICS)}
            if self.aos_r40 is not None and self.aos_r11 is not None:
                entry["AOS_R40"] = _by_difficulty(self.aos_r40[c])
                entry["AOS_R11"] = _by_difficulty(self.aos_r11[c])
            classes[name] = entry
        return {"frames": self.frames, "classes": classes}


def _by_difficulty(values: np.ndarray) -> dict[str, float]:
    return {level: round(float(v), 4) for level, v in zip(DIFFICULTIES, values, strict=True)}


@dataclass(frozen=True)
class _Stack:
    """Rows of many frames stacked: ``frame`` ``(N,)`` tells each row's frame."""

    frame: np.ndarray
    names: np.ndarray  # lower case
    truncated: np.ndarray
    occluded: np.ndarray
    alpha: np.ndarray
    bbox: np.ndarray
    boxes: np.ndarray
    score: np.ndarray

    @classmethod
    def of(cls, frames: Sequence[KittiObjects], keep: str) -> _Stack:
        """Stack the ``DontCare`` rows (``keep="dontcare"``) or the others (``"objects"``)."""
        sizes = [len(f) for f in frames]
        names = np.concatenate([f.names for f in frames]) if frames else np.zeros(0, str)
        rows = (names == "DontCare") == (keep == "dontcare")

        def cat(field: str, width: int = 0) -> np.ndarray:
            shape = (0, width) if width else (0,)
            parts = [getattr(f, field).reshape(-1, *shape[1:]) for f in frames]
            return (np.concatenate(parts) if parts else np.zeros(shape))[rows]

        return cls(
            frame=np.repeat(np.arange(len(frames)), sizes)[rows],
            names=np.char.lower(names[rows].astype(str)),
            truncated=cat("truncated"),
            occluded=cat("occluded"),
            alpha=cat("alpha"),
            bbox=cat("bbox", 4),
            boxes=cat("boxes", 7),
            score=cat("score"),
        )


def evaluate_kitti(
    ground_truth: Sequence[KittiObjects],
    detections: Sequence[KittiObjects],
    classes: Sequence[str] = DEFAULT_CLASSES,
    overlaps: str | Mapping[str, Sequence[float]] = "strict",
) -> KittiEvaluation:
    """Evaluate detections against KITTI labels, frame by frame (module docstring: the rules).

    Args:
        ground_truth: per frame, the label file's rows (``DontCare`` included).
        detections: per frame (same order), the result file's rows with scores.
        classes: classes to evaluate, among :data:`STRICT_OVERLAPS`' keys.
        overlaps: ``"strict"`` (:data:`STRICT_OVERLAPS`), ``"loose"`` (:data:`LOOSE_OVERLAPS`)
            or a mapping class -> (2D, BEV, 3D) IoU thresholds.

    Raises:
        DataError: the two sequences differ in length, or no detection has a 2D box.
        ConfigError: an unknown class or overlap set.
    """
    if len(ground_truth) != len(detections):
        raise DataError(
            f"{len(ground_truth)} frames of ground truth but {len(detections)} of detections"
        )
    table = _overlap_table(classes, overlaps)
    gt = _Stack.of(ground_truth, "objects")
    dc = _Stack.of(ground_truth, "dontcare")
    dt = _Stack.of(detections, "objects")
    if len(dt.score) and not (dt.bbox[:, 3] != dt.bbox[:, 1]).any():
        raise DataError(
            f"none of the {len(dt.score)} detections has a 2D box (all heights 0): KITTI's rules "
            "ignore detections lower than 25 px in every metric, so every AP would be 0; "
            "write each box's projection into the image as its bbox"
        )
    gi, di = _frame_pairs(gt.frame, dt.frame, len(ground_truth))
    pair_overlaps = (
        image_iou(dt.bbox[di], gt.bbox[gi]),
        *_box_overlaps(gt.boxes, dt.boxes, gi, di),
    )
    excused_by = _dont_care_coverage(dc, dt, len(ground_truth))
    with_aos = len(dt.alpha) > 0 and bool((dt.alpha != -10).all())
    shape = (len(METRICS), len(table), len(DIFFICULTIES))
    ap = {"R11": np.zeros(shape), "R40": np.zeros(shape)}
    aos = {"R11": np.zeros(shape[1:]), "R40": np.zeros(shape[1:])}
    for m, overlap in enumerate(pair_overlaps):
        positive = overlap > 0
        pairs = (gi[positive], di[positive], overlap[positive])
        for c, (name, thresholds) in enumerate(table.items()):
            excused = excused_by > thresholds[0] if m == 0 else np.zeros(len(dt.score), bool)
            for level in range(len(DIFFICULTIES)):
                precision, similarity = _precision(
                    gt, dt, pairs, name, level, thresholds[m], excused, m == 0 and with_aos
                )
                ap["R11"][m, c, level], ap["R40"][m, c, level] = _average(precision)
                if m == 0 and with_aos:
                    aos["R11"][c, level], aos["R40"][c, level] = _average(similarity)
    return KittiEvaluation(
        classes=tuple(table),
        min_overlaps=np.array(list(table.values()), dtype=np.float64).reshape(-1, 3),
        ap_r11=ap["R11"],
        ap_r40=ap["R40"],
        aos_r11=aos["R11"] if with_aos else None,
        aos_r40=aos["R40"] if with_aos else None,
        frames=len(ground_truth),
    )


def _overlap_table(
    classes: Sequence[str], overlaps: str | Mapping[str, Sequence[float]]
) -> dict[str, tuple[float, float, float]]:
    if isinstance(overlaps, str):
        if overlaps not in ("strict", "loose"):
            raise ConfigError(f"overlaps must be 'strict', 'loose' or a mapping, got {overlaps!r}")
        overlaps = STRICT_OVERLAPS if overlaps == "strict" else LOOSE_OVERLAPS
    if not classes:
        raise ConfigError("no class to evaluate")
    table = {}
    for name in classes:
        if name not in overlaps:
            raise ConfigError(f"unknown class {name!r} (known: {', '.join(overlaps)})")
        values = tuple(float(v) for v in overlaps[name])
        if len(values) != 3 or not all(0 <= v < 1 for v in values):
            raise ConfigError(
                f"{name}: overlap thresholds must be 3 values in [0, 1), got {values}"
            )
        table[name] = values
    return table


def _frame_pairs(
    frame_a: np.ndarray, frame_b: np.ndarray, frames: int
) -> tuple[np.ndarray, np.ndarray]:
    """Every (a, b) row pair of the same frame, ordered by a then b; rows sorted by frame."""
    count_b = np.bincount(frame_b, minlength=frames)
    start_b = np.concatenate([[0], np.cumsum(count_b)[:-1]])
    repeats = count_b[frame_a]
    ia = np.repeat(np.arange(len(frame_a)), repeats)
    first = np.repeat(np.cumsum(repeats) - repeats, repeats)
    ib = np.repeat(start_b[frame_a], repeats) + np.arange(len(ia)) - first
    return ia, ib


def _box_overlaps(
    gt_boxes: np.ndarray, dt_boxes: np.ndarray, gi: np.ndarray, di: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """BEV and 3D IoU ``(P,)`` of the pairs ``(gi, di)``; only pairs whose footprints' bounding
    circles meet are gathered (a frame holds many pairs of distant boxes)."""
    reach = (
        np.hypot(gt_boxes[:, 3], gt_boxes[:, 5])[gi] + np.hypot(dt_boxes[:, 3], dt_boxes[:, 5])[di]
    ) / 2
    gap = np.hypot(gt_boxes[gi, 0] - dt_boxes[di, 0], gt_boxes[gi, 2] - dt_boxes[di, 2])
    near = np.flatnonzero(gap <= reach * (1 + 1e-9))
    bev, box3d = np.zeros(len(gi)), np.zeros(len(gi))
    bev[near] = bev_iou(dt_boxes[di[near]], gt_boxes[gi[near]])
    box3d[near] = iou3d(dt_boxes[di[near]], gt_boxes[gi[near]])
    return bev, box3d


def _dont_care_coverage(dc: _Stack, dt: _Stack, frames: int) -> np.ndarray:
    """Per detection, the largest share of its 2D box inside one of its frame's DontCare boxes."""
    ci, di = _frame_pairs(dc.frame, dt.frame, frames)
    out = np.zeros(len(dt.score))
    np.maximum.at(out, di, image_coverage(dt.bbox[di], dc.bbox[ci]))
    return out


def _precision(
    gt: _Stack,
    dt: _Stack,
    pairs: tuple[np.ndarray, np.ndarray, np.ndarray],
    name: str,
    level: int,
    min_overlap: float,
    excused: np.ndarray,
    with_aos: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """Precision and orientation similarity ``(41,)`` at the recall points, non-increasing."""
    gt_ignored, dt_ignored = _ignore_flags(gt, dt, name.lower(), level)
    gi, di, overlap = pairs
    keep = (gt_ignored[gi] >= 0) & (dt_ignored[di] >= 0) & (overlap > min_overlap)
    gi, di, overlap = gi[keep], di[keep], overlap[keep]
    start = np.concatenate([[0], np.cumsum(np.bincount(gi, minlength=len(gt_ignored)))])
    scores = _matched_scores(gt_ignored, start, di, dt_ignored, dt.score)
    thresholds = _recall_thresholds(np.sort(scores)[::-1], int((gt_ignored == 0).sum()))
    counts = _counts_at(
        thresholds,
        _Objects(gt_ignored, gt.alpha),
        _Candidates(start, di, overlap),
        _Detections(dt_ignored, dt.score, dt.alpha, excused),
    )
    tp, fp, similarity = counts[:, 0], counts[:, 1], counts[:, 3]
    precision = np.zeros(SAMPLE_POINTS)
    orientation = np.zeros(SAMPLE_POINTS)
    found = tp + fp
    # A threshold can leave nothing counted (its detections all absorbed by ignored objects);
    # precision 0 there, where the reference would divide 0 by 0.
    np.divide(tp, found, out=precision[: len(tp)], where=found > 0)
    if with_aos:
        np.divide(similarity, found, out=orientation[: len(tp)], where=found > 0)
    return _running_max(precision), _running_max(orientation)


def _ignore_flags(gt: _Stack, dt: _Stack, name: str, level: int) -> tuple[np.ndarray, np.ndarray]:
    """Per object and per detection: 0 counts, 1 ignored (matchable), -1 not of the class."""
    height = gt.bbox[:, 3] - gt.bbox[:, 1]
    too_hard = (
        (gt.occluded > _MAX_OCCLUSION[level])
        | (gt.truncated > _MAX_TRUNCATION[level])
        | (height <= _MIN_HEIGHT[level])
    )
    own = gt.names == name
    neighbour = gt.names == _NEIGHBOUR.get(name, "")
    gt_flags = np.where(own & ~too_hard, 0, np.where(own | neighbour, 1, -1))
    small = np.abs(dt.bbox[:, 3] - dt.bbox[:, 1]) < _MIN_HEIGHT[level]
    dt_flags = np.where(small, 1, np.where(dt.names == name, 0, -1))
    return gt_flags.astype(np.int64), dt_flags.astype(np.int64)


def _running_max(values: np.ndarray) -> np.ndarray:
    """Each entry raised to the largest at or after it (precision non-increasing in recall)."""
    return np.maximum.accumulate(values[::-1])[::-1]


def _average(precision: np.ndarray) -> tuple[float, float]:
    """R11 (points 0, 4, ..., 40) and R40 (points 1..40) averages, in percent."""
    return float(precision[::4].mean() * 100), float(precision[1:].mean() * 100)


@nb.njit(cache=True, nogil=True)
def _matched_scores(gt_ignored, start, cand_det, dt_ignored, dt_score):  # pragma: no cover
    """Scores of the true positives when every object, in order, takes the best-scoring free
    candidate (no score threshold). Candidates of object g: ``cand_det[start[g]:start[g+1]]``,
    in detection order, so equal scores go to the first detection."""
    taken = np.zeros(dt_score.shape[0], np.bool_)
    out = np.empty(gt_ignored.shape[0])
    count = 0
    for g in range(gt_ignored.shape[0]):
        best = -1
        for k in range(start[g], start[g + 1]):
            d = cand_det[k]
            if not taken[d] and (best < 0 or dt_score[d] > dt_score[best]):
                best = d
        if best >= 0:
            taken[best] = True
            if gt_ignored[g] == 0 and dt_ignored[best] == 0:
                out[count] = dt_score[best]
                count += 1
    return out[:count]


@nb.njit(cache=True, nogil=True)
def _recall_thresholds(scores, valid):  # pragma: no cover - numba
    """Score thresholds (descending) whose recall comes nearest 0, 1/40, ..., 1 in turn.

    ``scores``: true-positive scores, descending; ``valid``: objects that count. A score is
    kept when its recall is at least as near the next sample recall as the following score's
    (the last score always is); the sample recall then moves on by 1/40.
    """
    out = np.empty(SAMPLE_POINTS)
    count = 0
    target = 0.0
    last = scores.shape[0] - 1
    for i in range(scores.shape[0]):
        here = (i + 1) / valid
        after = (i + 2) / valid if i < last else here
        if i < last and (after - target) < (target - here):
            continue
        if count == SAMPLE_POINTS:
            break
        out[count] = scores[i]
        count += 1
        target += 1.0 / (SAMPLE_POINTS - 1.0)
    return out[:count]


class _Objects(NamedTuple):
    """The labelled objects of one class and level: ``ignored`` flags (see
    :func:`_ignore_flags`) and observation angles."""

    ignored: np.ndarray
    alpha: np.ndarray


class _Candidates(NamedTuple):
    """Each object's candidate detections: ``start`` ``(G + 1,)`` its first slot, then per slot
    the detection and their overlap."""

    start: np.ndarray
    det: np.ndarray
    overlap: np.ndarray


class _Detections(NamedTuple):
    """The detections: ``ignored`` flags, scores, observation angles and ``excused`` (in a
    DontCare region: never a false positive)."""

    ignored: np.ndarray
    score: np.ndarray
    alpha: np.ndarray
    excused: np.ndarray


@nb.njit(cache=True, nogil=True)
def _counts_at(thresholds, objects, candidates, detections):  # pragma: no cover - numba
    """``(T, 4)`` true positives, false positives, misses and orientation similarity sum per
    score threshold: each object, in order, takes the free counted candidate with the largest
    overlap, or failing one the first free ignored candidate."""
    gt_ignored, gt_alpha = objects.ignored, objects.alpha
    start, cand_det, cand_overlap = candidates.start, candidates.det, candidates.overlap
    dt_ignored, dt_score = detections.ignored, detections.score
    dt_alpha, excused = detections.alpha, detections.excused
    out = np.zeros((thresholds.shape[0], 4))
    for t in range(thresholds.shape[0]):
        floor = thresholds[t]
        taken = np.zeros(dt_score.shape[0], np.bool_)
        for g in range(gt_ignored.shape[0]):
            best, best_overlap, best_ignored = -1, 0.0, False
            for k in range(start[g], start[g + 1]):
                d = cand_det[k]
                if taken[d] or dt_score[d] < floor:
                    continue
                if dt_ignored[d] == 0:
                    if cand_overlap[k] > best_overlap or best_ignored:
                        best, best_overlap, best_ignored = d, cand_overlap[k], False
                elif best < 0:
                    best, best_ignored = d, True
            if best < 0:
                out[t, 2] += gt_ignored[g] == 0
                continue
            taken[best] = True
            if gt_ignored[g] == 0 and dt_ignored[best] == 0:
                out[t, 0] += 1
                out[t, 3] += (1.0 + np.cos(gt_alpha[g] - dt_alpha[best])) / 2.0
        for d in range(dt_score.shape[0]):
            if dt_ignored[d] == 0 and not taken[d] and dt_score[d] >= floor and not excused[d]:
                out[t, 1] += 1
    return out
