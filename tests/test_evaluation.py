"""KITTI evaluator: overlaps against shapely, the devkit's rules on hand-made frames, file
errors, the CLI, and every AP against OpenPCDet's unmodified evaluator."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import kitti_eval_data
import numpy as np
import pytest
from conftest import KITTI_SAMPLE, SHARED
from shapely.geometry import Polygon, box

from drcpo.errors import ConfigError, DataError
from drcpo.evaluation import (
    KittiObjects,
    evaluate_kitti,
    evaluate_kitti_split,
    read_frames,
    read_kitti_objects,
)
from drcpo.evaluation.overlaps import (
    bev_intersection,
    bev_iou,
    image_coverage,
    image_iou,
    iou3d,
)

TESTS = Path(__file__).resolve().parent
REFERENCE = SHARED / "third_party/OpenPCDet/pcdet/datasets/kitti/kitti_object_eval_python"


# --------------------------------------------------------------------------------------------
# Overlaps against shapely polygons built from the KITTI definition
# --------------------------------------------------------------------------------------------
def _random_camera_boxes(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.column_stack(
        [
            rng.uniform(-3, 3, n),
            rng.uniform(1, 2, n),
            rng.uniform(10, 16, n),
            rng.uniform(0.5, 5, n),
            rng.uniform(0.5, 2.5, n),
            rng.uniform(0.5, 3, n),
            rng.uniform(-np.pi, np.pi, n),
        ]
    )


def _footprint(b: np.ndarray) -> Polygon:
    """x-z footprint: length along (cos ry, -sin ry), width along (sin ry, cos ry)."""
    x, _, z, length, _, width, ry = b
    along = np.array([np.cos(ry), -np.sin(ry)]) * length / 2
    across = np.array([np.sin(ry), np.cos(ry)]) * width / 2
    centre = np.array([x, z])
    return Polygon(
        [centre + sa * along + sc * across for sa, sc in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
    )


def test_bev_and_3d_iou_match_shapely(rng):
    a, b = _random_camera_boxes(rng, 400), _random_camera_boxes(rng, 400)
    inter = np.array(
        [_footprint(p).intersection(_footprint(q)).area for p, q in zip(a, b, strict=True)]
    )
    assert (inter > 0).sum() > 100  # the test exercises real overlaps
    np.testing.assert_allclose(bev_intersection(a, b), inter, atol=1e-9)
    union = a[:, 3] * a[:, 5] + b[:, 3] * b[:, 5] - inter
    np.testing.assert_allclose(bev_iou(a, b), inter / union, atol=1e-9)
    tall = np.clip(
        np.minimum(a[:, 1], b[:, 1]) - np.maximum(a[:, 1] - a[:, 4], b[:, 1] - b[:, 4]), 0, None
    )
    volume = inter * tall
    expected = volume / (a[:, 3:6].prod(1) + b[:, 3:6].prod(1) - volume)
    np.testing.assert_allclose(iou3d(a, b), expected, atol=1e-9)


def test_heading_sign_follows_kitti():
    # A thin 4 m box with ry = 0.5 reaches x, z = centre + 1.9 (cos 0.5, -sin 0.5), not +sin.
    long = np.array([[0, 1.5, 20, 4.0, 1.5, 0.2, 0.5]])
    tip = np.array([1.9 * np.cos(0.5), 1.5, 20 - 1.9 * np.sin(0.5), 0.05, 1.5, 0.05, 0.0])
    mirrored = tip.copy()
    mirrored[2] = 20 + 1.9 * np.sin(0.5)
    assert bev_intersection(long, tip[None])[0] == pytest.approx(0.05**2)
    assert bev_intersection(long, mirrored[None])[0] == 0.0
    # A mirrored heading is a different box: IoU well below 1 for an elongated box.
    flipped = long.copy()
    flipped[0, 6] = -0.5
    assert bev_iou(long, flipped)[0] < 0.3


def test_image_overlaps_match_shapely(rng):
    corner = rng.uniform(0, 100, (300, 2))
    a = np.column_stack([corner, corner + rng.uniform(1, 60, (300, 2))])
    b = np.column_stack(
        [corner + rng.normal(0, 20, (300, 2)), corner + rng.uniform(1, 60, (300, 2))]
    )
    b[:, 2:] = np.maximum(b[:, 2:], b[:, :2] + 1)
    inter = np.array([box(*p).intersection(box(*q)).area for p, q in zip(a, b, strict=True)])
    area_a = np.array([box(*p).area for p in a])
    area_b = np.array([box(*q).area for q in b])
    np.testing.assert_allclose(image_iou(a, b), inter / (area_a + area_b - inter), atol=1e-12)
    np.testing.assert_allclose(image_coverage(a, b), inter / area_a, atol=1e-12)


# --------------------------------------------------------------------------------------------
# The devkit's rules on hand-made frames
# --------------------------------------------------------------------------------------------
def _objects(rows: list[tuple]) -> KittiObjects:
    """rows: (name, truncated, occluded, bbox (4), camera box (7), score)."""
    names = [r[0] for r in rows]
    table = np.array([[r[1], r[2], 0.0, *r[3], *r[4], r[5]] for r in rows]).reshape(-1, 15)
    return KittiObjects(
        names=np.array(names, dtype=str),
        truncated=table[:, 0],
        occluded=table[:, 1],
        alpha=np.full(len(rows), -10.0),
        bbox=table[:, 3:7],
        boxes=table[:, 7:14],
        score=table[:, 14],
    )


CAR_AT = [np.array([x, 1.6, 15.0, 3.9, 1.5, 1.6, 0.3]) for x in (-6.0, 0.0, 6.0)]
BOX_AT = [np.array([100.0 + 300 * i, 150, 200 + 300 * i, 200]) for i in range(3)]  # 50 px tall


def _ap(gt_rows, dt_rows, metric="3d", name="Car", recall="R40", copies=100) -> np.ndarray:
    """AP over ``copies`` copies of one frame: the devkit's 41 score thresholds need many
    objects (with few, recall points past the last true positive score 0)."""
    frames = [_objects(gt_rows)] * copies, [_objects(dt_rows)] * copies
    return evaluate_kitti(*frames, [name]).ap(metric, name, recall)


def test_perfect_detections_score_100_and_a_mirrored_heading_does_not():
    gt = [("Car", 0.0, 0, BOX_AT[i], CAR_AT[i], 0.0) for i in range(3)]
    dt = [("Car", -1, -1, BOX_AT[i], CAR_AT[i] + 0.01, 0.9 - 0.1 * i) for i in range(3)]
    for metric in ("2d", "bev", "3d"):
        np.testing.assert_allclose(_ap(gt, dt, metric), 100.0)
        np.testing.assert_allclose(_ap(gt, dt, metric, recall="R11"), 100.0)
    mirrored = [(n, t, o, b, c * [1, 1, 1, 1, 1, 1, -1], s) for n, t, o, b, c, s in dt]
    np.testing.assert_allclose(_ap(gt, mirrored, "3d"), 0.0)
    np.testing.assert_allclose(_ap(gt, mirrored, "2d"), 100.0)


def test_few_objects_leave_the_last_recall_points_empty():
    gt = [("Car", 0.0, 0, BOX_AT[i], CAR_AT[i], 0.0) for i in range(3)]
    dt = [("Car", -1, -1, BOX_AT[i], CAR_AT[i], 0.9 - 0.1 * i) for i in range(3)]
    # 3 objects, 3 thresholds: recall points 3..40 get precision 0 (as in the devkit).
    np.testing.assert_allclose(_ap(gt, dt, copies=1), 100 * 2 / 40)
    np.testing.assert_allclose(_ap(gt, dt, recall="R11", copies=1), 100 / 11)


def test_van_is_ignored_for_car_and_other_classes_count():
    gt = [("Car", 0.0, 0, BOX_AT[0], CAR_AT[0], 0.0), ("Van", 0.0, 0, BOX_AT[1], CAR_AT[1], 0.0)]
    dt = [
        ("Car", -1, -1, BOX_AT[0], CAR_AT[0], 0.8),
        ("Car", -1, -1, BOX_AT[1], CAR_AT[1], 0.9),  # on the Van: neither true nor false
    ]
    np.testing.assert_allclose(_ap(gt, dt), 100.0)
    truck = [gt[0], ("Truck", 0.0, 0, BOX_AT[1], CAR_AT[1], 0.0)]
    # On a Truck the higher-scoring detection is a false positive: precision 1/2 throughout.
    np.testing.assert_allclose(_ap(truck, dt), 50.0)
    sitting = [("Pedestrian", 0.0, 0, BOX_AT[0], CAR_AT[0], 0.0)]
    sitting.append(("Person_sitting", 0.0, 0, BOX_AT[1], CAR_AT[1], 0.0))
    on_sitting = [("Pedestrian", *row[1:]) for row in dt]
    np.testing.assert_allclose(_ap(sitting, on_sitting, name="Pedestrian"), 100.0)


def test_difficulty_levels_ignore_occluded_truncated_and_small_objects():
    gt = [
        ("Car", 0.0, 0, BOX_AT[0], CAR_AT[0], 0.0),
        ("Car", 0.0, 2, BOX_AT[1], CAR_AT[1], 0.0),  # occlusion 2: hard only
        ("Car", 0.4, 0, BOX_AT[2], CAR_AT[2], 0.0),  # truncation 0.4: hard only
    ]
    dt = [("Car", -1, -1, BOX_AT[0], CAR_AT[0], 0.9)]
    easy, moderate, hard = _ap(gt, dt)
    assert easy == moderate == pytest.approx(100.0)
    # In hard they count: as if all three were plain objects, two of them missed.
    visible = [(name, 0.0, 0, *rest) for name, _, _, *rest in gt]
    assert hard == pytest.approx(_ap(visible, dt)[0]) and hard < 50
    short = [("Car", 0.0, 0, BOX_AT[0] + [0, 10, 0, 0], CAR_AT[0], 0.0)]  # 40 px: not easy
    # The detection keeps its 50 px box: it matches the ignored easy object (no FP), so easy
    # has nothing to find.
    np.testing.assert_allclose(_ap(short, dt), [0, 100, 100])


def test_small_detections_and_dont_care_regions_excuse_false_positives():
    gt = [("Car", 0.0, 0, BOX_AT[0], CAR_AT[0], 0.0)]
    small = ("Car", -1, -1, np.array([500.0, 150, 540, 174.9]), CAR_AT[2], 0.95)  # < 25 px
    dt = [("Car", -1, -1, BOX_AT[0], CAR_AT[0], 0.9), small]
    np.testing.assert_allclose(_ap(gt, dt), 100.0)  # ignored at every level
    in_dc = ("Car", -1, -1, BOX_AT[2], CAR_AT[2], 0.95)
    dont_care = ("DontCare", -1, -1, BOX_AT[2] + [-5, -5, 5, 5], np.full(7, -1.0), 0.0)
    dt = [dt[0], in_dc]
    # In 2D the detection inside the DontCare region is excused; in BEV and 3D it is a false
    # positive, as in OpenPCDet's evaluator.
    np.testing.assert_allclose(_ap([*gt, dont_care], dt, "2d"), 100.0)
    np.testing.assert_allclose(_ap([*gt, dont_care], dt, "3d"), 50.0)
    np.testing.assert_allclose(_ap(gt, dt, "2d"), 50.0)


def test_scores_rank_detections_and_empty_inputs_score_zero():
    gt = [("Car", 0.0, 0, BOX_AT[i], CAR_AT[i], 0.0) for i in range(2)]
    far = CAR_AT[2] + [0, 0, 20, 0, 0, 0, 0]
    good_first = [
        ("Car", -1, -1, BOX_AT[0], CAR_AT[0], 0.9),
        ("Car", -1, -1, BOX_AT[1], CAR_AT[1], 0.8),
        ("Car", -1, -1, BOX_AT[2], far, 0.1),
    ]
    bad_first = [(*row[:5], 1.0 - row[5]) for row in good_first]
    assert _ap(gt, good_first)[0] == pytest.approx(100.0)
    assert _ap(gt, bad_first)[0] == pytest.approx(100 * 2 / 3)  # precision 2/3 at recall 1
    np.testing.assert_allclose(_ap(gt, []), 0.0)
    np.testing.assert_allclose(_ap([], good_first), 0.0)


def test_bad_arguments_raise_clear_errors():
    frame = _objects([])
    with pytest.raises(DataError, match="1 frames of ground truth but 2"):
        evaluate_kitti([frame], [frame, frame])
    with pytest.raises(ConfigError, match="unknown class 'Bus'"):
        evaluate_kitti([frame], [frame], ["Bus"])
    no_box = _objects([("Car", -1, -1, np.zeros(4), CAR_AT[0], 0.5)])
    with pytest.raises(DataError, match="none of the 1 detections has a 2D box"):
        evaluate_kitti([frame], [no_box])
    with pytest.raises(ConfigError, match="overlaps must be"):
        evaluate_kitti([frame], [frame], overlaps="tight")


# --------------------------------------------------------------------------------------------
# The matching kernels against OpenPCDet's loops written out (compute_statistics_jit,
# get_thresholds), over a dense overlap matrix
# --------------------------------------------------------------------------------------------
def naive_statistics(overlap, gt_flags, dt_flags, score, alphas, excused, threshold, first):
    """One pass of OpenPCDet's compute_statistics_jit: every object (flag -1: not of the class)
    in order against every detection in order. ``first``: the pass without a score threshold
    that picks the highest-scoring free detection and returns the true positives' scores;
    else (tp, fp, fn, orientation similarity) at ``threshold``, each object taking the free
    counted detection of largest overlap, else the first free ignored one. ``overlap`` holds 0
    where a pair does not overlap above the class's minimum."""
    gt_alpha, dt_alpha = alphas
    assigned = np.zeros(len(score), bool)
    tp = fn = 0
    similarity, scores = 0.0, []
    for g in range(len(gt_flags)):
        if gt_flags[g] == -1:
            continue
        det, valid, max_overlap, took_ignored = -1, None, 0.0, False
        for d in range(len(score)):
            if dt_flags[d] == -1 or assigned[d] or overlap[g, d] <= 0:
                continue
            if first:
                if valid is None or score[d] > valid:
                    det, valid = d, score[d]
            elif score[d] < threshold:
                continue
            elif dt_flags[d] == 0 and (overlap[g, d] > max_overlap or took_ignored):
                det, valid, max_overlap, took_ignored = d, 1, overlap[g, d], False
            elif valid is None and dt_flags[d] == 1:
                det, valid, took_ignored = d, 1, True
        if valid is None:
            fn += gt_flags[g] == 0
        elif gt_flags[g] == 1 or dt_flags[det] == 1:
            assigned[det] = True
        else:
            tp += 1
            scores.append(score[det])
            similarity += (1.0 + np.cos(gt_alpha[g] - dt_alpha[det])) / 2.0
            assigned[det] = True
    if first:
        return np.array(scores)
    counted = (dt_flags == 0) & ~assigned & (score >= threshold) & ~excused
    return tp, int(counted.sum()), fn, similarity


