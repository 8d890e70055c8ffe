"""Does the augmentation help a detector? The data-efficiency grid on the synthetic world.

A small CenterPoint-style BEV detector (``benchmarks/detection/``, torch on CPU: install with
``pip install -e ".[detection]"``) is trained on subsets of a synthetic training pool with each
augmentation arm and several seeds, and evaluated on held-out frames of other worlds (other
seeds) with drcpo's KITTI evaluator (moderate AP_R40 at KITTI's strict overlaps: Car 0.7,
Pedestrian and Cyclist 0.5; 3D and BEV).

Data, made as a user would: ``write_synthetic_kitti`` (the KITTI layout ``drcpo synth`` writes)
with streets up to ``--street-angle`` degrees from the sensor axis for both the training pool and
the validation set; per training subset (the first N frames of the pool, nested), a ground-truth
database (``drcpo.database.build.build_database``) and candidate index
(``drcpo.index.build_index``) built from exactly that subset. Frames are cut to the camera's
field of view, as OpenPCDet trains KITTI.

Arms: ``none`` (no augmentation), ``cda`` (the conventional augmentation: ground-truth sampling
and global flip, rotation, scaling), ``paper`` (DR.CPO with the paper's configuration, drcpo's
``default`` config), or any other name: DR.CPO with the drcpo preset or YAML config of that name
(``--arms none cda paper realistic`` once a ``realistic`` preset exists).

Runs (subset x arm x seed) go to ``--workers`` processes, each pinned to one core with one torch
thread. Seed ``s`` fixes the model's initialisation, the order of the frames and each sample's
augmentation generator ``default_rng([s, epoch, index])``, so arms are compared in pairs.

Printed: per subset and arm, mean and spread (sample standard deviation) over seeds of the
moderate AP; paired differences per seed against ``cda`` and ``none``; the objects each arm adds
per frame; the heading error of matched detections; the time of each step. Writes
``OUT/detection.png`` (AP against training frames per arm, with the spread) and
``OUT/detection.json``. The last stdout line is one JSON object.

Usage: ``python benchmarks/bench_detection.py [--quick] [--work DIR] [--out DIR] [--steps N]
[--frames N] [--val-frames N] [--fractions 0.1 0.25 ...] [--arms none cda paper ...]
[--seeds N] [--workers N] [--street-angle DEG]``. ``--work`` keeps the synthetic data and
databases between runs. ``--quick`` (for CI) proves the loop end to end on a few frames and a
few steps; its AP means nothing.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import multiprocessing
import os
import shutil
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

TRAIN_SEED = 1000  # synthetic worlds of the training pool: frame i uses (TRAIN_SEED, i)
VAL_SEED = 2000  # validation worlds: other seeds, so no validation object is in a database
REFERENCE_ARMS = ("cda", "none")  # paired differences are taken against these


@dataclass(frozen=True)
class Plan:
    """What the grid runs: training pool and validation sizes, subsets (fractions of the pool),
    arms, seeds, optimiser steps per run, batch size, worker processes, street angle (deg)."""

    frames: int = 240
    val_frames: int = 300
    fractions: tuple[float, ...] = (0.1, 0.25, 0.5, 1.0)
    arms: tuple[str, ...] = ("none", "cda", "paper")
    seeds: tuple[int, ...] = (0, 1, 2)
    steps: int = 360
    batch_size: int = 4
    workers: int = 2
    street_angle: float = 45.0

    def subset_size(self, fraction: float) -> int:
        return max(1, round(fraction * self.frames))


QUICK = Plan(frames=12, val_frames=8, fractions=(0.5, 1.0), seeds=(0,), steps=3, batch_size=2)


# Data -----------------------------------------------------------------------------------------
def _cpu() -> float:
    """CPU seconds of this process and its finished children (timings on a shared machine)."""
    times = os.times()
    return times.user + times.system + times.children_user + times.children_system


def _synthesize(root: Path, frames: int, seed: int, street_angle: float) -> dict[str, Any]:
    """Write (or reuse, when its ``synth.json`` matches) a synthetic KITTI root of ``frames``
    frames, all in ``train``; returns the seconds it took (0 when reused)."""
    from drcpo.synth import LidarConfig, WorldConfig, write_synthetic_kitti
    from drcpo.synth.dataset import matches, synth_parameters

    world = WorldConfig().with_street_angle(street_angle)
    if matches(root, synth_parameters(frames, seed, world, LidarConfig(), 0.0)):
        return {"root": str(root), "seconds": 0.0, "reused": True}
    start = _cpu()
    write_synthetic_kitti(root, frames, seed, world, val_fraction=0.0, overwrite=True)
    return {"root": str(root), "seconds": _cpu() - start, "reused": False}


def prepare_data(work: Path, plan: Plan) -> dict[str, Any]:
    """Synthesise the training pool and the validation set (in parallel), write the subset
    splits, and build each subset's database (and index, when a DR.CPO arm runs). Timings
    (``*_s``) are CPU seconds."""
    from drcpo.database.build import build_database
    from drcpo.datasets.kitti import read_split
    from drcpo.datasets.kitti_writer import write_image_sets
    from drcpo.index import IndexConfig, build_index

    train_root, val_root = work / "train", work / "val"
    jobs = [
        (train_root, plan.frames, TRAIN_SEED, plan.street_angle),
        (val_root, plan.val_frames, VAL_SEED, plan.street_angle),
    ]
    context = multiprocessing.get_context("spawn")
    with context.Pool(min(2, plan.workers)) as pool:
        made = pool.starmap(_synthesize, jobs)
    timings: dict[str, Any] = {
        "synth_train_s": made[0]["seconds"],
        "synth_val_s": made[1]["seconds"],
    }
    if not made[0]["reused"]:
        shutil.rmtree(work / "db", ignore_errors=True)  # databases of an older pool
    write_image_sets(val_root, {"val": read_split(val_root, "train")})
    pool_ids = read_split(train_root, "train")
    needs_db = any(arm != "none" for arm in plan.arms)
    needs_index = any(arm not in ("none", "cda") for arm in plan.arms)
    subsets: dict[float, dict[str, Any]] = {}
    for fraction in plan.fractions:
        size = plan.subset_size(fraction)
        split = f"train_{size:04d}"
        write_image_sets(train_root, {split: pool_ids[:size]})
        entry = {"split": split, "frames": size, "db": None}
        db = work / "db" / split
        if needs_db:
            start = _cpu()
            if not (db / "manifest.json").is_file():
                build_database(train_root, split, db, workers=plan.workers, overwrite=True)
            entry["db_s"] = _cpu() - start
            entry["db"] = str(db)
        if needs_index and not (db / "index" / "manifest.json").is_file():
            from drcpo.database import GroundTruthDatabase

            start = _cpu()
            database = GroundTruthDatabase.open(db)
            build_index(database, IndexConfig(workers=plan.workers)).save(db, overwrite=True)
            entry["index_s"] = _cpu() - start
        subsets[fraction] = entry
    return {"train": str(train_root), "val": str(val_root), "subsets": subsets, **timings}


def make_augment(arm: str, db: str | None):
    """The augmentation callable of an arm (``None`` for ``none``)."""
    if arm == "none":
        return None
    from drcpo.database import GroundTruthDatabase
    from drcpo.pipeline import build_pipeline

    database = GroundTruthDatabase.open(db)
    if arm == "cda":
        return build_pipeline("default", database, kind="cda")
    config = "default" if arm == "paper" else arm
    return build_pipeline(config, database, kind="drcpo")


# Runs -----------------------------------------------------------------------------------------
_VAL_FRAMES: dict[str, Any] = {}


def _pin(cores) -> None:
    """Pool initializer: pin this worker to one core (DR.CPO then keeps to one thread too)."""
    core = cores.get()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {core})


def run_one(task: dict[str, Any]) -> dict[str, Any]:
    """Train one (subset, arm, seed) run, detect on the validation frames, score them."""
    from detection.scoring import heading_errors, kitti_ap, write_results
    from detection.train import TrainConfig, load_frames, predict, train

    wall = time.perf_counter()
    clock = [time.process_time()]

    def lap() -> float:
        clock.append(time.process_time())
        return clock[-1] - clock[-2]

    frames = load_frames(task["train"], task["split"])
    augment = make_augment(task["arm"], task["db"])
    config = TrainConfig(steps=task["steps"], batch_size=task["batch_size"], seed=task["seed"])
    setup = lap()
    result = train(frames, augment, config)
    trained = lap()
    if task["val"] not in _VAL_FRAMES:
        _VAL_FRAMES.clear()
        _VAL_FRAMES[task["val"]] = load_frames(task["val"], "val")
    val_frames = _VAL_FRAMES[task["val"]]
    detections = predict(result.model, val_frames)
    results_dir = Path(task["results"])
    lines = [d.kitti_lines(f) for d, f in zip(detections, val_frames, strict=True)]
    write_results(results_dir, [f.frame_id for f in val_frames], lines)
    predicted = lap()
    ap = kitti_ap(task["val"], "val", results_dir)
    evaluated = lap()
    samples = max(result.samples, 1)
    return {
        **{k: task[k] for k in ("arm", "fraction", "seed", "split")},
        "frames": len(frames),
        "ap": ap,
        "heading": heading_errors(val_frames, detections),
        "added_per_frame": {
            transform: {name: count / samples for name, count in per_class.items()}
            for transform, per_class in result.added.items()
        },
        "labels_per_frame": {name: count / samples for name, count in result.labels.items()},
        "final_loss": float(np.mean(result.losses[-20:])),
        "seconds": {  # CPU seconds of this single-threaded process, except wall
            "setup": setup,
            **{f"{k}_per_step": v / config.steps for k, v in result.seconds.items()},
            "train": trained,
            "predict": predicted,
            "evaluate": evaluated,
            "cpu": clock[-1] - clock[0],
            "wall": time.perf_counter() - wall,
        },
    }


def run_grid(work: Path, plan: Plan, data: dict[str, Any]) -> list[dict[str, Any]]:
    tasks = [
        {
            "train": data["train"],
            "val": data["val"],
            "split": data["subsets"][fraction]["split"],
            "db": data["subsets"][fraction]["db"],
            "arm": arm,
            "fraction": fraction,
            "seed": seed,
            "steps": plan.steps,
            "batch_size": plan.batch_size,
            "results": str(work / "results" / f"{arm}-{fraction:g}-{seed}"),
        }
        for seed in plan.seeds
        for fraction in plan.fractions
        for arm in plan.arms
    ]
    context = multiprocessing.get_context("spawn")
    cores = context.Queue()
    available = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else [0]
    for k in range(plan.workers):
        cores.put(available[k % len(available)])
    runs = []
    with context.Pool(plan.workers, initializer=_pin, initargs=(cores,)) as pool:
        for run in pool.imap_unordered(run_one, tasks):
            ap = run["ap"]
            print(
                f"  {run['arm']:>8} {run['frames']:4d} frames seed {run['seed']}: moderate AP_R40 "
                f"3D {ap['3d']['mean']:5.1f} BEV {ap['bev']['mean']:5.1f} "
                f"({run['seconds']['cpu']:.0f} CPU-s, {run['seconds']['wall']:.0f} s)",
                file=sys.stderr,
            )
            runs.append(run)
    return sorted(runs, key=lambda r: (r["fraction"], r["arm"], r["seed"]))


# Summary --------------------------------------------------------------------------------------
def _references(arm: str, arms: tuple[str, ...]) -> list[str]:
    """The reference arms ``arm`` is paired with (each pair of references once: cda - none)."""
    rank = {name: i for i, name in enumerate(REFERENCE_ARMS)}
    return [
        ref
        for ref in REFERENCE_ARMS
        if ref in arms and ref != arm and rank.get(arm, -1) < rank[ref]
    ]


def _difference(pairs: list[tuple[dict, dict]], metric: str, name: str) -> dict[str, Any]:
    """Paired AP differences (first minus second run of each seed): per seed, mean, spread,
    and how many seeds the first won."""
    from detection.scoring import mean_and_spread

    delta = [a["ap"][metric][name] - b["ap"][metric][name] for a, b in pairs]
    return {
        "per_seed": [round(d, 2) for d in delta],
        "wins": sum(d > 0 for d in delta),
        **mean_and_spread(delta),
    }


def summarise(runs: list[dict[str, Any]], plan: Plan) -> dict[str, Any]:
    """Mean and spread over seeds, paired differences, objects added, heading errors."""
    from detection.heads import CLASSES
    from detection.scoring import mean_and_spread

    names = (*CLASSES, "mean")
    by_key = {(r["arm"], r["fraction"], r["seed"]): r for r in runs}
    ap: dict[str, Any] = {}
    paired: dict[str, Any] = {}
    for arm in plan.arms:
        ap[arm] = {}
        for fraction in plan.fractions:
            seeds = [by_key[(arm, fraction, s)] for s in plan.seeds]
            ap[arm][str(seeds[0]["frames"])] = {
                metric: {n: mean_and_spread([r["ap"][metric][n] for r in seeds]) for n in names}
                for metric in ("3d", "bev")
            }
        for reference in _references(arm, plan.arms):
            rows = {}
            for fraction in plan.fractions:
                pairs = [
                    (by_key[(arm, fraction, s)], by_key[(reference, fraction, s)])
                    for s in plan.seeds
                ]
                rows[str(pairs[0][0]["frames"])] = {
                    metric: {n: _difference(pairs, metric, n) for n in names}
                    for metric in ("3d", "bev")
                }
            paired[f"{arm}-{reference}"] = rows
    added, heading, seconds = {}, {}, {}
    for arm in plan.arms:
        mine = [r for r in runs if r["arm"] == arm]
        totals: dict[str, dict[str, float]] = {}
        for r in mine:
            for transform, per_class in r["added_per_frame"].items():
                row = totals.setdefault(transform, {})
                for name, value in per_class.items():
                    row[name] = row.get(name, 0.0) + value / len(mine)
        added[arm] = {t: {n: round(v, 2) for n, v in row.items()} for t, row in totals.items()}
        heading[arm] = {}
        for name in CLASSES:
            values = [r["heading"][name]["mean_deg"] for r in mine if r["heading"][name]["matched"]]
            heading[arm][name] = round(float(np.mean(values)), 2) if values else None
        seconds[arm] = {
            key: round(float(np.mean([r["seconds"][key] for r in mine])), 4)
            for key in mine[0]["seconds"]
        }
    return {
        "ap": ap,
        "paired": paired,
        "added_per_frame": added,
        "heading_error_deg": heading,
        "seconds": seconds,
    }


def print_table(summary: dict[str, Any], plan: Plan) -> None:
    from detection.heads import CLASSES

    names = (*CLASSES, "mean")
    for metric in ("3d", "bev"):
        print(f"moderate AP_R40 {metric.upper()} (mean +- sd over {len(plan.seeds)} seeds)")
        print(f"{'arm':>10} {'frames':>6} " + " ".join(f"{n:>14}" for n in names))
        for arm, per_size in summary["ap"].items():
            for size, row in per_size.items():
                cells = " ".join(
                    f"{row[metric][n]['mean']:8.1f} +-{row[metric][n]['sd']:4.1f}" for n in names
                )
                print(f"{arm:>10} {size:>6} {cells}")
    for pair, per_size in summary["paired"].items():
        print(f"paired difference {pair} (mean +- sd, wins of {len(plan.seeds)})")
        for size, row in per_size.items():
            for metric in ("3d", "bev"):
                cells = " ".join(
                    "{mean:+6.1f} +-{sd:4.1f} ({wins})".format(**row[metric][n]) for n in names
                )
                print(f"{metric:>10} {size:>6} {cells}")
    print("objects added per frame:", json.dumps(summary["added_per_frame"]))
    print("heading error of matched detections, degrees:", json.dumps(summary["heading_error_deg"]))


def plot(summary: dict[str, Any], path: Path) -> None:
    """AP against training frames per arm (mean over seeds, bars: the spread), 3D and BEV rows,
    one column per class and the mean."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from detection.heads import CLASSES

    names = (*CLASSES, "mean")
    figure, axes = plt.subplots(2, len(names), figsize=(4 * len(names), 7), squeeze=False)
    for row, metric in enumerate(("3d", "bev")):
        for col, name in enumerate(names):
            ax = axes[row, col]
            for arm, per_size in summary["ap"].items():
                sizes = [int(s) for s in per_size]
                mean = [per_size[s][metric][name]["mean"] for s in per_size]
                sd = [per_size[s][metric][name]["sd"] for s in per_size]
                ax.errorbar(sizes, mean, yerr=sd, marker="o", capsize=3, label=arm)
            ax.set_xscale("log")
            ax.set_xticks(sizes, [str(s) for s in sizes])  # the subsets, not log decades
            ax.minorticks_off()
            ax.set_title(f"{name}, {metric.upper()} moderate AP_R40")
            ax.set_xlabel("training frames")
            ax.grid(alpha=0.3)
    axes[0, 0].legend()
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    figure.savefig(tmp, dpi=90)
    plt.close(figure)
    os.replace(tmp, path)


