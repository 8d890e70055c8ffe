"""Candidate-index build time and peak memory at KITTI and Waymo scale, and approximate recall.

Synthetic databases (sizes drawn around each class's typical box, points spread over the box
with a visible side, as real LiDAR objects have):

* **KITTI size**: Car 14,357, Pedestrian 2,207, Cyclist 734 objects, 100-1,000 points each,
  sizes rounded to 1 cm as in KITTI labels.
* **Waymo size**: 1,000,000 Car objects (8% trucks and buses), continuous sizes, 16-64 points
  each. Fewer points than real Waymo objects keep the database at 0.6 GB; points only enter
  the density count, which is linear in the number of points and measured at KITTI size.

Each build runs in its own process (so peak RSS is the build's own): open the saved database
(memory-mapped), ``build_index`` with the default configuration on all cores, save the index.
``waymo_s`` / ``waymo_peak_rss_mb`` are that, for the exact search (the default at every size).

``approx_recall``: on a sample of the Waymo-size class, the share of each object's exact top-2K
(by the exact grid search, itself checked against brute force on a sub-sample) that the
approximate mode (L1 nearest neighbours in log-size space, re-ranked by IoU) finds. Its time
per object and the exact search's, on the same sample, are printed next to it.

Usage: ``python benchmarks/bench_index.py [--quick]``; the last stdout line is
one JSON object ``{"kitti_s", "kitti_peak_rss_mb", "waymo_s", "waymo_peak_rss_mb",
"approx_recall", ...}``.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from drcpo.database import GroundTruthDatabase
from drcpo.geometry import canonical_iou3d
from drcpo.index import IndexConfig
from drcpo.index_build import build_index
from drcpo.similarity import SimilaritySearch, similarity_recall

KITTI = {"Car": 14_357, "Pedestrian": 2_207, "Cyclist": 734}
WAYMO = {"Car": 1_000_000}
# Typical KITTI box sizes (length, width, height) and their spread, metres.
SIZE_MEAN = {
    "Car": (3.89, 1.62, 1.53),
    "Pedestrian": (0.84, 0.66, 1.76),
    "Cyclist": (1.76, 0.6, 1.74),
}
SIZE_STD = {
    "Car": (0.43, 0.10, 0.14),
    "Pedestrian": (0.23, 0.14, 0.11),
    "Cyclist": (0.18, 0.12, 0.09),
}


def synthetic_sizes(rng: np.random.Generator, name: str, n: int, waymo: bool) -> np.ndarray:
    mean, std = np.array(SIZE_MEAN[name]), np.array(SIZE_STD[name])
    dims = rng.normal(mean, std, (n, 3))
    if waymo:
        big = rng.random(n) < 0.08  # trucks and buses
        dims[big] = rng.normal((9.0, 2.6, 3.2), (2.0, 0.2, 0.4), (int(big.sum()), 3))
    else:
        dims = np.round(dims, 2)
    return np.maximum(dims, 0.2)


def synthetic_database(counts: dict[str, int], points: tuple[int, int], seed: int, waymo: bool):
    """Objects in canonical pose; most points on one randomly chosen side and the top."""
    rng = np.random.default_rng(seed)
    names = np.concatenate([np.full(n, name) for name, n in counts.items()])
    dims = np.concatenate([synthetic_sizes(rng, name, n, waymo) for name, n in counts.items()])
    n = len(names)
    sizes = rng.integers(points[0], points[1] + 1, n)
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    xyz = np.empty((int(offsets[-1]), 4), np.float32)
    side = rng.choice([-1.0, 1.0], n)
    step = 1 << 22
    for start in range(0, n, step // max(points[1], 1)):
        stop = min(n, start + step // max(points[1], 1))
        owner = np.repeat(np.arange(start, stop), sizes[start:stop])
        local = rng.uniform(-0.5, 0.5, (len(owner), 3))
        seen = rng.random(len(owner)) < 0.8
        local[seen, 1] = side[owner[seen]] * np.abs(local[seen, 1])
        local[:, 2] = 0.5 - np.abs(local[:, 2]) ** 1.5 * 0.9  # denser near the top
        chunk = slice(offsets[start], offsets[stop])
        xyz[chunk, :3] = local * dims[owner]
        xyz[chunk, 3] = rng.random(len(owner))
    boxes = np.column_stack([rng.uniform(0, 60, (n, 3)), dims, rng.uniform(-3, 3, n)])
    difficulty = rng.integers(0, 3, n).astype(np.int8)
    return GroundTruthDatabase.from_arrays(xyz, offsets, names, boxes, difficulty=difficulty)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# Child steps ----------------------------------------------------------------------------------
def step_make(args) -> dict:
    counts, points, waymo = scale(args)
    start = time.perf_counter()
    database = synthetic_database(counts, points, seed=0, waymo=waymo)
    database.save(args.dir, overwrite=True)
    return {
        "objects": len(database),
        "points": len(database.points),
        "make_s": time.perf_counter() - start,
    }


def step_index(args) -> dict:
    database = GroundTruthDatabase.open(args.dir)
    database.checksum  # noqa: B018 - read from the manifest, not timed as indexing
    start = time.perf_counter()
    index = build_index(database, IndexConfig())
    index.save(args.dir, overwrite=True)
    seconds = time.perf_counter() - start
    return {"seconds": seconds, "peak_rss_mb": peak_rss_mb(), "classes": index.classes}


def step_recall(args) -> dict:
    database = GroundTruthDatabase.open(args.dir)
    rows = database.rows_of_class("Car")
    dims = np.asarray(database.boxes[rows, 3:6])
    s = 2 * IndexConfig().k
    rng = np.random.default_rng(1)
    sample = np.sort(rng.choice(len(rows), min(args.sample, len(rows)), replace=False))
    exact = SimilaritySearch(dims, s)
    checked = sample[: args.brute]
    ids, _ = exact.top(checked)
    for q, got in zip(checked, ids, strict=True):  # the exact search against brute force
        iou = canonical_iou3d(dims[q], dims)
        iou[q] = -1.0
        # Everything at least as good as the s-th best IoU, then (IoU desc, row asc).
        near = np.flatnonzero(iou >= -np.partition(-iou, s - 1)[s - 1])
        want = near[np.lexsort((near, -iou[near]))][:s]
        if not np.array_equal(got, want):
            raise AssertionError(f"exact search differs from brute force for object {q}")
    timings = {}
    for mode in ("exact", "approximate"):
        search = SimilaritySearch(dims, s, mode=mode)
        search.top(sample[:8])
        start = time.perf_counter()
        for i in range(0, len(sample), 512):
            search.top(sample[i : i + 512])
        timings[mode] = (time.perf_counter() - start) / len(sample) * 1e6
    recall = similarity_recall(dims, s, sample)
    return {
        "recall": recall,
        "sample": len(sample),
        "brute_checked": len(checked),
        "exact_us_per_object": timings["exact"],
        "approx_us_per_object": timings["approximate"],
    }


def scale(args) -> tuple[dict[str, int], tuple[int, int], bool]:
    factor = 20 if args.quick else 1
    if args.part == "kitti":
        return {k: max(v // factor, 2) for k, v in KITTI.items()}, (100, 1000), False
    return {k: v // (50 if args.quick else 1) for k, v in WAYMO.items()}, (16, 64), True


# Driver ---------------------------------------------------------------------------------------
def child(step: str, part: str, work: Path, args) -> dict:
    command = [
        sys.executable,
        __file__,
        "--step",
        step,
        "--part",
        part,
        "--dir",
        str(work / part),
        "--sample",
        str(args.sample),
        "--brute",
        str(args.brute),
    ]
    if args.quick:
        command.append("--quick")
    done = subprocess.run(command, check=True, capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1/20 KITTI, 1/50 Waymo size")
    parser.add_argument("--sample", type=int, default=None, help="objects in the recall sample")
    parser.add_argument("--brute", type=int, default=None, help="of those, checked by brute force")
    parser.add_argument("--step", choices=("make", "index", "recall"), help=argparse.SUPPRESS)
    parser.add_argument("--part", choices=("kitti", "waymo"), help=argparse.SUPPRESS)
    parser.add_argument("--dir", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    args.sample = args.sample or (2_000 if args.quick else 20_000)
    args.brute = args.brute or (20 if args.quick else 200)
    if args.step:
        step = {"make": step_make, "index": step_index, "recall": step_recall}[args.step]
        print(json.dumps(step(args)))
        return

    result = {}
    with tempfile.TemporaryDirectory(prefix="drcpo-bench-index-") as tmp:
        work = Path(tmp)
        for part in ("kitti", "waymo"):
            made = child("make", part, work, args)
            print(
                f"{part}: {made['objects']:,} objects, {made['points']:,} points "
                f"(made in {made['make_s']:.1f} s)",
                flush=True,
            )
            built = child("index", part, work, args)
            for name, stats in built["classes"].items():
                print(
                    f"  {name:<11} {stats['indexed']:>9,} indexed  "
                    f"{stats['mean_candidates']:6.1f} candidates/object  ({stats['mode']})"
                )
            print(
                f"  index built in {built['seconds']:.1f} s, peak RSS "
                f"{built['peak_rss_mb']:.0f} MB",
                flush=True,
            )
            result[f"{part}_s"] = round(built["seconds"], 2)
            result[f"{part}_peak_rss_mb"] = round(built["peak_rss_mb"], 1)
        recall = child("recall", "waymo", work, args)
        print(
            f"approximate mode on {recall['sample']:,} Waymo-size objects: recall "
            f"{recall['recall']:.4f} of the exact top-2K; "
            f"{recall['approx_us_per_object']:.0f} us/object vs exact "
            f"{recall['exact_us_per_object']:.0f} us/object (one thread); exact search equal "
            f"to brute force on {recall['brute_checked']} objects"
        )
        result["approx_recall"] = round(recall["recall"], 5)
        result["approx_us_per_object"] = round(recall["approx_us_per_object"], 1)
        result["exact_us_per_object"] = round(recall["exact_us_per_object"], 1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