def naive_thresholds(scores, num_gt, points=41):
    """OpenPCDet's get_thresholds: a score is kept when its recall is nearer the next sample
    recall than the following score's (the last always)."""
    scores = np.sort(scores)[::-1]
    current, kept = 0.0, []
    for i, value in enumerate(scores):
        left = (i + 1) / num_gt
        right = (i + 2) / num_gt if i < len(scores) - 1 else left
        if right - current < current - left and i < len(scores) - 1:
            continue
        kept.append(value)
        current += 1 / (points - 1.0)
    return np.array(kept)


def matching_case(rng, objects, detections):
    """Random flags, scores and overlaps with many ties (a few distinct values each)."""
    gt_flags = rng.choice([0, 0, 0, 1, -1], objects)
    dt_flags = rng.choice([0, 0, 0, 1, -1], detections)
    score = rng.choice([0.1, 0.3, 0.5, 0.5, 0.7, 0.9], detections)
    score += rng.choice([0, 1e-3], detections)
    overlap = rng.choice([0.0, 0.0, 0.0, 0.6, 0.75, 0.9], (objects, detections))
    alphas = (rng.uniform(-np.pi, np.pi, objects), rng.uniform(-np.pi, np.pi, detections))
    excused = rng.random(detections) < 0.15
    return overlap, gt_flags, dt_flags, score, alphas, excused