# Main -----------------------------------------------------------------------------------------
def parse_plan(argv: list[str] | None) -> tuple[Plan, argparse.Namespace]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a few frames and steps (CI)")
    parser.add_argument("--work", type=Path, help="keep data and databases here between runs")
    parser.add_argument("--out", type=Path, default=Path("bench_detection"), help="png and json")
    parser.add_argument("--frames", type=int, help="training pool size")
    parser.add_argument("--val-frames", type=int, help="validation frames (other seeds)")
    parser.add_argument("--fractions", type=float, nargs="+", help="training subsets")
    parser.add_argument("--arms", nargs="+", help="none, cda, paper, or drcpo preset names")
    parser.add_argument("--seeds", type=int, help="seeds per subset and arm")
    parser.add_argument("--steps", type=int, help="optimiser steps per run")
    parser.add_argument("--batch-size", type=int)
    parser.add_argument("--workers", type=int, help="processes, one core each")
    parser.add_argument("--street-angle", type=float, help="max |street yaw|, degrees")
    args = parser.parse_args(argv)
    plan = QUICK if args.quick else Plan()
    changes = {
        key: getattr(args, key)
        for key in ("frames", "val_frames", "steps", "batch_size", "workers", "street_angle")
        if getattr(args, key) is not None
    }
    if args.fractions:
        changes["fractions"] = tuple(args.fractions)
    if args.arms:
        changes["arms"] = tuple(args.arms)
    if args.seeds is not None:
        changes["seeds"] = tuple(range(args.seeds))
    plan = replace(plan, **changes)
    if not all(0 < f <= 1 for f in plan.fractions) or min(plan.frames, plan.val_frames) < 1:
        parser.error("fractions must be in (0, 1] and frame counts positive")
    if min(plan.steps, plan.batch_size, plan.workers, len(plan.seeds)) < 1:
        parser.error("steps, batch size, workers and seeds must be positive")
    return plan, args


