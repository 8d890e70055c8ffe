"""Time opening a ground-truth database with and without verification, side by side.

``GroundTruthDatabase.open`` verifies by default: one streaming pass over every array, the
manifest's SHA-256 recomputed and points/boxes checked for NaN/inf. This prints the seconds of
``open(verify=False)`` and ``open(verify=True)`` (best of ``--repeats``, files in the page
cache) for the database built from the KITTI sample (``../shared/data/kitti_sample``, when
present) and for a synthetic one of ``--points`` points (default 20 million, 320 MB).

Usage: ``python benchmarks/bench_verify.py [--points 20000000] [--repeats 3]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from drcpo.database import GroundTruthDatabase

KITTI_SAMPLE = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti_sample"


def synthetic_database(points: int, per_object: int = 200) -> GroundTruthDatabase:
    rng = np.random.default_rng(0)
    objects = max(1, points // per_object)
    offsets = np.linspace(0, points, objects + 1).astype(np.int64)
    xyz = rng.normal(size=(points, 4)).astype(np.float32)
    boxes = np.column_stack(
        [rng.normal(size=(objects, 3)), np.ones((objects, 3)), np.zeros(objects)]
    )
    names = np.array(["Car", "Pedestrian", "Cyclist"])[rng.integers(0, 3, objects)]
    return GroundTruthDatabase.from_arrays(xyz, offsets, names, boxes)


def best(call, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return min(times)


def report(name: str, path: Path, repeats: int) -> None:
    db = GroundTruthDatabase.open(path, verify=False)
    size = sum(f.stat().st_size for f in path.glob("*.npy")) / 1e6
    GroundTruthDatabase.open(path)  # into the page cache
    plain = best(lambda: GroundTruthDatabase.open(path, verify=False), repeats)
    checked = best(lambda: GroundTruthDatabase.open(path), repeats)
    print(
        f"{name:24s} {len(db):8d} objects {len(db.points):10d} points {size:8.1f} MB   "
        f"open {plain * 1e3:8.1f} ms   open+verify {checked * 1e3:8.1f} ms"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=20_000_000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_verify_") as scratch:
        if (KITTI_SAMPLE / "training" / "velodyne").is_dir():
            from drcpo.database.build import build_database

            build_database(KITTI_SAMPLE, "train", Path(scratch) / "kitti")
            report("KITTI sample", Path(scratch) / "kitti", args.repeats)
        else:
            print(f"(no KITTI sample at {KITTI_SAMPLE})", file=sys.stderr)
        synthetic_database(args.points).save(Path(scratch) / "synthetic")
        report("synthetic", Path(scratch) / "synthetic", args.repeats)


if __name__ == "__main__":
    main()