def test_matching_kernels_follow_openpcdets_loops():
    from drcpo.evaluation.kitti import (  # test seams: the numba kernels of _precision
        _Candidates,
        _counts_at,
        _Detections,
        _matched_scores,
        _Objects,
        _recall_thresholds,
    )

    def check(case):
        overlap, gt_flags, dt_flags, score, alphas, excused = case
        # The kernels' candidate lists, as _precision builds them: per object in order, its
        # counted or ignored detections above the minimum overlap, in detection order.
        usable = (gt_flags[:, None] >= 0) & (dt_flags[None] >= 0) & (overlap > 0)
        gi, di = np.nonzero(usable)
        start = np.concatenate([[0], np.cumsum(np.bincount(gi, minlength=len(gt_flags)))])
        scores = naive_statistics(*case, None, first=True)
        got = _matched_scores(gt_flags, start, di, dt_flags, score)
        np.testing.assert_array_equal(got, scores)
        valid = int((gt_flags == 0).sum())
        thresholds = naive_thresholds(scores, valid)
        np.testing.assert_array_equal(_recall_thresholds(np.sort(got)[::-1], valid), thresholds)
        # every threshold found, and ties: scores exactly at a threshold, above all, none
        floors = np.concatenate([thresholds, [0.5, 0.5 + 1e-3, 2.0, 0.0, -np.inf]])
        counts = _counts_at(
            floors,
            _Objects(gt_flags, alphas[0]),
            _Candidates(start, di, overlap[gi, di]),
            _Detections(dt_flags, score, alphas[1], excused),
        )
        want = np.array([naive_statistics(*case, f, first=False) for f in floors]).reshape(-1, 4)
        np.testing.assert_array_equal(counts[:, :3], want[:, :3])
        np.testing.assert_allclose(counts[:, 3], want[:, 3], rtol=1e-12)
        return thresholds

    rng = np.random.default_rng(61)
    for objects, detections in [(30, 40), (80, 60), (5, 0), (0, 7), (0, 0), (1, 1), (300, 200)] * 3:
        check(matching_case(rng, objects, detections))
    # Every object found once, at 97 distinct scores: all 41 recall points get a threshold.
    n = 97
    perfect = (np.eye(n) * 0.9, np.zeros(n, int), np.zeros(n, int), rng.permutation(n) / n)
    assert len(check((*perfect, (np.zeros(n), np.zeros(n)), np.zeros(n, bool)))) == 41