def main(argv: list[str] | None = None) -> int:
    plan, args = parse_plan(argv)
    from drcpo.config import load_config
    from drcpo.errors import DrcpoError

    try:  # an unknown preset fails now, not after the data are made
        for arm in plan.arms:
            if arm not in ("none", "cda", "paper"):
                load_config(arm)
    except DrcpoError as exc:
        print(f"error: arm {arm!r}: {exc}", file=sys.stderr)
        return 1
    if importlib.util.find_spec("torch") is None:
        print('error: bench_detection needs torch: pip install -e ".[detection]"', file=sys.stderr)
        return 1
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_detection_") as scratch:
        work = args.work or Path(scratch)
        work.mkdir(parents=True, exist_ok=True)
        try:
            data = prepare_data(work, plan)
            prepared = time.perf_counter()
            runs = run_grid(work, plan, data)
        except DrcpoError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
    summary = summarise(runs, plan)
    print_table(summary, plan)
    png = args.out / "detection.png"
    plot(summary, png)
    subsets = {
        str(v["frames"]): {k: v[k] for k in v if k.endswith("_s")} for v in data["subsets"].values()
    }
    payload = {
        "quick": args.quick,
        "plan": asdict(plan),
        **summary,
        "prepare_seconds": {
            "total": round(prepared - start, 1),
            "synth_train": round(data["synth_train_s"], 1),
            "synth_val": round(data["synth_val_s"], 1),
            "subsets": subsets,
        },
        "wall_seconds": round(time.perf_counter() - start, 1),
        "png": str(png),
    }
    (args.out / "detection.json").write_text(json.dumps({**payload, "runs": runs}, indent=1) + "\n")
    print(json.dumps(payload))
    return 0


if __name__ == "__main__":
    sys.exit(main())
