"""Does the augmentation help a detector? Arms judged by a detector on the synthetic world.

A small CenterPoint-style BEV detector (``benchmarks/detection/``, torch on CPU or ``--device
cuda``: install with ``pip install -e ".[detection]"``) is trained on subsets of a synthetic
training pool with each augmentation arm and several seeds (1,200 steps of batch 4, about 9
CPU-minutes a run), and evaluated on held-out frames of other worlds (other seeds) with drcpo's
KITTI evaluator (moderate AP_R40 at KITTI's strict overlaps: Car 0.7, Pedestrian and Cyclist
0.5; 3D and BEV).

Data, made as a user would: ``write_synthetic_kitti`` with streets up to ``--street-angle``
degrees from the sensor axis for the training pool and the validation set; per training subset
(the first N frames of the pool, nested) a ground-truth database and candidate index built from
exactly that subset. Frames are cut to the camera's field of view, as OpenPCDet trains KITTI.

Arms (:mod:`detection.arms`): ``none``, ``cda`` (ground-truth sampling and global flip, rotation,
scaling), ``paper`` (DR.CPO as the paper configures it), ``broken`` (the negative control: cda
with every inserted label moved 0.5 m), any drcpo preset or YAML config (DR.CPO with it), each
optionally with overrides: ``NAME:KEY=VALUE,KEY=VALUE`` (``paper:placement.location=source``).

Seed ``s`` fixes the model's initialisation, the order of the frames and each sample's
augmentation generator ``default_rng([s, epoch, index])``, so arms are compared in pairs: every
arm against ``cda`` (DR.CPO arms against ``paper`` too) by a paired bootstrap over seeds and
validation frames (:mod:`detection.stats`), with a 95 % interval and a verdict per class; the
controls ``cda`` vs ``none`` (better) and ``broken`` vs ``cda`` (worse) are checked in the report.
Finished runs are cached in ``WORK/runs/`` by arm, subset, seed, plan and code hash.

Printed: per subset and arm, AP mean and spread over seeds; the paired differences; the
controls; per arm the labelled objects per class per frame, their median range, points and
augmentation ms per frame. Writes ``OUT/detection.png`` (AP against training frames per arm)
and ``OUT/detection.json`` (with every run, its environment and revision). The last stdout line
is one JSON object.

Usage: ``python benchmarks/bench_detection.py [--quick] [--work DIR] [--out DIR] [--steps N]
[--frames N] [--val-frames N] [--fractions 0.1 0.25 ...] [--arms ARM ...] [--seeds 0 1 2]
[--workers N] [--street-angle DEG] [--curve-every N] [--replicates N] [--device cpu|cuda]``.
``--quick`` (for CI) proves the loop end to end on a few frames and a few steps; its AP means
nothing.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import json
import multiprocessing
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from detection.arms import make_augment, parse_arm

from drcpo.frame import Frame

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
    steps: int = 1200
    batch_size: int = 4
    workers: int = 2
    street_angle: float = 45.0
    curve_every: int = 0
    replicates: int = 1000
    device: str = "cpu"

    def subset_size(self, fraction: float) -> int:
        return max(1, round(fraction * self.frames))


QUICK = Plan(
    frames=12, val_frames=8, fractions=(0.5, 1.0), arms=("none", "cda", "paper", "broken"),
    seeds=(0, 1), steps=3, batch_size=2, replicates=50,
)  # fmt: skip


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
    from drcpo.index import IndexConfig
    from drcpo.index_build import build_index

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
    needs_index = any(parse_arm(arm).kind == "drcpo" for arm in plan.arms)
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
            build_index(database, IndexConfig()).save(db, overwrite=True)
            entry["index_s"] = _cpu() - start
        subsets[fraction] = entry
    return {
        "train": str(train_root), "val": str(val_root), "val_id": _tree_digest(val_root),
        "subsets": subsets, **timings,
    }  # fmt: skip


def _tree_digest(root: Path) -> str:
    """A hash of a KITTI root's frames, labels, calibrations and ``val`` split (not of
    ``synth.json``, which names the version that wrote it)."""
    digest = hashlib.sha256()
    files = [p for p in (root / "training").rglob("*") if p.is_file()]
    for file in sorted([*files, root / "ImageSets" / "val.txt"]):
        digest.update(str(file.relative_to(root)).encode() + b"\0" + file.read_bytes())
    return digest.hexdigest()[:16]


# Runs -----------------------------------------------------------------------------------------
_VAL: dict[str, Any] = {}
#: What the arms' samples depend on: a run made by the same code is found without augmenting.
CODE_FILES = ("src/drcpo", "benchmarks/detection")
#: What turns a run's samples into AP: the detector, its training and scoring.
TRAINER_FILES = ("benchmarks/detection", "src/drcpo/evaluation")
#: Bump when :func:`run_one` changes what a run trains or scores: with the hash of
#: :data:`TRAINER_FILES` and the digest of the samples it keys the cache of finished runs.
RUN_VERSION = 1


def _hash_files(root: Path, entries: tuple[str, ...]) -> str:
    digest = hashlib.sha256(f"run version {RUN_VERSION}".encode())
    for entry in entries:
        path = root / entry
        files = sorted(path.rglob("*")) if path.is_dir() else [path]
        for file in files:
            if file.suffix in (".py", ".yaml") and file.is_file():
                digest.update(str(file.relative_to(root)).encode() + b"\0" + file.read_bytes())
    return digest.hexdigest()[:16]


def code_revision() -> dict[str, Any]:
    """The git commit (when in a checkout), a hash of the code a run's samples depend on
    (drcpo's sources and configs, the detector and the arms) and one of the code that trains
    and scores them, each with :data:`RUN_VERSION`."""
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--", *CODE_FILES],
            capture_output=True,
            text=True,
        ).stdout.strip()
    except OSError:
        head, dirty = "", ""
    return {
        "commit": head or None,
        "dirty": bool(dirty),
        "code": _hash_files(root, CODE_FILES),
        "trainer": _hash_files(root, TRAINER_FILES),
    }


def environment(device: str) -> dict[str, Any]:
    """What a result depends on beyond the code: library versions, threads, device, load."""
    import numba
    import torch

    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "numba": numba.__version__,
        "torch_threads": torch.get_num_threads(),
        "device": device if device == "cpu" else torch.cuda.get_device_name(0),
        "cpus": os.cpu_count(),
        "load_average": [round(x, 2) for x in os.getloadavg()],
    }


def _pin(cores) -> None:
    """Pool initializer: pin this worker to one core (DR.CPO then keeps to one thread too)."""
    core = cores.get()
    if core is not None and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {core})


def _val_frames(root: str) -> list[Frame]:
    from detection.train import load_frames

    if root not in _VAL:
        _VAL.clear()
        _VAL[root] = load_frames(root, "val")
    return _VAL[root]


def _score(model, task: dict[str, Any], directory: Path) -> tuple[dict, list]:
    """Detect on the validation frames, write the result files, score them."""
    from detection.scoring import kitti_ap, write_results
    from detection.train import predict

    val_frames = _val_frames(task["val"])
    detections = predict(model, val_frames, device=task["device"])
    lines = [d.kitti_lines(f) for d, f in zip(detections, val_frames, strict=True)]
    write_results(directory, [f.frame_id for f in val_frames], lines)
    return kitti_ap(task["val"], "val", directory), detections


def _finished(runs: Path, key: str) -> dict[str, Any] | None:
    for record in runs.glob(f"*-{key}/run.json"):
        return json.loads(record.read_text())
    return None


def _write_json(path: Path, payload: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(payload, indent=1) + "\n")
    os.replace(tmp, path)  # a reader sees the whole file or none


def _cached(run: dict[str, Any], task: dict[str, Any]) -> dict[str, Any]:
    """A finished run as the result of ``task``: another arm with the same samples (an override
    equal to a default, say) shares it."""
    return {**run, "arm": task["arm"], "fraction": task["fraction"], "trained_as": run["arm"],
            "cached": True}  # fmt: skip


def run_one(task: dict[str, Any]) -> dict[str, Any]:
    """Train one (subset, arm, seed) run, detect on the validation frames, score them.

    A run is known by what it trains on: its key hashes the digest of its augmented samples
    with the plan, the trainer's code and the validation set. A finished run of the same key
    (``run.json`` in its directory) is read back instead, whichever arm or code made its samples;
    ``aliases/`` remembers the key of (arm, subset, seed, drcpo's code), so a grid run again by
    the same code does not even augment."""
    from detection.scoring import heading_errors
    from detection.train import TrainConfig, augment_samples, load_frames, train

    runs = Path(task["runs"])
    alias = runs / "aliases" / f"{task['alias']}.json"
    if alias.is_file():
        run = _finished(runs, json.loads(alias.read_text())["key"])
        if run is not None:
            return _cached(run, task)
    wall = time.perf_counter()
    clock = [time.process_time()]

    def lap() -> float:
        clock.append(time.process_time())
        return clock[-1] - clock[-2]

    frames = load_frames(task["train"], task["split"])
    augment = make_augment(parse_arm(task["arm"]), task["db"])
    config = TrainConfig(
        steps=task["steps"], batch_size=task["batch_size"], seed=task["seed"],
        device=task["device"],
    )  # fmt: skip
    samples = augment_samples(frames, augment, config)
    plan = task["plan"]
    key = run_key(plan, len(frames), task["seed"], samples.digest, task["trainer"], task["val_id"])
    run = _finished(runs, key)
    if run is not None:
        _write_json(alias, {"key": key})
        return _cached(run, task)
    directory = runs / f"{parse_arm(task['arm']).slug}-{len(frames)}-s{task['seed']}-{key}"
    shutil.rmtree(directory, ignore_errors=True)  # an unfinished run's files
    curve: list[dict[str, Any]] = []

    def progress(step: int, loss: float, model) -> None:
        every = task["curve_every"]
        if every and step % every == 0 and step < config.steps:
            ap, _ = _score(model, task, directory / "curve")
            curve.append({"step": step, "ap": ap})
            model.train()

    setup = lap()
    result = train(samples, config, progress=progress)
    trained = lap()
    ap, detections = _score(result.model, task, directory / "detections")
    curve.append({"step": config.steps, "ap": ap})
    evaluated = lap()
    count = max(samples.count, 1)
    run = {
        **{k: task[k] for k in ("arm", "fraction", "seed", "split")},
        "key": key,
        "samples": samples.digest,
        "frames": len(frames),
        "ap": ap,
        "curve": curve if task["curve_every"] else [],
        "heading": heading_errors(_val_frames(task["val"]), detections),
        "added_per_frame": {
            transform: {name: n / count for name, n in per_class.items()}
            for transform, per_class in samples.added.items()
        },
        "labels_per_frame": {name: n / count for name, n in samples.labels.items()},
        "labels_with_points_per_frame": {
            name: n / count for name, n in samples.labels_with_points.items()
        },
        "empty_label_share": {
            name: samples.empty_labels.get(name, 0) / n for name, n in samples.labels.items() if n
        },
        "median_range_m": {
            name: round(float(np.median(values)), 2) for name, values in samples.ranges.items()
        },
        "points_per_frame": samples.points / count,
        "augment_ms_per_frame": 1000 * float(np.median(samples.augment_seconds or [0.0])),
        "final_loss": float(np.mean(result.losses[-20:])),
        "seconds": {  # CPU seconds of this single-threaded process, except wall
            "setup": setup,
            "augment_per_step": float(np.sum(samples.augment_seconds)) / config.steps,
            **{f"{k}_per_step": v / config.steps for k, v in result.seconds.items()},
            "train": trained,
            "evaluate": evaluated,
            "cpu": clock[-1] - clock[0],
            "wall": time.perf_counter() - wall,
        },
        "revision": task["revision"],
        "environment": environment(task["device"]),
    }
    _write_json(directory / "run.json", run)  # its presence marks the run finished
    _write_json(alias, {"key": key})
    return {**run, "cached": False}


def _settings(plan: Plan, frames: int, seed: int) -> dict[str, Any]:
    # A GPU's arithmetic differs from the CPU's: its runs are its own (CPU keys as they were).
    device = {} if plan.device == "cpu" else {"device": plan.device}
    return {
        "frames": frames, "seed": seed, "pool": plan.frames, "val_frames": plan.val_frames,
        "street_angle": plan.street_angle, "steps": plan.steps, "batch_size": plan.batch_size,
        "curve_every": plan.curve_every, **device,
    }  # fmt: skip


def _sha(settings: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:12]


def run_key(plan: Plan, frames: int, seed: int, samples: str, trainer: str, val: str) -> str:
    """What a finished run depends on, hashed: the subset, seed and training settings of the
    plan, the digest of its augmented samples, the trainer's code and the validation set."""
    return _sha({**_settings(plan, frames, seed), "samples": samples, "trainer": trainer,
                 "val": val})  # fmt: skip


def alias_key(plan: Plan, arm: str, frames: int, seed: int, code: str) -> str:
    """The arm, subset, seed and settings and the code that makes the samples, hashed: where a
    grid run again by the same code finds its runs' keys without augmenting (the cache's key
    before runs were keyed by their samples, so earlier runs' ``key`` is their alias)."""
    return _sha({**_settings(plan, frames, seed), "arm": arm, "code": code})


def run_grid(work: Path, plan: Plan, data: dict[str, Any]) -> list[dict[str, Any]]:
    revision = code_revision()
    tasks = []
    for seed in plan.seeds:
        for fraction in plan.fractions:
            subset = data["subsets"][fraction]
            for arm in plan.arms:
                alias = alias_key(plan, arm, subset["frames"], seed, revision["code"])
                tasks.append(
                    {
                        "train": data["train"], "val": data["val"], "split": subset["split"],
                        "db": subset["db"], "arm": arm, "fraction": fraction, "seed": seed,
                        "steps": plan.steps, "batch_size": plan.batch_size,
                        "curve_every": plan.curve_every, "device": plan.device, "alias": alias,
                        "revision": revision, "trainer": revision["trainer"], "plan": plan,
                        "val_id": data["val_id"], "runs": str(work / "runs"),
                    }
                )  # fmt: skip
    context = multiprocessing.get_context("spawn")
    cores = context.Queue()
    available = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else [None]
    # With a GPU too: each process augments its samples on its core, then trains on the shared
    # GPU (the detector is small), so several runs keep it busy.
    workers = plan.workers
    for k in range(workers):
        cores.put(available[k % len(available)])
    runs = []
    with context.Pool(workers, initializer=_pin, initargs=(cores,)) as pool:
        for run in pool.imap_unordered(run_one, tasks):
            ap = run["ap"]
            how = "cached" if run["cached"] else f"{run['seconds']['cpu']:.0f} CPU-s"
            print(
                f"  {run['arm']:>12} {run['frames']:4d} frames seed {run['seed']}: moderate "
                f"AP_R40 3D {ap['3d']['mean']:5.1f} BEV {ap['bev']['mean']:5.1f} ({how})",
                file=sys.stderr,
            )
            runs.append(run)
    order = {arm: i for i, arm in enumerate(plan.arms)}
    return sorted(runs, key=lambda r: (r["fraction"], order[r["arm"]], r["seed"]))


def _adopt_one(task: dict[str, Any]) -> str:
    from detection.train import TrainConfig, augment_samples, load_frames

    record = Path(task["record"])
    run = json.loads(record.read_text())
    frames = load_frames(task["train"], run["split"])
    config = TrainConfig(steps=task["plan"].steps, batch_size=task["plan"].batch_size,
                         seed=run["seed"])  # fmt: skip
    samples = augment_samples(frames, make_augment(parse_arm(run["arm"]), task["db"]), config)
    key = run_key(task["plan"], len(frames), run["seed"], samples.digest, task["trainer"],
                  task["val_id"])  # fmt: skip
    before = run["key"]
    directory = record.parent.with_name(record.parent.name.removesuffix(before) + key)
    adopted = {"key_before": before, "trainer": task["trainer"], "samples_by": task["commit"]}
    _write_json(record, {**run, "key": key, "samples": samples.digest, "adopted": adopted})
    os.replace(record.parent, directory)
    _write_json(record.parent.parent / "aliases" / f"{before}.json", {"key": key})
    return f"  {directory.name}: was {before}"


def adopt(work: Path, plan: Plan, data: dict[str, Any]) -> None:
    """Key the runs finished before runs were keyed by their samples (``run.json`` without
    ``samples``) by the digest of their samples, as the drcpo imported here makes them: it must
    be a clean checkout at the commit that made the run, and the run's plan must be this one.
    Their trainer is taken to be today's: the move to samples augmented before training left
    every step's batch and the optimiser's path as they were (one run retrained shows it)."""
    import drcpo

    checkout = Path(drcpo.__file__).resolve().parents[2]
    git = ["git", "-C", str(checkout)]
    head = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True).stdout
    dirty = subprocess.run(
        [*git, "status", "--porcelain", "--", "src/drcpo"], capture_output=True, text=True
    ).stdout.strip()
    revision = code_revision()
    tasks = []
    for record in sorted((work / "runs").glob("*/run.json")):
        run = json.loads(record.read_text())
        if "samples" in run:
            continue
        made = run["revision"]
        if made["commit"] != head.strip() or dirty:
            here = f"{head.strip() or '?'}{' (changed)' if dirty else ''}"
            print(f"  {record.parent.name}: made at {made['commit']}, drcpo here at {here}",
                  file=sys.stderr)  # fmt: skip
            continue
        if alias_key(plan, run["arm"], run["frames"], run["seed"], made["code"]) != run["key"]:
            print(f"  {record.parent.name}: another plan", file=sys.stderr)
            continue
        tasks.append(
            {"record": str(record), "train": data["train"], "db": str(work / "db" / run["split"]),
             "plan": plan, "trainer": revision["trainer"], "val_id": data["val_id"],
             "commit": made["commit"]}
        )  # fmt: skip
    print(f"adopting {len(tasks)} runs", file=sys.stderr)
    context = multiprocessing.get_context("spawn")
    with context.Pool(plan.workers) as pool:
        for line in pool.imap_unordered(_adopt_one, tasks):
            print(line, file=sys.stderr)


# Summary --------------------------------------------------------------------------------------
METRIC_NAMES = ("3d", "bev")
#: Paired comparisons that the report must find as expected, or say it cannot judge.
CONTROLS = (("cda", "none", "better"), ("broken", "cda", "worse"))


def _quantities() -> list[tuple[str, str]]:
    from detection.heads import CLASSES

    return [(metric, name) for metric in METRIC_NAMES for name in (*CLASSES, "mean")]


def _tables_of(run: dict[str, Any], val: str, work: Path, cache: dict[str, Any]):
    """The per-frame evaluation tables of a run's detections (moderate, strict overlaps)."""
    from detection.heads import CLASSES

    from drcpo.datasets.kitti import read_split
    from drcpo.evaluation import read_frames
    from drcpo.evaluation.resampling import frame_tables

    if "gt" not in cache:
        cache["ids"] = read_split(val, "val")
        cache["gt"] = read_frames(Path(val) / "training" / "label_2", cache["ids"])
    if run["key"] not in cache:
        directory = next((work / "runs").glob(f"*-{run['key']}")) / "detections"
        detections = read_frames(directory, cache["ids"], results=True)
        cache[run["key"]] = frame_tables(cache["gt"], detections, CLASSES, "strict")
    return cache[run["key"]]


def _scorer(tables: list) -> Any:
    from detection.heads import CLASSES

    def score(seed: int, weights: np.ndarray) -> np.ndarray:
        out = []
        for metric in METRIC_NAMES:
            per_class = [tables[seed].ap_r40(metric, name, weights) for name in CLASSES]
            out += [*per_class, float(np.mean(per_class))]
        return np.array(out)

    return score


def comparisons(arms: tuple[str, ...]) -> list[tuple[str, str]]:
    """The (arm, reference) pairs the report holds: every arm against ``cda``, every DR.CPO
    arm against ``paper`` too, and ``cda`` against ``none``."""
    pairs = [(arm, "cda") for arm in arms if "cda" in arms and arm not in ("cda", "none")]
    if "paper" in arms:
        pairs += [
            (arm, "paper") for arm in arms if arm != "paper" and parse_arm(arm).kind == "drcpo"
        ]
    if "cda" in arms and "none" in arms:
        pairs.append(("cda", "none"))
    return pairs


def summarise(
    runs: list[dict[str, Any]], plan: Plan, work: Path, val: str, replicates: int
) -> dict[str, Any]:
    """Per subset and arm: AP mean and spread over seeds, the paired differences with their
    bootstrap intervals, what the augmentation gave per frame, heading errors, timings."""
    from detection.heads import CLASSES
    from detection.scoring import mean_and_spread
    from detection.stats import paired_bootstrap

    names = (*CLASSES, "mean")
    by_key = {(r["arm"], r["fraction"], r["seed"]): r for r in runs}
    ap: dict[str, Any] = {}
    for arm in plan.arms:
        ap[arm] = {}
        for fraction in plan.fractions:
            seeds = [by_key[(arm, fraction, s)] for s in plan.seeds]
            ap[arm][str(seeds[0]["frames"])] = {
                metric: {n: mean_and_spread([r["ap"][metric][n] for r in seeds]) for n in names}
                for metric in METRIC_NAMES
            }
    cache: dict[str, Any] = {}
    paired: dict[str, Any] = {}
    quantities = _quantities()
    for arm, reference in comparisons(plan.arms):
        rows = {}
        for fraction in plan.fractions:
            mine = [by_key[(arm, fraction, s)] for s in plan.seeds]
            theirs = [by_key[(reference, fraction, s)] for s in plan.seeds]
            a = [_tables_of(r, val, work, cache) for r in mine]
            b = [_tables_of(r, val, work, cache) for r in theirs]
            rng = np.random.default_rng([len(plan.seeds), a[0].frames, 7])
            found = paired_bootstrap(
                _scorer(a), _scorer(b), len(plan.seeds), a[0].frames, rng, replicates
            )
            row: dict[str, Any] = {metric: {} for metric in METRIC_NAMES}
            for (metric, name), difference in zip(quantities, found, strict=True):
                row[metric][name] = difference.to_dict()
            rows[str(mine[0]["frames"])] = row
        paired[f"{arm} - {reference}"] = rows
    controls = []
    for arm, reference, expected in CONTROLS:
        pair = paired.get(f"{arm} - {reference}")
        for size, row in (pair or {}).items():
            got = row["3d"]["mean"]["verdict"]
            controls.append(
                {"pair": f"{arm} - {reference}", "frames": int(size), "expected": expected,
                 "verdict": got, "passed": got == expected}
            )  # fmt: skip
    per_arm: dict[str, Any] = {}
    for arm in plan.arms:
        per_arm[arm] = {}
        for fraction in plan.fractions:
            mine = [by_key[(arm, fraction, s)] for s in plan.seeds]

            def mean_of(field: str, rows=mine) -> dict[str, float]:
                keys = sorted({k for r in rows for k in r[field]})
                return {
                    k: round(float(np.mean([r[field].get(k, 0.0) for r in rows])), 3) for k in keys
                }

            heading = {}
            for name in CLASSES:
                values = [
                    r["heading"][name]["mean_deg"] for r in mine if r["heading"][name]["matched"]
                ]
                heading[name] = round(float(np.mean(values)), 1) if values else None
            per_arm[arm][str(mine[0]["frames"])] = {
                "labels_per_frame": mean_of("labels_per_frame"),
                "labels_with_points_per_frame": mean_of("labels_with_points_per_frame"),
                "empty_label_share": mean_of("empty_label_share"),
                "median_range_m": mean_of("median_range_m"),
                "added_per_frame": {
                    transform: mean_of_added(mine, transform)
                    for transform in sorted({t for r in mine for t in r["added_per_frame"]})
                },
                "points_per_frame": round(float(np.mean([r["points_per_frame"] for r in mine])), 1),
                "augment_ms_per_frame": round(
                    float(np.mean([r["augment_ms_per_frame"] for r in mine])), 2
                ),
                "heading_error_deg": heading,
                "cpu_seconds_per_run": round(
                    float(np.mean([r["seconds"]["cpu"] for r in mine])), 1
                ),
            }
    decision = decide(paired, plan.arms) if "cda" in plan.arms else None
    return {
        "ap": ap, "paired": paired, "controls": controls, "per_arm": per_arm,
        "decision": decision,
    }  # fmt: skip


#: Arms that never become the default: the floor and the negative control.
NOT_CANDIDATES = ("none", "broken")
DECISION_RULE = (
    "the default is, of cda and the arms compared with it, one no worse than cda at any "
    "subset (3D mean AP, paired 95 % interval) with the best paired mean 3D AP difference to "
    "cda averaged over the subsets (cda: 0; a tie goes to cda, the simpler)"
)


def decide(paired: dict[str, Any], arms: tuple[str, ...]) -> dict[str, Any]:
    """The default by :data:`DECISION_RULE`, with each candidate's mean difference to ``cda``
    over the subsets and the subsets where it was worse or better."""
    candidates: dict[str, Any] = {"cda": {"mean_difference": 0.0, "worse_at": [], "better_at": []}}
    for arm in arms:
        rows = paired.get(f"{arm} - cda")
        if arm in ("cda", *NOT_CANDIDATES) or not rows:
            continue
        verdicts = {int(size): row["3d"]["mean"]["verdict"] for size, row in rows.items()}
        candidates[arm] = {
            "mean_difference": round(
                float(np.mean([row["3d"]["mean"]["mean"] for row in rows.values()])), 2
            ),
            "worse_at": sorted(k for k, v in verdicts.items() if v == "worse"),
            "better_at": sorted(k for k, v in verdicts.items() if v == "better"),
        }
    eligible = [arm for arm, c in candidates.items() if not c["worse_at"]]
    chosen = max(eligible, key=lambda a: (candidates[a]["mean_difference"], a == "cda"))
    return {"chosen": chosen, "rule": DECISION_RULE, "candidates": candidates}


def mean_of_added(rows: list[dict[str, Any]], transform: str) -> dict[str, float]:
    keys = sorted({k for r in rows for k in r["added_per_frame"].get(transform, {})})
    return {
        k: round(
            float(np.mean([r["added_per_frame"].get(transform, {}).get(k, 0.0) for r in rows])), 2
        )
        for k in keys
    }


def print_table(summary: dict[str, Any], plan: Plan) -> None:
    from detection.heads import CLASSES

    names = (*CLASSES, "mean")
    for metric in METRIC_NAMES:
        print(f"moderate AP_R40 {metric.upper()} (mean +- sd over {len(plan.seeds)} seeds)")
        print(f"{'arm':>24} {'frames':>6} " + " ".join(f"{n:>14}" for n in names))
        for arm, per_size in summary["ap"].items():
            for size, row in per_size.items():
                cells = " ".join(
                    f"{row[metric][n]['mean']:8.1f} +-{row[metric][n]['sd']:4.1f}" for n in names
                )
                print(f"{arm:>24} {size:>6} {cells}")
    print("paired difference, mean [95 % interval over seeds and validation frames] verdict")
    for pair, per_size in summary["paired"].items():
        for size, row in per_size.items():
            for metric in METRIC_NAMES:
                cells = "  ".join(
                    "{n} {mean:+.1f} [{low:+.1f}, {high:+.1f}] {verdict}".format(
                        n=n, **row[metric][n]
                    )
                    for n in names
                )
                print(f"{pair:>28} {size:>4} {metric:>3}: {cells}")
    for control in summary["controls"]:
        mark = "ok" if control["passed"] else "FAILED"
        print(
            f"control {control['pair']} at {control['frames']} frames: expected "
            f"{control['expected']}, got {control['verdict']} ({mark})"
        )
    if summary.get("decision"):
        decision = summary["decision"]
        print(f"decision ({decision['rule']}): {decision['chosen']}")
        for arm, c in decision["candidates"].items():
            print(
                f"{arm:>24}: mean 3D difference to cda {c['mean_difference']:+5.1f}, worse at "
                f"{c['worse_at'] or 'no subset'}, better at {c['better_at'] or 'no subset'}"
            )
    print("per training frame the detector saw (labels with >= 5 points; points; augmentation ms):")
    for arm, per_size in summary["per_arm"].items():
        for size, row in per_size.items():
            labels = " ".join(
                f"{n} {row['labels_with_points_per_frame'].get(n, 0.0):5.1f}" for n in CLASSES
            )
            ranges = " ".join(f"{row['median_range_m'].get(n, float('nan')):4.1f}" for n in CLASSES)
            print(
                f"{arm:>24} {size:>6}: {labels}  median range m {ranges}  points "
                f"{row['points_per_frame']:8.0f}  {row['augment_ms_per_frame']:6.1f} ms"
            )


def plot(summary: dict[str, Any], path: Path) -> None:
    """AP against training frames per arm (mean over seeds, bars: the spread), 3D and BEV rows,
    one column per class and the mean."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from detection.heads import CLASSES

    names = (*CLASSES, "mean")
    figure, axes = plt.subplots(2, len(names), figsize=(4 * len(names), 7), squeeze=False)
    for row, metric in enumerate(METRIC_NAMES):
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
    parser.add_argument("--work", type=Path, help="keep data, databases and runs here")
    parser.add_argument("--out", type=Path, default=Path("bench_detection"), help="png and json")
    parser.add_argument("--frames", type=int, help="training pool size")
    parser.add_argument("--val-frames", type=int, help="validation frames (other seeds)")
    parser.add_argument("--fractions", type=float, nargs="+", help="training subsets")
    parser.add_argument(
        "--arms", nargs="+", help="none, cda, paper, broken, or a drcpo preset / YAML path, "
        "each optionally with overrides: NAME:KEY=VALUE,KEY=VALUE"
    )  # fmt: skip
    parser.add_argument("--seeds", type=int, nargs="+", help="seeds (default 0 1 2)")
    parser.add_argument("--steps", type=int, help="optimiser steps per run")
    parser.add_argument("--batch-size", type=int)
    parser.add_argument("--workers", type=int, help="processes, one core each (also with cuda)")
    parser.add_argument("--street-angle", type=float, help="max |street yaw|, degrees")
    parser.add_argument("--curve-every", type=int, help="validation AP every N steps (a curve)")
    parser.add_argument("--replicates", type=int, help="bootstrap replicates")
    parser.add_argument("--device", choices=("cpu", "cuda"), help="where the detector trains")
    parser.add_argument(
        "--adopt", action="store_true",
        help="key --work's runs made before runs were keyed by their samples, then stop",
    )  # fmt: skip
    args = parser.parse_args(argv)
    plan = QUICK if args.quick else Plan()
    changes = {
        key: getattr(args, key)
        for key in (
            "frames",
            "val_frames",
            "steps",
            "batch_size",
            "workers",
            "street_angle",
            "curve_every",
            "replicates",
            "device",
        )
        if getattr(args, key) is not None
    }
    if args.fractions:
        changes["fractions"] = tuple(args.fractions)
    if args.arms:
        changes["arms"] = tuple(dict.fromkeys(args.arms))
    if args.seeds is not None:
        changes["seeds"] = tuple(dict.fromkeys(args.seeds))
    plan = replace(plan, **changes)
    if not all(0 < f <= 1 for f in plan.fractions) or min(plan.frames, plan.val_frames) < 1:
        parser.error("fractions must be in (0, 1] and frame counts positive")
    if min(plan.steps, plan.batch_size, plan.workers, plan.replicates, len(plan.seeds)) < 1:
        parser.error("steps, batch size, workers, replicates and seeds must be positive")
    if plan.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            parser.error("--device cuda: torch sees no GPU here")
    return plan, args


def main(argv: list[str] | None = None) -> int:
    plan, args = parse_plan(argv)
    from drcpo.errors import DrcpoError

    try:  # a bad arm fails now, not after the data are made
        for arm in plan.arms:
            parse_arm(arm)
    except DrcpoError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if importlib.util.find_spec("torch") is None:
        print('error: bench_detection needs torch: pip install -e ".[detection]"', file=sys.stderr)
        return 1
    start = time.perf_counter()
    load = [round(x, 2) for x in os.getloadavg()]
    with tempfile.TemporaryDirectory(prefix="bench_detection_") as scratch:
        work = args.work or Path(scratch)
        work.mkdir(parents=True, exist_ok=True)
        try:
            data = prepare_data(work, plan)
            if args.adopt:
                adopt(work, plan, data)
                return 0
            prepared = time.perf_counter()
            runs = run_grid(work, plan, data)
            summary = summarise(runs, plan, work, data["val"], plan.replicates)
        except DrcpoError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
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
        "revision": code_revision(),
        "environment": {**environment(plan.device), "load_average_at_start": load},
        "runs_cached": sum(r["cached"] for r in runs),
        "prepare_seconds": {
            "total": round(prepared - start, 1),
            "synth_train": round(data["synth_train_s"], 1),
            "synth_val": round(data["synth_val_s"], 1),
            "subsets": subsets,
        },
        "wall_seconds": round(time.perf_counter() - start, 1),
        "png": str(png),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "detection.json").write_text(json.dumps({**payload, "runs": runs}, indent=1) + "\n")
    print(json.dumps(payload))
    return 0


if __name__ == "__main__":
    sys.exit(main())