# --------------------------------------------------------------------------------------------
# Files and the CLI
# --------------------------------------------------------------------------------------------
def _kitti_root(tmp_path: Path, frames: int = 12, seed: int = 3) -> tuple[Path, Path]:
    root, pred = tmp_path / "kitti", tmp_path / "pred"
    ids = kitti_eval_data.write_frames(
        root / "training" / "label_2", pred, frames, np.random.default_rng(seed)
    )
    (root / "ImageSets").mkdir(parents=True)
    (root / "ImageSets" / "val.txt").write_text("\n".join(ids) + "\n")
    return root, pred


def test_malformed_and_missing_files_are_named(tmp_path):
    root, pred = _kitti_root(tmp_path)
    bad = pred / "000003.txt"
    lines = bad.read_text().splitlines()
    bad.write_text("\n".join([lines[0], " ".join(lines[1].split()[:-1]), *lines[2:]]))
    with pytest.raises(DataError, match=r"000003\.txt:2: expected 16 fields"):
        evaluate_kitti_split(root, "val", pred)
    bad.write_text(lines[0].replace("Car", "Car").rsplit(" ", 1)[0] + " high\n")
    with pytest.raises(DataError, match=r"000003\.txt:1: not a number"):
        read_kitti_objects(bad, results=True)
    bad.unlink()
    with pytest.raises(DataError, match=r"000003\.txt: result file missing \(1 of 12"):
        evaluate_kitti_split(root, "val", pred)
    with_empty = evaluate_kitti_split(root, "val", pred, missing_as_empty=True)
    assert with_empty.frames == 12
    (root / "training" / "label_2" / "000005.txt").unlink()
    with pytest.raises(DataError, match=r"000005\.txt: label file missing"):
        evaluate_kitti_split(root, "val", pred, missing_as_empty=True)


