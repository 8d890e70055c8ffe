"""Score HPR occlusion against ray-cast truth in the built-in synthetic world.

For each frame of the synthetic world (swept without range noise, so every return lies on a
surface), objects of the three classes are placed at random free poses and sampled densely on
their whole outer surface. Ray casting from the sensor says which samples it truly sees:

* **s-HPR** (``drcpo.occlusion.self_occlusion``, R = box diagonal x 200, viewpoint the sensor)
  is scored against the object's self-visibility (the object alone in the world).
* **e-HPR** (``drcpo.occlusion.external_occlusion`` with each detector preset's R and
  viewpoint height) is scored on the frame after insertion: the frame's points in the KITTI
  detection range, minus those inside the inserted boxes, plus the inserted objects' truly
  self-visible samples (a perfect s-HPR).
  Truth: visible from the sensor in the world with the objects inserted.

Scores are precision and recall of the *kept* points (kept and truly visible / kept; kept and
truly visible / truly visible), over all points and separately over inserted and original
points, with the median milliseconds per call. The last stdout line is one JSON object::

    {"frames": F, "objects": n, "self_hpr": {"precision": p, "recall": r, ...},
     "external": {method: {"all": {...}, "inserted": {...}, "original": {...}, "ms": t}}}

Usage: ``python benchmarks/bench_occlusion_truth.py [--quick] [--frames N] [--seed S]``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

from drcpo import occlusion
from drcpo.config import PRESETS, load_config
from drcpo.geometry import bev_overlap_area, points_in_boxes
from drcpo.synth import (
    LidarConfig,
    Scene,
    Solids,
    frame_rng,
    free_pose,
    generate_world,
    make_actor,
    scan,
    visible_points,
)

DETECTION_RANGE = (0.0, -40.0, -3.0, 70.4, 40.0, 1.0)  # OpenPCDet's KITTI point cloud range
CLASS_SHARE = {"Car": 0.5, "Pedestrian": 0.3, "Cyclist": 0.2}
SELF_RADIUS_FACTOR = 200.0
TOLERANCE = 0.02  # metres; samples and noise-free returns lie exactly on their surfaces


class Score:
    """Counts of kept / truly visible points, for precision and recall."""

    def __init__(self) -> None:
        self.kept_visible = self.kept = self.visible = self.points = 0

    def add(self, kept: np.ndarray, visible: np.ndarray) -> None:
        self.kept_visible += int(np.count_nonzero(kept & visible))
        self.kept += int(np.count_nonzero(kept))
        self.visible += int(np.count_nonzero(visible))
        self.points += len(kept)

    def to_dict(self) -> dict[str, float | int]:
        precision = self.kept_visible / self.kept if self.kept else 1.0
        recall = self.kept_visible / self.visible if self.visible else 1.0
        return {
            "precision": round(precision, 4),
            "recall": round(recall, 4),
            "points": self.points,
            "truly_visible": self.visible,
            "kept": self.kept,
        }


def in_range(points: np.ndarray) -> np.ndarray:
    lo, hi = np.array(DETECTION_RANGE[:3]), np.array(DETECTION_RANGE[3:])
    return ((points[:, :3] >= lo) & (points[:, :3] <= hi)).all(axis=1)


def place_objects(world, rng, count):
    """Actors, boxes and surface samples of ``count`` objects at free, non-overlapping poses."""
    placed = []
    for name in rng.choice(list(CLASS_SHARE), size=count, p=list(CLASS_SHARE.values())):
        actor = make_actor(str(name), rng)
        for _ in range(20):
            box = free_pose(world, actor, rng, x_range=(4.0, 60.0), y_range=(-25.0, 25.0))
            taken = np.array([b for _, b, _ in placed]).reshape(-1, 7)
            if box is not None and not (bev_overlap_area(box[None], taken) > 0).any():
                break
            box = None
        if box is None:
            continue
        solids = actor.placed(box, len(world.actors) + len(placed))
        placed.append((str(name), box, solids))
    return placed


def frame_case(seed: int, index: int, objects: int, spacing: float):
    rng = frame_rng(seed, index)
    world = generate_world(rng)
    sweep = scan(world, rng, LidarConfig(range_noise=0.0))
    placed = place_objects(world, rng, objects)
    samples = []
    for name, box, solids in placed:
        points, _ = solids.surface_samples(rng, spacing)
        self_visible = visible_points(Scene(solids), points, TOLERANCE)
        samples.append((name, box, points, self_visible))
    inserted_solids = Solids.concatenate([s for _, _, s in placed])
    scene = world.with_extra(inserted_solids)
    return sweep, samples, scene


def timed(fn, *args):
    start = time.perf_counter()
    out = fn(*args)
    return out, (time.perf_counter() - start) * 1e3


def external_methods():
    """e-HPR with each detector preset."""
    methods = {}
    for name in PRESETS:
        setting = load_config(name).drcpo.external_occlusion
        r, z = setting.radius, setting.viewpoint_z
        label = f"e-hpr {name} (R={r:g}, z={z:g})"
        methods[label] = lambda p, r=r, z=z: occlusion.external_occlusion(p, r, z)
    return methods


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="1 frame, 4 objects, 6 cm spacing")
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--objects", type=int, default=8, help="objects placed per frame")
    parser.add_argument("--spacing", type=float, default=0.04, help="surface sample spacing, m")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.quick:
        args.frames, args.objects, args.spacing = 1, 4, 0.06

    self_score = {name: Score() for name in CLASS_SHARE}
    self_all, self_ms = Score(), []
    methods = external_methods()
    external = {m: {k: Score() for k in ("all", "inserted", "original")} for m in methods}
    external_ms: dict[str, list[float]] = {m: [] for m in methods}
    placed_count = 0
    for index in range(args.frames):
        sweep, samples, scene = frame_case(args.seed, index, args.objects, args.spacing)
        placed_count += len(samples)
        for name, box, points, self_visible in samples:
            kept, ms = timed(occlusion.self_occlusion, points, box, SELF_RADIUS_FACTOR)
            self_ms.append(ms)
            self_score[name].add(kept, self_visible)
            self_all.add(kept, self_visible)
        frame = sweep.points[in_range(sweep.points)]
        boxes = np.array([b for _, b, _, _ in samples]).reshape(-1, 7)
        frame = frame[~points_in_boxes(frame, boxes).any(axis=1)]
        inserted = [p[v] for _, _, p, v in samples]
        points = np.concatenate([frame[:, :3].astype(np.float64), *inserted])
        is_inserted = np.arange(len(points)) >= len(frame)
        truth = visible_points(scene, points, TOLERANCE)
        for method, fn in methods.items():
            kept, ms = timed(fn, points)
            external_ms[method].append(ms)
            external[method]["all"].add(kept, truth)
            external[method]["inserted"].add(kept[is_inserted], truth[is_inserted])
            external[method]["original"].add(kept[~is_inserted], truth[~is_inserted])
        print(
            f"frame {index}: {len(frame)} frame points, {len(samples)} objects, "
            f"{int(is_inserted.sum())} inserted points, "
            f"{int((~truth[~is_inserted]).sum())} frame points hidden by them",
            flush=True,
        )

    report = {
        "frames": args.frames,
        "objects": placed_count,
        "spacing_m": args.spacing,
        "self_hpr": {
            **self_all.to_dict(),
            "ms_median": round(statistics.median(self_ms), 3) if self_ms else None,
            "by_class": {name: s.to_dict() for name, s in self_score.items()},
        },
        "external": {
            method: {
                **{k: s.to_dict() for k, s in scores.items()},
                "ms_median": round(statistics.median(external_ms[method]), 1),
            }
            for method, scores in external.items()
        },
    }
    print(f"\ns-HPR (R = diagonal x {SELF_RADIUS_FACTOR:g}) vs self-visibility truth:")
    print(f"  all: {self_all.to_dict()}")
    for name, s in self_score.items():
        print(f"  {name}: {s.to_dict()}")
    print("\nexternal occlusion vs ray-cast truth (precision / recall of kept points):")
    for method, scores in external.items():
        parts = ", ".join(
            f"{k} {s.to_dict()['precision']:.3f}/{s.to_dict()['recall']:.3f}"
            for k, s in scores.items()
        )
        print(f"  {method}: {parts}; {statistics.median(external_ms[method]):.0f} ms")
    print(json.dumps(report))


if __name__ == "__main__":
    main()
