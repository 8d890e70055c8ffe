"""Time the KITTI evaluator on 1,000 synthetic frames (labels and noisy detections).

The frames come from ``tests/kitti_eval_data.py`` (KITTI-like labels, about 7 objects and 9
detections per frame). The numba kernels are compiled (or loaded from cache) on a small run
first, so the times are those of evaluation proper. Reported: reading the label and result
files, and evaluating Car, Pedestrian, Cyclist (2D, BEV, 3D, AOS; R11 and R40) with the strict
and the loose thresholds, each the best of ``--repeat`` runs.

Usage: ``python benchmarks/bench_evaluation.py [--frames N] [--repeat R] [--quick]``; the last
stdout line is one JSON object ``{"frames", "objects", "detections", "read_s", "evaluate_s", ...}``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from drcpo.evaluation import evaluate_kitti, read_frames

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import kitti_eval_data


def _best(repeat: int, run) -> tuple[float, object]:
    times, value = [], None
    for _ in range(repeat):
        start = time.perf_counter()
        value = run()
        times.append(time.perf_counter() - start)
    return min(times), value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="100 frames, one run")
    args = parser.parse_args()
    if args.quick:
        args.frames, args.repeat = 100, 1
    with tempfile.TemporaryDirectory() as tmp:
        gt_dir, dt_dir = Path(tmp) / "gt", Path(tmp) / "dt"
        ids = kitti_eval_data.write_frames(gt_dir, dt_dir, args.frames, np.random.default_rng(0))
        warm = read_frames(gt_dir, ids[:5]), read_frames(dt_dir, ids[:5], results=True)
        evaluate_kitti(*warm)  # compiles or loads the numba kernels
        read_s, (gt, dt) = _best(
            args.repeat, lambda: (read_frames(gt_dir, ids), read_frames(dt_dir, ids, results=True))
        )
    report = {"frames": args.frames, "objects": sum(map(len, gt)), "detections": sum(map(len, dt))}
    report["read_s"] = round(read_s, 3)
    for overlaps in ("strict", "loose"):
        seconds, result = _best(args.repeat, lambda o=overlaps: evaluate_kitti(gt, dt, overlaps=o))
        report[f"evaluate_{overlaps}_s"] = round(seconds, 3)
        report[f"car_3d_moderate_R40_{overlaps}"] = round(float(result.ap("3d", "Car")[1]), 2)
    report["evaluate_s"] = report["evaluate_strict_s"]
    print(
        f"{args.frames} frames ({report['objects']} objects, {report['detections']} detections): "
        f"read {report['read_s']:.2f} s, evaluate {report['evaluate_s']:.2f} s"
    )
    print(json.dumps(report))


if __name__ == "__main__":
    main()