def test_a_missing_result_file_means_no_detections(tmp_path):
    root, pred = _kitti_root(tmp_path)
    full = evaluate_kitti_split(root, "val", pred)
    ids = [line for line in (root / "ImageSets" / "val.txt").read_text().split()]
    for frame_id in ids[:6]:
        (pred / f"{frame_id}.txt").write_text("")
    emptied = evaluate_kitti_split(root, "val", pred)
    for frame_id in ids[:6]:
        (pred / f"{frame_id}.txt").unlink()
    missing = evaluate_kitti_split(root, "val", pred, missing_as_empty=True)
    np.testing.assert_array_equal(missing.ap_r40, emptied.ap_r40)
    assert (missing.ap_r40 < full.ap_r40).any()


def test_label_files_keep_dont_care_and_read_float64(tmp_path):
    path = tmp_path / "000000.txt"
    path.write_text(
        "Car 0.00 0 1.85 387.63 181.54 423.81 203.12 1.67 1.87 3.69 -16.53 2.39 58.49 1.57\n"
        "DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10\n"
    )
    objects = read_kitti_objects(path)
    assert objects.names.tolist() == ["Car", "DontCare"]
    assert objects.bbox.dtype == np.float64 and objects.bbox[0, 3] == 203.12
    np.testing.assert_array_equal(objects.boxes[0], [-16.53, 2.39, 58.49, 3.69, 1.67, 1.87, 1.57])
    with pytest.raises(DataError, match="expected 16 fields"):
        read_kitti_objects(path, results=True)
    path.write_text("Car 0 0 0 1 1 2 2 1.5 1.6 0 1 1 10 0\n")
    with pytest.raises(DataError, match=r"000000\.txt:1: Car has a non-positive size"):
        read_kitti_objects(path)
    with pytest.raises(DataError, match="result directory missing"):
        read_frames(tmp_path / "none", ["000000"], results=True)


