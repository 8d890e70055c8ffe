"""How well and how fast ``sensor: auto`` (:func:`drcpo.sensor_config.estimate_sensor`) estimates a
frame's sensor.

KITTI sample (when ``../shared`` is present): per frame, the beams found, the azimuth step, the
share of returns (2 m or more away) within 0.1 degree of their beam's elevation seen from the
beam's fitted origin, the median such miss, and the time per estimate (median of repeats).
Synthetic world (seeds not used by the tests, several azimuth steps): the largest elevation
error against the world's sensor, the step error, and whether every return falls in the ray
cell it was fired in; the same with the points shuffled (the histogram fallback).

The last stdout line is one JSON object. Usage: ``python benchmarks/bench_sensor.py
[--repeats N] [--seeds N]``
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from drcpo.sensor import Sensor
from drcpo.sensor_config import estimate_sensor
from drcpo.synth import LidarConfig, generate_world, scan
from drcpo.synth.dataset import frame_rng

KITTI_VELODYNE = (
    Path(__file__).resolve().parents[1].parent / "shared/data/kitti_sample/training/velodyne"
)
STEPS_DEG = (0.17, 0.1, 0.2, 0.3)


def _on_beam(sensor: Sensor, points: np.ndarray) -> tuple[float, float]:
    """Share of the returns 2 m or more away within 0.1 degree of their beam, and the median
    miss (degrees), elevations seen from each beam's origin."""
    beam, _, _ = sensor.cells(points)
    horizontal = np.hypot(points[:, 0], points[:, 1])
    on = (beam >= 0) & (horizontal >= 2.0)
    own = np.arctan2(points[on, 2] - sensor.offsets[beam[on]], horizontal[on])
    miss = np.degrees(np.abs(own - sensor.elevations[beam[on]]))
    share = float((miss <= 0.1).sum() / max(1, int((horizontal >= 2.0).sum())))
    return share, float(np.median(miss))


def _timed(points: np.ndarray, repeats: int) -> tuple[Sensor, float]:
    sensor = estimate_sensor(points)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        estimate_sensor(points)
        times.append(time.perf_counter() - start)
    return sensor, 1000.0 * float(np.median(times))


def kitti(repeats: int) -> dict:
    rows = []
    for path in sorted(KITTI_VELODYNE.glob("*.bin")):
        points = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
        sensor, ms = _timed(points, repeats)
        share, miss = _on_beam(sensor, points)
        rows.append(
            {
                "frame": path.stem,
                "beams": sensor.num_beams,
                "step_deg": round(math.degrees(sensor.azimuth_step), 5),
                "on_beam_0.1deg": round(share, 4),
                "median_miss_deg": round(miss, 4),
                "ms": round(ms, 2),
            }
        )
        print(json.dumps(rows[-1]))
    if not rows:
        return {}
    return {
        "frames": rows,
        "median_ms": round(float(np.median([r["ms"] for r in rows])), 2),
        "min_on_beam": min(r["on_beam_0.1deg"] for r in rows),
    }


def synthetic(seeds: int, repeats: int) -> dict:
    rows = []
    for seed in range(1000, 1000 + seeds):
        config = LidarConfig(azimuth_step_deg=STEPS_DEG[seed % len(STEPS_DEG)])
        rng = frame_rng(seed, 0)
        sweep = scan(generate_world(rng, None, mount_height=config.mount_height), rng, config)
        step = 2 * math.pi / config.num_columns
        truth = config.sensor(sweep.grid.azimuth[0] + math.pi - 0.5 * step)
        shuffled = sweep.points[np.random.default_rng(seed).permutation(len(sweep.points))]
        for order, points in (("scan", sweep.points), ("shuffled", shuffled)):
            sensor, ms = _timed(points, repeats)
            same = sensor.num_beams == truth.num_beams
            beam, column, _ = sensor.cells(sweep.points)
            want_beam, want_column, _ = truth.cells(sweep.points)
            error = np.abs(sensor.elevations - truth.elevations).max() if same else math.inf
            rows.append(
                {
                    "seed": seed,
                    "order": order,
                    "step_deg": config.azimuth_step_deg,
                    "beams": sensor.num_beams,
                    "max_elevation_error_deg": float(np.degrees(error)),
                    "step_error_deg": abs(math.degrees(sensor.azimuth_step - truth.azimuth_step)),
                    "cells_exact": bool(
                        np.array_equal(beam, want_beam) and np.array_equal(column, want_column)
                    ),
                    "ms": round(ms, 2),
                }
            )
            print(json.dumps(rows[-1]))
    return {
        "frames": len(rows),
        "max_elevation_error_deg": max(r["max_elevation_error_deg"] for r in rows),
        "all_64_beams": all(r["beams"] == 64 for r in rows),
        "all_cells_exact": all(r["cells_exact"] for r in rows),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=11, help="timed estimates per frame")
    parser.add_argument("--seeds", type=int, default=4, help="synthetic worlds")
    args = parser.parse_args()
    summary = {"kitti": kitti(args.repeats), "synthetic": synthetic(args.seeds, args.repeats)}
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
