"""Time input validation against augmentation, per frame, side by side.

Every transform call runs :func:`drcpo.frame.validate_frame` once on its input (a pipeline
once in all). This prints, per frame, the microseconds of that check (median of many runs) and
the milliseconds of one augmentation by the baseline (CDA) and the DR.CPO pipeline (median of
``--repeats``), on the frames and quick database of ``bench_augment.py`` (the KITTI sample cut
to the camera's view when present, else the built-in synthetic world).

Usage: ``python benchmarks/bench_validation.py [--frames 6] [--repeats 5] [--work DIR]``
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_augment import (
    KITTI_SAMPLE,
    QUICK_COUNTS,
    database_and_index,
    kitti_frames,
    synthetic_frames,
)

from drcpo.frame import validate_frame
from drcpo.pipeline import build_pipeline


def median_seconds(call, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--work", type=Path, help="keep the database and index here")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_validation_") as scratch:
        work = args.work or Path(scratch)
        work.mkdir(parents=True, exist_ok=True)
        database, index, _ = database_and_index(QUICK_COUNTS, 20, work)
        use_kitti = (KITTI_SAMPLE / "training" / "velodyne").is_dir()
        frames = kitti_frames(args.frames) if use_kitti else synthetic_frames(args.frames)
        cda = build_pipeline("default", database, index, kind="cda")
        drcpo = build_pipeline("default", database, index, kind="drcpo")
        for frame in frames:  # warm-up: compilation, first touches
            cda(frame, np.random.default_rng(0))
            drcpo(frame, np.random.default_rng(0))
        print(f"{'frame':>8} {'points':>7} {'validate us':>12} {'cda ms':>8} {'drcpo ms':>9}")
        shares = []
        for frame in frames:
            check = median_seconds(lambda f=frame: validate_frame(f), 200) * 1e6
            base = median_seconds(lambda f=frame: cda(f, np.random.default_rng(1)), args.repeats)
            full = median_seconds(lambda f=frame: drcpo(f, np.random.default_rng(1)), args.repeats)
            shares.append((check / 1e3 / (base * 1e3), check / 1e3 / (full * 1e3)))
            print(
                f"{frame.frame_id!s:>8} {len(frame):7d} {check:12.1f} {base * 1e3:8.2f} "
                f"{full * 1e3:9.2f}"
            )
        cda_share, drcpo_share = (statistics.median(s) * 100 for s in zip(*shares, strict=True))
        print(
            f"validation / augmentation (median): {cda_share:.2f} % of CDA, "
            f"{drcpo_share:.2f} % of DR.CPO ({'kitti_sample' if use_kitti else 'synthetic'})"
        )


if __name__ == "__main__":
    main()