def test_cli_evaluate_prints_a_table_and_json(tmp_path):
    from typer.testing import CliRunner

    from drcpo.cli import app

    root, pred = _kitti_root(tmp_path)
    args = ["evaluate", "--gt", str(root), "--split", "val", "--pred", str(pred)]
    shown = CliRunner().invoke(app, args)
    assert shown.exit_code == 0, shown.output
    assert "Pedestrian" in shown.output and "moderate" in shown.output
    as_json = CliRunner().invoke(app, [*args, "--json", "--loose", "--classes", "Car"])
    assert as_json.exit_code == 0, as_json.output
    payload = json.loads(as_json.output)
    expected = evaluate_kitti_split(root, "val", pred, ["Car"], "loose")
    assert payload["frames"] == 12 and list(payload["classes"]) == ["Car"]
    car = payload["classes"]["Car"]
    assert car["min_overlap"] == {"2d": 0.7, "bev": 0.5, "3d": 0.5}
    assert car["AP_R40"]["3d"]["moderate"] == pytest.approx(expected.ap("3d", "Car")[1], abs=1e-4)
    (pred / "000000.txt").unlink()
    missing = CliRunner().invoke(app, args)
    assert missing.exit_code == 1 and "000000.txt: result file missing" in missing.output
    assert "Traceback" not in missing.output
    allowed = CliRunner().invoke(app, [*args, "--missing-empty", "--json"])
    assert allowed.exit_code == 0 and json.loads(allowed.output)["frames"] == 12


