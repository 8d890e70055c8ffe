"""``drcpo augment`` in one process against a local Ray cluster of N workers, in one run.

Data: the built-in synthetic world (``drcpo synth``: a ray-cast HDL-64E in procedural streets),
its ground-truth database and index, built once under ``--work``. Each side runs in its own
process (so peak RSS is its own) on the same frames, config and seed:

* **one process**: open the database, build the pipeline, warm its kernels
  (:func:`drcpo.warmup.warmup`; ``startup_s``), then
  :func:`~drcpo.datasets.export.augment_kitti` (``augment_s``).
* **cluster**: :func:`~drcpo.distributed.augment_kitti_cluster` on a local cluster started by
  the call; ``startup_s`` is starting the cluster and its actors up to all of them warmed,
  ``augment_s`` from then to the last frame written (``total_s`` adds the shut-down). Peak
  RSS per worker (actor) as each reports it, and the driver's.

Both sides run with one BLAS thread (``OMP_NUM_THREADS=1``, ``OPENBLAS_NUM_THREADS=1``), as
Ray gives its workers. ``frames_per_s`` is frames / ``augment_s``. The two output trees are
compared file by file (``timings.jsonl`` left out: the only file that holds timings). The
machine's load (``uptime``) is printed before and after: on a shared machine it moves the
figures.

Usage: ``python benchmarks/bench_cluster.py [--frames 48] [--workers 2] [--work DIR] [--quick]``;
needs ``pip install -e ".[ray]"``. The last stdout line is one JSON object ``{"one": {...},
"cluster": {...}, "identical": bool, "speedup": x, ...}``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from drcpo.distributed.cluster import peak_rss_mb

TIMINGS_FILE = "timings.jsonl"


def prepare(work: Path, frames: int) -> tuple[Path, Path]:
    """The synthetic KITTI root (all frames in split train) and its database with index."""
    from drcpo.database.build import build_database
    from drcpo.index_build import build_index
    from drcpo.synth import write_synthetic_kitti

    kitti, db = work / "kitti", work / "db"
    marker = work / "prepared.json"
    if marker.is_file() and json.loads(marker.read_text()) == {"frames": frames}:
        return kitti, db
    write_synthetic_kitti(kitti, frames, seed=0, val_fraction=0.0, overwrite=True)
    database = build_database(kitti, "train", db, overwrite=True)
    build_index(database).save(db, overwrite=True)
    marker.write_text(json.dumps({"frames": frames}))
    return kitti, db


def run_side(side: str, kitti: Path, db: Path, out: Path, config: str, workers: int) -> dict:
    """One side, in this process (called through ``--side``)."""
    from drcpo.database import GroundTruthDatabase
    from drcpo.pipeline import build_pipeline

    start = time.perf_counter()
    transform = build_pipeline(config, GroundTruthDatabase.open(db))
    if side == "one":
        from drcpo.datasets.export import augment_kitti
        from drcpo.warmup import warmup

        warmup(transform)
        startup = time.perf_counter() - start
        summary = augment_kitti(kitti, "train", transform, out, seed=0)
        frames_s = time.perf_counter() - start - startup  # staging and assembly included
        workers_info: list[dict[str, Any]] = []
    else:
        from drcpo.distributed import augment_kitti_cluster

        begin = time.perf_counter()
        summary = augment_kitti_cluster(
            kitti, "train", transform, out, seed=0, cluster="local", workers=workers
        )
        startup = (begin - start) + summary["cluster"]["startup_s"]
        frames_s = summary["cluster"]["frames_s"]
        workers_info = summary["cluster"]["workers"]
    total = time.perf_counter() - start
    return {
        "frames": summary["frames"],
        "startup_s": round(startup, 2),
        "augment_s": round(frames_s, 2),
        "total_s": round(total, 2),
        "frames_per_s": round(summary["frames"] / frames_s, 2),
        "median_ms_per_frame": round(summary["median_ms"], 1),
        "peak_rss_mb": round(peak_rss_mb(), 1),
        "workers": [
            {k: round(v, 2) if isinstance(v, float) else v for k, v in w.items()}
            for w in workers_info
        ],
    }


def tree(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != TIMINGS_FILE
    }


def uptime() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "unknown"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=48, help="synthetic frames to augment")
    parser.add_argument("--workers", type=int, default=2, help="cluster workers (actors)")
    parser.add_argument("--config", default="default", help="pipeline config or preset")
    parser.add_argument("--work", type=Path, default=None, help="keep the data here")
    parser.add_argument("--quick", action="store_true", help="8 frames")
    parser.add_argument("--side", choices=["one", "cluster"], help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="drcpo_cluster_"))
    frames = 8 if args.quick else args.frames
    if args.side:  # a child: one side, its result as the last line
        kitti, db = work / "kitti", work / "db"
        out = work / f"out-{args.side}"
        result = run_side(args.side, kitti, db, out, args.config, args.workers)
        print(json.dumps(result))
        return result
    load_before = uptime()
    kitti, db = prepare(work, frames)
    sides = {}
    # One BLAS thread on both sides, as Ray gives its workers (OMP_NUM_THREADS=1): a threaded
    # BLAS spins on the other core after each product (docs/augmentation.md, on threads).
    threads = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", **threads}
    for side in ("one", "cluster"):
        out = work / f"out-{side}"
        shutil.rmtree(out, ignore_errors=True)
        command = [sys.executable, __file__, "--side", side, "--work", str(work)]
        command += ["--workers", str(args.workers), "--config", args.config]
        done = subprocess.run(command, env=env, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            sys.exit(f"{side} failed:\n{done.stderr[-3000:]}")
        sides[side] = json.loads(done.stdout.strip().splitlines()[-1])
    identical = tree(work / "out-one") == tree(work / "out-cluster")
    one, spread = sides["one"], sides["cluster"]
    rows = [
        ("frames", one["frames"], spread["frames"]),
        ("start-up s", one["startup_s"], spread["startup_s"]),
        ("augment s", one["augment_s"], spread["augment_s"]),
        ("total s (with start-up, shut-down)", one["total_s"], spread["total_s"]),
        ("frames/s", one["frames_per_s"], spread["frames_per_s"]),
        ("median ms per frame", one["median_ms_per_frame"], spread["median_ms_per_frame"]),
        ("peak RSS MB (process / driver)", one["peak_rss_mb"], spread["peak_rss_mb"]),
    ]
    for i, w in enumerate(spread["workers"]):
        rows.append((f"peak RSS MB worker {i}", "", w["peak_rss_mb"]))
    print(f"{'':32s} {'one process':>12s} {f'{args.workers} workers':>12s}")
    for name, a, b in rows:
        print(f"{name:32s} {a!s:>12s} {b!s:>12s}")
    print(f"outputs identical: {identical}; load average before {load_before}, after {uptime()}")
    result = {
        "one": one,
        "cluster": spread,
        "identical": identical,
        "speedup": round(spread["frames_per_s"] / one["frames_per_s"], 2),
        "config": args.config,
        "cpus": os.cpu_count(),
        "load_before": load_before,
        "load_after": uptime(),
    }
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
