"""Time the conventional baseline (CDA) and the full DR.CPO pipeline on the same frames.

CDA = ground-truth sampling + global augmentation; DR.CPO = ground-truth sampling + DR.CPO +
global augmentation with the ``paper`` preset (the paper's reference configuration). The
database is synthetic and KITTI-sized (Car 14,357, Pedestrian 2,207, Cyclist 734 objects, points
on the faces a sensor would see, inside their boxes as in a database cut with points_in_boxes),
indexed with K = 400. Frames are the real KITTI sample in
``../shared/data/kitti_sample`` cut to the camera's field of view, as OpenPCDet trains KITTI,
when present, else frames of the built-in synthetic world.

Each frame is augmented ``--repeats`` times by each pipeline, alternating, with the same seeds;
the medians of the per-frame milliseconds are reported. The last stdout line is one JSON object::

    {"cda_ms": a, "drcpo_ms": b, "ratio": b / a, "stages_ms": {stage: median ms}, ...}

With ``--processes N``, it also measures throughput the way a data loader's worker processes
see it: N forked processes each augment every frame 4 x ``--repeats`` times (after one untimed
pass), first with the baseline, then with DR.CPO; the JSON gains ``processes``,
``cda_frames_per_s`` and ``drcpo_frames_per_s`` (all processes together).

Usage: ``python benchmarks/bench_augment.py [--quick] [--work DIR] [--processes N]``
(``--work`` keeps the database and its index between runs).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from drcpo.database import GroundTruthDatabase, ObjectRecord
from drcpo.frame import Frame
from drcpo.index import IndexConfig, load_index
from drcpo.index_build import build_index
from drcpo.pipeline import build_pipeline

KITTI_SAMPLE = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti_sample"
KITTI_COUNTS = {"Car": 14357, "Pedestrian": 2207, "Cyclist": 734}
QUICK_COUNTS = {"Car": 600, "Pedestrian": 150, "Cyclist": 80}
# Mean size (l, w, h) and the spread of each class (KITTI statistics, rounded).
SIZES = {"Car": (3.9, 1.6, 1.56), "Pedestrian": (0.8, 0.6, 1.73), "Cyclist": (1.76, 0.6, 1.73)}
SENSOR_HEIGHT = 1.73


def synthetic_object(rng: np.random.Generator, name: str) -> ObjectRecord:
    """One object: points on the faces of its box that a sensor at a random distance sees.

    Points per object are log-normal (median about 150, clipped to [5, 3000]), like KITTI's.
    """
    dims = np.asarray(SIZES[name]) * rng.normal(1.0, 0.08, 3).clip(0.75, 1.3)
    distance = rng.uniform(5.0, 60.0)
    azimuth = rng.uniform(-np.pi, np.pi)  # direction of the sensor in the object's frame
    count = int(np.clip(rng.lognormal(np.log(150.0), 0.9), 5, 3000))
    toward = np.array([np.cos(azimuth), np.sin(azimuth)])
    # Faces seen: the two side faces facing the sensor (weighted by how squarely) and the top.
    weights = np.array(
        [max(toward[0], 0), max(-toward[0], 0), max(toward[1], 0), max(-toward[1], 0), 0.15]
    )
    face = rng.choice(5, size=count, p=weights / weights.sum())
    local = rng.uniform(-0.5, 0.5, (count, 3))
    axis = np.array([0, 0, 1, 1, 2])[face]
    sign = np.array([0.5, -0.5, 0.5, -0.5, 0.5])[face]
    local[np.arange(count), axis] = sign
    # Range noise of a few cm, inward on the seen face: a database cut with points_in_boxes
    # (OpenPCDet's and drcpo's) holds only the points inside each box.
    noise = rng.normal(0.0, 0.02, (count, 3))
    noise[np.arange(count), axis] = -np.sign(sign) * np.abs(noise[np.arange(count), axis])
    xyz = np.clip(local * dims + noise, -dims / 2, dims / 2)
    intensity = rng.uniform(0.0, 1.0, count)
    box = np.array(
        [
            distance * np.cos(azimuth),
            distance * np.sin(azimuth),
            -SENSOR_HEIGHT + dims[2] / 2,
            *dims,
            rng.uniform(-np.pi, np.pi),
        ]
    )
    points = np.column_stack([xyz, intensity]).astype(np.float32)
    difficulty = int(rng.integers(0, 3))
    return ObjectRecord(points, name, box, frame_id="synthetic", difficulty=difficulty)


def database_and_index(counts: dict[str, int], k: int, work: Path, seed: int = 0):
    """The synthetic database and its index under ``work`` (built once, then reused)."""
    db_dir = work / f"db_{'_'.join(f'{n}{c}' for n, c in counts.items())}_k{k}_inside"
    if (db_dir / "index" / "manifest.json").is_file():
        database = GroundTruthDatabase.open(db_dir)
        return database, load_index(database), 0.0
    rng = np.random.default_rng(seed)
    records = [synthetic_object(rng, name) for name, n in counts.items() for _ in range(n)]
    database = GroundTruthDatabase.from_records(records)
    database.save(db_dir, overwrite=True)
    database = GroundTruthDatabase.open(db_dir)
    start = time.perf_counter()
    index = build_index(database, IndexConfig(k=k))
    seconds = time.perf_counter() - start
    index.save(db_dir, overwrite=True)
    return database, load_index(database), seconds


def kitti_frames(limit: int) -> list[Frame]:
    from drcpo.datasets.kitti import KittiDataset
    from drcpo.datasets.kitti_coordinates import fov_mask

    dataset = KittiDataset(KITTI_SAMPLE, "train")
    frames = []
    for frame_id in dataset.frame_ids[:limit]:
        frame = dataset.frame(frame_id)
        keep = fov_mask(frame.points, frame.metadata["calib"], dataset.image_shape(frame_id))
        frames.append(
            frame.replace(points=frame.points[keep], metadata={**frame.metadata, "fov_only": True})
        )
    return frames


def synthetic_frames(limit: int, seed: int = 0) -> list[Frame]:
    from drcpo.datasets.kitti_coordinates import fov_mask
    from drcpo.datasets.kitti_writer import reference_calibration
    from drcpo.synth import frame_rng, synthesize_frame

    calib = reference_calibration()
    frames = []
    for i in range(limit):
        made = synthesize_frame(frame_rng(seed, i), calib=calib)
        points = np.asarray(made.sweep.points, dtype=np.float32)
        keep = fov_mask(points, calib)
        metadata = {"frame_id": f"synth{i:03d}", "calib": calib, "fov_only": True}
        frames.append(Frame(points[keep], made.boxes, made.names, metadata))
    return frames


def time_call(transform, frame: Frame, seed: int) -> tuple[float, float, dict]:
    """Wall and CPU milliseconds of one call (CPU time is the steadier figure on a shared
    machine), and its statistics."""
    start, cpu = time.perf_counter(), time.process_time()
    out = transform(frame, np.random.default_rng(seed))
    wall = (time.perf_counter() - start) * 1000.0
    return wall, (time.process_time() - cpu) * 1000.0, out.metadata["augment_stats"]


def _throughput_worker(transform, frames, worker, repeats, ready, done) -> None:
    """One forked process of :func:`frames_per_second`: an untimed pass (first touches of
    memory in a new process), then, once every process is ready, the timed ones."""
    try:
        for f, frame in enumerate(frames):
            transform(frame, np.random.default_rng([worker, repeats, f]))
    except BaseException:
        ready.abort()  # the parent stops waiting at once
        raise
    ready.wait()
    for r in range(repeats):
        for f, frame in enumerate(frames):
            transform(frame, np.random.default_rng([worker, r, f]))
    done.put(repeats * len(frames))


def frames_per_second(transform, frames: list[Frame], repeats: int, processes: int) -> float:
    """Frames per second of ``processes`` forked processes that each augment every frame
    ``repeats`` times, all started together."""
    if "fork" not in multiprocessing.get_all_start_methods():
        raise SystemExit("--processes needs the fork start method (Linux or macOS)")
    context = multiprocessing.get_context("fork")
    ready, done = context.Barrier(processes + 1, timeout=600), context.Queue()
    workers = [
        context.Process(
            target=_throughput_worker, args=(transform, frames, w, repeats, ready, done)
        )
        for w in range(processes)
    ]
    for worker in workers:
        worker.start()
    try:
        try:
            ready.wait()
        except threading.BrokenBarrierError:
            raise SystemExit("a throughput process failed before starting") from None
        start = time.perf_counter()
        count = sum(done.get(timeout=3600) for _ in workers)
        elapsed = time.perf_counter() - start
    finally:
        for worker in workers:
            worker.join(timeout=10)
            if worker.is_alive():
                worker.terminate()
    if any(worker.exitcode for worker in workers):
        raise SystemExit(
            f"a throughput process failed (exit codes {[w.exitcode for w in workers]})"
        )
    return count / elapsed


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small database, 2 frames")
    parser.add_argument("--work", type=Path, help="keep the database and index here")
    parser.add_argument("--frames", type=int, help="frames to use (default 6, quick 2)")
    parser.add_argument("--repeats", type=int, help="runs per frame and pipeline (default 5)")
    parser.add_argument("--source", choices=("auto", "kitti", "synth"), default="auto")
    parser.add_argument(
        "--processes", type=int, default=0, help="also measure throughput of N forked processes"
    )
    args = parser.parse_args(argv)
    if args.processes < 0:
        parser.error("--processes must be 0 (no throughput run) or more")
    counts = QUICK_COUNTS if args.quick else KITTI_COUNTS
    k = 100 if args.quick else 400
    n_frames = args.frames or (2 if args.quick else 6)
    repeats = args.repeats or (2 if args.quick else 5)

    with tempfile.TemporaryDirectory(prefix="bench_augment_") as scratch:
        work = args.work or Path(scratch)
        work.mkdir(parents=True, exist_ok=True)
        database, index, index_s = database_and_index(counts, k, work)
        use_kitti = args.source == "kitti" or (
            args.source == "auto" and (KITTI_SAMPLE / "training" / "velodyne").is_dir()
        )
        frames = kitti_frames(n_frames) if use_kitti else synthetic_frames(n_frames)
        cda = build_pipeline("default", database, index, kind="cda")
        drcpo = build_pipeline("paper", database, index, kind="drcpo")
        pipelines = {"cda": cda, "drcpo": drcpo}
        # Warm-up, every frame through every pipeline: numba compilation, first touch of the
        # memory-mapped database and of each frame's data.
        for f, frame in enumerate(frames):
            for pipeline in pipelines.values():
                time_call(pipeline, frame, 900_000 + f)
        wall = {name: [] for name in pipelines}
        cpu = {name: [] for name in pipelines}
        stages = {name: {} for name in pipelines}
        added = {name: {} for name in pipelines}
        for f, frame in enumerate(frames):
            for r in range(repeats):
                seed = 1000 * f + r
                for name, pipeline in pipelines.items():  # alternating, the same seeds
                    elapsed, used, stats = time_call(pipeline, frame, seed)
                    wall[name].append(elapsed)
                    cpu[name].append(used)
                    for stage, record in stats["stages"].items():
                        stages[name].setdefault(stage, []).append(record["ms"])
                    for cls, counts in stats["objects"].get("drcpo", {}).items():
                        added[name].setdefault(cls, []).append(counts["added"])
        cda_ms, drcpo_ms = wall["cda"], wall["drcpo"]
        throughput = {}
        if args.processes:
            throughput = {
                "processes": args.processes,
                "cda_frames_per_s": frames_per_second(cda, frames, 4 * repeats, args.processes),
                "drcpo_frames_per_s": frames_per_second(drcpo, frames, 4 * repeats, args.processes),
            }
    result = {
        "cda_ms": statistics.median(cda_ms),
        "drcpo_ms": statistics.median(drcpo_ms),
    }
    result["ratio"] = result["drcpo_ms"] / result["cda_ms"]
    result["stages_ms"] = {name: statistics.median(v) for name, v in stages["drcpo"].items()}
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    result.update(
        cda_cpu_ms=statistics.median(cpu["cda"]),
        drcpo_cpu_ms=statistics.median(cpu["drcpo"]),
        load_average=load,
        frames=len(frames),
        source="kitti_sample" if use_kitti else "synthetic_world",
        points_per_frame=int(np.median([len(f) for f in frames])),
        runs_per_pipeline=len(drcpo_ms),
        database_objects=len(database),
        k=k,
        index_build_s=round(index_s, 1),
        drcpo_objects_added_mean=_added_per_frame(added["drcpo"]),
        added_per_class={
            name: {cls: float(np.mean(v)) for cls, v in per_class.items()}
            for name, per_class in added.items()
            if name != "cda"
        },
        **throughput,
    )
    print(
        f"{result['frames']} frames ({result['source']}, ~{result['points_per_frame']} points), "
        f"database {len(database)} objects, K={k}",
        file=sys.stderr,
    )
    print(" paper:", file=sys.stderr)
    for name, ms in result["stages_ms"].items():
        print(f"  {name:28s} {ms:8.2f} ms", file=sys.stderr)
    if throughput:
        print(
            f"{args.processes} processes: baseline {throughput['cda_frames_per_s']:.0f} frames/s, "
            f"DR.CPO pipeline {throughput['drcpo_frames_per_s']:.0f} frames/s",
            file=sys.stderr,
        )
    sys.stderr.flush()
    print(json.dumps(result), flush=True)
    return result


def _added_per_frame(per_class: dict[str, list[int]]) -> float:
    """Mean DR.CPO objects added per frame, all classes together."""
    if not per_class:
        return 0.0
    return float(np.mean(np.sum([np.asarray(v) for v in per_class.values()], axis=0)))


if __name__ == "__main__":
    main()