# --------------------------------------------------------------------------------------------
# Every AP against OpenPCDet's evaluator (run unmodified, on numba's CUDA simulator)
# --------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_every_ap_matches_openpcdet(tmp_path):
    if not (REFERENCE / "eval.py").is_file():
        pytest.skip(f"OpenPCDet's evaluator not found at {REFERENCE}")
    label_dir = KITTI_SAMPLE / "training" / "label_2"
    if not label_dir.is_dir():
        pytest.skip(f"KITTI sample labels not found at {label_dir}")
    rng = np.random.default_rng(2024)
    gt_dir, dt_dir = tmp_path / "gt", tmp_path / "dt"
    # 100 synthetic frames, then the 6 real frames' labels 4 times each with fresh noise.
    kitti_eval_data.write_frames(gt_dir, dt_dir, 100, rng)
    real = [kitti_eval_data.read_rows(p) for p in sorted(label_dir.glob("*.txt"))]
    extra_gt, extra_dt = tmp_path / "gt_real", tmp_path / "dt_real"
    kitti_eval_data.write_frames(extra_gt, extra_dt, 4 * len(real), rng, labels=real)
    for source, target in ((extra_gt, gt_dir), (extra_dt, dt_dir)):
        for path in sorted(source.glob("*.txt")):
            path.rename(target / f"{100 + int(path.stem):06d}.txt")
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"}
    script = [sys.executable, str(TESTS / "kitti_reference_eval.py"), str(REFERENCE)]
    run = subprocess.run(
        [*script, str(gt_dir), str(dt_dir)], env=env, capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, run.stderr[-3000:]
    reference = json.loads(run.stdout.splitlines()[-1])

    ids = sorted(path.stem for path in gt_dir.glob("*.txt"))
    assert len(ids) == 124
    ground_truth, detections = read_frames(gt_dir, ids), read_frames(dt_dir, ids, results=True)
    ours = [evaluate_kitti(ground_truth, detections, overlaps=s) for s in ("strict", "loose")]
    for key, index in (("bbox", 0), ("bev", 1), ("3d", 2)):
        for recall in ("R11", "R40"):
            theirs = np.array(reference[key][recall])  # (class, difficulty, overlap set)
            mine = np.stack([getattr(r, f"ap_{recall.lower()}")[index] for r in ours], axis=-1)
            np.testing.assert_allclose(mine, theirs, atol=0.01, err_msg=f"{key} {recall}")
    for recall in ("R11", "R40"):
        mine = np.stack([getattr(r, f"aos_{recall.lower()}") for r in ours], axis=-1)
        np.testing.assert_allclose(mine, np.array(reference["aos"][recall]), atol=0.01)
    # The data spread the APs (a degenerate set, all 0 or all 100, would prove little).
    values = np.concatenate([r.ap_r40.ravel() for r in ours])
    assert ((values > 5) & (values < 95)).mean() > 0.8
    assert len(np.unique(values.round(3))) > 30  # 2D thresholds are shared by both sets


# --------------------------------------------------------------------------------------------
# AP of resampled frames (bootstrap) from per-frame tables
# --------------------------------------------------------------------------------------------
def test_frame_tables_score_any_multiset_of_frames_as_the_evaluator_does(tmp_path):
    from drcpo.evaluation import DIFFICULTIES, METRICS
    from drcpo.evaluation.resampling import frame_tables

    root, pred = _kitti_root(tmp_path, frames=40, seed=11)
    ids = (root / "ImageSets" / "val.txt").read_text().split()
    gt = read_frames(root / "training" / "label_2", ids)
    dt = read_frames(pred, ids, results=True)
    rng = np.random.default_rng(5)
    draws = [np.ones(len(ids), np.int64), rng.multinomial(len(ids), np.full(len(ids), 1 / 40))]
    draws.append(np.zeros(len(ids), np.int64))
    draws[-1][[3, 7]] = (4, 1)  # a few frames, one drawn four times
    for level in ("easy", "moderate"):
        tables = frame_tables(gt, dt, difficulty=level)
        for weights in draws:
            picked = np.repeat(np.arange(len(ids)), weights)
            full = evaluate_kitti([gt[i] for i in picked], [dt[i] for i in picked])
            for metric in METRICS:
                for name in full.classes:
                    expected = full.ap(metric, name)[DIFFICULTIES.index(level)]
                    got = tables.ap_r40(metric, name, weights)
                    assert got == pytest.approx(expected, abs=1e-9), (level, metric, name)
    assert tables.ap_r40("3d", "Car") > 0  # the frames hold matches, the check is not vacuous
    with pytest.raises(DataError, match="weights must be 40 counts"):
        tables.ap_r40("3d", "Car", np.ones(3, np.int64))
    with pytest.raises(DataError, match="difficulty must be one of"):
        frame_tables(gt, dt, difficulty="medium")
