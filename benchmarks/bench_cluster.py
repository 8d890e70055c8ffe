"""``drcpo augment`` in one process against N local worker processes and a local Ray cluster of
N workers, in one run.

Data: the built-in synthetic world (``drcpo synth``: a ray-cast HDL-64E in procedural streets),
its ground-truth database and index, built once under ``--work``. Each side runs in its own
process (so peak RSS is its own) on the same frames, config and seed:

* **one process**: open the database, build the pipeline, warm its kernels
  (:func:`drcpo.warmup.warmup`; ``startup_s``), then
  :func:`~drcpo.datasets.export.augment_kitti` (``augment_s``).
* **processes** (``drcpo augment --workers N``, no Ray):
  :func:`~drcpo.distributed.augment_kitti_processes`; ``startup_s`` is building the pipeline and
  spawning the N processes up to all of them warmed, ``augment_s`` the rest of the call
  (as for one process: staging, the frames, the assembly; and the processes' shut-down). Peak
  RSS of the driver and of the largest worker.
* **cluster**: :func:`~drcpo.distributed.augment_kitti_cluster` on a local cluster started by
  the call; ``startup_s`` is starting the cluster and its actors up to all of them warmed,
  ``augment_s`` from then to the last frame written (``total_s`` adds the shut-down). Peak
  RSS per worker (actor) as each reports it, and the driver's. Needs ``pip install -e ".[ray]"``.

All sides run with one BLAS thread (``OMP_NUM_THREADS=1``, ``OPENBLAS_NUM_THREADS=1``), as
Ray gives its workers. ``frames_per_s`` is frames / ``augment_s``; ``speedup`` a side's
``frames_per_s`` over one process's, ``speedup_with_startup`` the same with ``total_s`` (start-up
and shut-down paid once per run: what a short run gets). Each output tree is compared with one
process's file by file (``timings.jsonl`` left out: the only file that holds timings). The
machine's load (``uptime``) is printed before and after: on a shared machine it moves the
figures.

Usage: ``python benchmarks/bench_cluster.py [--frames 48] [--workers 2] [--sides one processes
cluster] [--work DIR] [--quick]`` (default sides: one and processes, and cluster where Ray is
installed). The last stdout line is one JSON object ``{"one": {...}, "processes": {...},
"cluster": {...}, "compared": side, "identical": bool, "speedup": x, "speedup_with_startup": x,
...}``: each side's figures (with its own ``identical`` and speedups), and at the top level those
of ``compared`` (processes when it ran, else cluster) with ``identical`` over all sides.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from drcpo.distributed.cluster import peak_rss_mb

TIMINGS_FILE = "timings.jsonl"
SIDES = ("one", "processes", "cluster")
LABELS = {"one": "one process", "processes": "processes", "cluster": "cluster"}


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
    workers_info: list[dict[str, Any]] = []
    if side == "one":
        from drcpo.datasets.export import augment_kitti
        from drcpo.warmup import warmup

        warmup(transform)
        startup = time.perf_counter() - start
        summary = augment_kitti(kitti, "train", transform, out, seed=0)
        frames_s = time.perf_counter() - start - startup  # staging and assembly included
    elif side == "processes":
        from drcpo.distributed import augment_kitti_processes

        begin = time.perf_counter()
        summary = augment_kitti_processes(kitti, "train", transform, out, seed=0, workers=workers)
        spawn = summary["processes"]["startup_s"]
        startup = (begin - start) + spawn
        frames_s = time.perf_counter() - begin - spawn  # as for one: staging, assembly included
        # their memory at start-up only: the peak over the run is peak_rss_mb_worker_max
        workers_info = [
            {k: v for k, v in w.items() if k != "peak_rss_mb"}
            for w in summary["processes"]["workers"]
        ]
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
    result = {
        "frames": summary["frames"],
        "startup_s": round(startup, 2),
        "augment_s": round(frames_s, 2),
        "total_s": round(total, 2),
        "frames_per_s": round(summary["frames"] / frames_s, 2),
        "frames_per_s_with_startup": round(summary["frames"] / total, 2),
        "median_ms_per_frame": round(summary["median_ms"], 1),
        "peak_rss_mb": round(peak_rss_mb(), 1),
        "workers": [
            {k: round(v, 2) if isinstance(v, float) else v for k, v in w.items()}
            for w in workers_info
        ],
    }
    if side == "processes":  # the workers have ended: the largest one's peak, as this OS keeps it
        children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        result["peak_rss_mb_worker_max"] = round(
            children / (1 << 20 if sys.platform == "darwin" else 1024), 1
        )
    return result


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
    parser.add_argument(
        "--workers", type=int, default=2, help="worker processes, and cluster workers (actors)"
    )
    parser.add_argument(
        "--sides",
        nargs="+",
        choices=SIDES,
        default=None,
        help="sides to run (one process always runs: the others are compared with it); "
        "default: one and processes, and cluster where Ray is installed",
    )
    parser.add_argument("--config", default="default", help="pipeline config or preset")
    parser.add_argument("--work", type=Path, default=None, help="keep the data here")
    parser.add_argument("--quick", action="store_true", help="8 frames")
    parser.add_argument("--side", choices=SIDES, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="drcpo_cluster_"))
    frames = 8 if args.quick else args.frames
    if args.side:  # a child: one side, its result as the last line
        kitti, db = work / "kitti", work / "db"
        out = work / f"out-{args.side}"
        result = run_side(args.side, kitti, db, out, args.config, args.workers)
        print(json.dumps(result))
        return result
    chosen = args.sides or ["one", "processes"] + ["cluster"] * has_ray()
    order = [side for side in SIDES if side == "one" or side in chosen]
    load_before = uptime()
    kitti, db = prepare(work, frames)
    sides = {}
    # One BLAS thread on every side, as Ray gives its workers (OMP_NUM_THREADS=1): a threaded
    # BLAS spins on the other core after each product (docs/augmentation.md, on threads).
    threads = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", **threads}
    for side in order:
        out = work / f"out-{side}"
        shutil.rmtree(out, ignore_errors=True)
        command = [sys.executable, __file__, "--side", side, "--work", str(work)]
        command += ["--workers", str(args.workers), "--config", args.config]
        done = subprocess.run(command, env=env, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            sys.exit(f"{side} failed:\n{done.stderr[-3000:]}")
        sides[side] = json.loads(done.stdout.strip().splitlines()[-1])
    one = sides["one"]
    reference = tree(work / "out-one")
    for side in order[1:]:
        figures = sides[side]
        figures["identical"] = tree(work / f"out-{side}") == reference
        figures["speedup"] = round(figures["frames_per_s"] / one["frames_per_s"], 2)
        figures["speedup_with_startup"] = round(one["total_s"] / figures["total_s"], 2)
    rows = [
        ("frames", "frames"),
        ("start-up s", "startup_s"),
        ("augment s", "augment_s"),
        ("total s (with start-up, shut-down)", "total_s"),
        ("frames/s", "frames_per_s"),
        ("frames/s with start-up", "frames_per_s_with_startup"),
        ("speedup over one process", "speedup"),
        ("speedup with start-up", "speedup_with_startup"),
        ("median ms per frame", "median_ms_per_frame"),
        ("peak RSS MB (process / driver)", "peak_rss_mb"),
        ("peak RSS MB largest worker", "peak_rss_mb_worker_max"),
        ("outputs identical to one process", "identical"),
    ]
    heads = [LABELS[side] if side == "one" else f"{args.workers} {LABELS[side]}" for side in order]
    print(f"{'':36s}" + "".join(f" {h:>13s}" for h in heads))
    for name, key in rows:
        print(f"{name:36s}" + "".join(f" {sides[side].get(key, '')!s:>13s}" for side in order))
    for side in order[1:]:
        for i, w in enumerate(sides[side]["workers"]):
            cells = {k: w[k] for k in ("startup_s", "warmup_s", "peak_rss_mb") if k in w}
            print(f"{side} worker {i}: {cells}")
    if "cluster" not in order:
        print("cluster side not run" + ("" if has_ray() else " (Ray is not installed)"))
    load_after = uptime()
    print(f"load average before {load_before}, after {load_after} ({os.cpu_count()} CPUs)")
    compared = next((side for side in ("processes", "cluster") if side in sides), None)
    result: dict[str, Any] = {
        **sides,
        "compared": compared,
        "identical": all(sides[side]["identical"] for side in order[1:]),
        "speedup": sides[compared]["speedup"] if compared else None,
        "speedup_with_startup": sides[compared]["speedup_with_startup"] if compared else None,
        "workers": args.workers,
        "config": args.config,
        "cpus": os.cpu_count(),
        "load_before": load_before,
        "load_after": load_after,
    }
    print(json.dumps(result))
    return result


def has_ray() -> bool:
    return importlib.util.find_spec("ray") is not None


if __name__ == "__main__":
    main()
