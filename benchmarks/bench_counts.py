"""What each arm gives a detector to learn from: labelled objects per class per frame and where
they lie, against ``cda`` on the same frames and draws (the paper's Table 3, and its range).

Frames are synthetic worlds written in KITTI layout, cut to the camera's view (as the detection
benchmark trains); by default the detection benchmark's training pool (seed 1000) and a pool of
worlds of a seed no benchmark or test uses (3000), so a result tuned on one is checked on the
other. Each frame is augmented once per arm with generator ``default_rng([0, 0, i])`` and global
augmentation off (it moves objects, not counts). A label counts when at least 5 of the frame's
points lie in its box (fewer is hardly an object to a detector); labels holding no point are
reported apart.

Printed per pool and arm: labelled objects per class per frame and their ratio to ``cda``'s; the
median range (BEV distance from the sensor) per class and its ratio to ``cda``'s; the share of
empty labels; points per frame; and what DR.CPO was asked for, added, and why not (per class,
per frame). The last stdout line is one JSON object.

Usage: ``python benchmarks/bench_counts.py --work DIR [--frames 20] [--arms cda paper ...]
[--pools 1000 3000] [--db DB]`` (``--db``: the database and index the arms sample from; default:
one built from the first pool's frames, as a user would).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import numpy as np
from detection.arms import make_augment, parse_arm

from drcpo.geometry import box_members

CLASSES = ("Car", "Pedestrian", "Cyclist")
MIN_POINTS = 5
STREET_ANGLE = 45.0  # as the detection benchmark's worlds


def pool(work: Path, seed: int, frames: int) -> Path:
    """A synthetic KITTI root of ``frames`` frames of worlds of ``seed`` (reused when it
    matches)."""
    from drcpo.synth import LidarConfig, WorldConfig, write_synthetic_kitti
    from drcpo.synth.dataset import matches, synth_parameters

    root = work / f"pool_{seed}_{frames}"
    world = WorldConfig().with_street_angle(STREET_ANGLE)
    if not matches(root, synth_parameters(frames, seed, world, LidarConfig(), 0.0)):
        write_synthetic_kitti(root, frames, seed, world, val_fraction=0.0, overwrite=True)
    return root


def database(work: Path, root: Path) -> str:
    from drcpo.database import GroundTruthDatabase
    from drcpo.database.build import build_database
    from drcpo.index import IndexConfig
    from drcpo.index_build import build_index

    db = work / f"db_{root.name}"
    if not (db / "manifest.json").is_file():
        build_database(root, "train", db, workers=1, overwrite=True)
    if not (db / "index" / "manifest.json").is_file():
        build_index(GroundTruthDatabase.open(db), IndexConfig()).save(db, overwrite=True)
    return str(db)


def without_global(spec: str) -> str:
    """The arm with global augmentation off (added to its overrides)."""
    if spec == "none":
        return spec
    joiner = "," if ":" in spec else ":"
    return f"{spec}{joiner}global_augmentation.enabled=false"


def tally(frames: list, spec: str, db: str) -> dict[str, Any]:
    """Labelled objects, ranges, empty labels, points and DR.CPO's bookkeeping of one arm."""
    from drcpo.transforms import STATS_KEY

    augment = make_augment(parse_arm(without_global(spec)), db)
    labels, empty, points = Counter(), Counter(), 0
    ranges: dict[str, list[float]] = defaultdict(list)
    asked: dict[str, Counter] = defaultdict(Counter)
    for i, frame in enumerate(frames):
        out = frame if augment is None else augment(frame, np.random.default_rng([0, 0, i]))
        inside = np.zeros(len(out.boxes), dtype=np.int64)
        if len(out.boxes):
            _, box = box_members(out.points[:, :3], out.boxes)
            inside = np.bincount(box, minlength=len(out.boxes))
        for name, count, row in zip(out.names.astype(str), inside, out.boxes, strict=True):
            if count >= MIN_POINTS:
                labels[name] += 1
                ranges[name].append(float(np.hypot(row[0], row[1])))
            elif count == 0:
                empty[name] += 1
        points += len(out.points)
        for name, entry in (
            out.metadata.get(STATS_KEY, {}).get("objects", {}).get("drcpo", {}).items()
        ):
            asked[name]["tried"] += entry["tried"]
            asked[name]["added"] += entry["added"]
            for reason, n in entry.get("rejected", {}).items():
                asked[name][reason] += n
    n = len(frames)
    return {
        "labels_per_frame": {c: round(labels[c] / n, 2) for c in CLASSES},
        "median_range_m": {
            c: round(float(np.median(ranges[c])), 1) if ranges[c] else None for c in CLASSES
        },
        "empty_labels_per_frame": {c: round(empty[c] / n, 2) for c in CLASSES},
        "points_per_frame": round(points / n),
        "drcpo_per_frame": {
            c: {k: round(v / n, 2) for k, v in asked[c].items()} for c in CLASSES if asked[c]
        },
    }


def with_ratios(result: dict[str, Any], cda: dict[str, Any]) -> dict[str, Any]:
    """The arm's labels and median ranges over ``cda``'s, per class."""

    def ratio(a, b):
        return round(a / b, 2) if a is not None and b else None

    return {
        **result,
        "labels_to_cda": {
            c: ratio(result["labels_per_frame"][c], cda["labels_per_frame"][c]) for c in CLASSES
        },
        "median_range_to_cda": {
            c: ratio(result["median_range_m"][c], cda["median_range_m"][c]) for c in CLASSES
        },
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True, help="pools and databases")
    parser.add_argument("--frames", type=int, default=20, help="frames per pool")
    parser.add_argument("--pools", type=int, nargs="+", default=[1000, 3000], help="world seeds")
    parser.add_argument("--arms", nargs="+", default=["none", "cda", "paper"])
    parser.add_argument("--db", help="database (with its index) to sample from")
    args = parser.parse_args(argv)
    from detection.train import load_frames

    from drcpo.errors import DrcpoError

    arms = list(dict.fromkeys(["cda", *args.arms]))
    try:
        for spec in arms:
            parse_arm(without_global(spec))
        roots = [pool(args.work, seed, args.frames) for seed in args.pools]
        db = args.db or database(args.work, roots[0])
    except DrcpoError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    report: dict[str, Any] = {"frames": args.frames, "db": db, "pools": {}}
    for seed, root in zip(args.pools, roots, strict=True):
        frames = load_frames(root, "train")
        results = {spec: tally(frames, spec, db) for spec in arms}
        rows = {spec: with_ratios(r, results["cda"]) for spec, r in results.items()}
        report["pools"][str(seed)] = rows
        print(f"pool of seed {seed} ({len(frames)} frames), labels with >= {MIN_POINTS} points:")
        for spec, row in rows.items():
            cells = "  ".join(
                f"{c} {row['labels_per_frame'][c]:5.1f} ({row['labels_to_cda'][c]}) "
                f"{row['median_range_m'][c]} m ({row['median_range_to_cda'][c]})"
                for c in CLASSES
            )
            print(f"  {spec[:60]:>60}: {cells}  points {row['points_per_frame']}")
            if row["drcpo_per_frame"]:
                print(f"  {'':>60}  DR.CPO per frame: {json.dumps(row['drcpo_per_frame'])}")
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
