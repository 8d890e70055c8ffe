"""Benchmark: hidden point removal on whole KITTI frames, ours against Open3D, side by side.

For each whole-frame HPR fixture (``../shared/fixtures/hpr/frame*.npz``: points, viewpoint,
radius and Open3D's visible set) it times, in the same run and interleaved so that load from
other processes hits both alike:

* ``ours``: ``drcpo.occlusion.hidden_point_removal`` with its defaults (``method="auto"``),
* ``open3d``: ``open3d.geometry.PointCloud.hidden_point_removal`` (when open3d imports; install
  the ``bench`` extra),

and, for the record, each of our methods on its own (``reference`` = one Qhull hull,
``local``). Every result is checked against the fixture's visible set
(Jaccard index). Without the fixtures it runs on a sweep of drcpo's synthetic LiDAR world.

Objects (s-HPR): on the object fixtures (``object*.npz``, else synthetic box-shaped objects) it
times ``method="reference"`` as s-HPR runs it (:mod:`drcpo.occlusion.hull`'s certified hull)
against the plain Qhull hull, interleaved, in CPU milliseconds per object, and checks that both
give the same points (and the fixture's).

Usage::

    python benchmarks/bench_hpr.py [--quick] [--repeats N] [--fixtures DIR]

The last line of stdout is one JSON object::

    {"frames": [{"name": ..., "points": n, "ours_ms": x, "open3d_ms": y, "speedup": y / x,
                 "jaccard": j, "methods_ms": {...}}, ...],
     "objects": {"objects": n, "certified_ms": a, "qhull_ms": b, "speedup": b / a, ...}}
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from drcpo.occlusion import hidden_point_removal, hpr

DEFAULT_FIXTURES = Path(__file__).resolve().parents[2] / "shared" / "fixtures" / "hpr"
VARIANTS = {
    "reference": {"method": "reference"},
    "local": {"method": "local"},
}


def load_frames(directory: Path, quick: bool) -> list[dict]:
    """Whole-frame fixtures, or a synthetic scene when there are none."""
    paths = sorted(directory.glob("frame*.npz")) if directory.is_dir() else []
    frames = []
    for path in paths[:1] if quick else paths:
        with np.load(path, allow_pickle=False) as data:
            visible = np.zeros(len(data["points"]), dtype=bool)
            visible[data["visible"]] = True
            frames.append(
                {
                    "name": path.stem,
                    "points": np.ascontiguousarray(data["points"], dtype=np.float64),
                    "viewpoint": np.asarray(data["viewpoint"], dtype=np.float64),
                    "radius": float(data["radius"]),
                    "expected": visible,
                }
            )
    if not frames:
        print(f"no fixtures under {directory}: timing a synthetic LiDAR sweep instead")
        frames.append(synthetic_frame(np.random.default_rng(0)))
    return frames


def synthetic_frame(rng: np.random.Generator) -> dict:
    """A sweep of drcpo's synthetic LiDAR world, range-filtered to 70 m like the KITTI fixtures,
    seen from the sensor with the PV-RCNN setting (no Open3D answer to compare with)."""
    from drcpo.synth.dataset import synthesize_frame

    points = synthesize_frame(rng).sweep.points[:, :3].astype(np.float64)
    points = points[np.linalg.norm(points, axis=1) < 70.0]
    return {
        "name": f"synthetic_{len(points)}",
        "points": points,
        "viewpoint": np.zeros(3),
        "radius": 1e5,
        "expected": None,
    }


def open3d_runner(frame: dict) -> Callable[[], np.ndarray] | None:
    """A call of Open3D's HPR on the frame returning a visible mask, or ``None`` without open3d."""
    try:
        import open3d as o3d
    except ImportError:  # also raised when its shared libraries are missing
        return None
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(frame["points"]))
    count = len(frame["points"])

    def run() -> np.ndarray:
        _, indices = cloud.hidden_point_removal(frame["viewpoint"], frame["radius"])
        mask = np.zeros(count, dtype=bool)
        mask[np.asarray(indices, dtype=np.int64)] = True
        return mask

    return run


def timed(run: Callable[[], np.ndarray]) -> tuple[float, np.ndarray]:
    start = time.perf_counter()
    result = run()
    return (time.perf_counter() - start) * 1e3, result


def jaccard(a: np.ndarray, b: np.ndarray | None) -> float | None:
    if b is None:
        return None
    return float((a & b).sum() / max(1, (a | b).sum()))


def bench_frame(frame: dict, repeats: int, variant_repeats: int) -> dict:
    def ours() -> np.ndarray:
        return hidden_point_removal(frame["points"], frame["viewpoint"], frame["radius"])

    theirs = open3d_runner(frame)
    ours()  # warm-up: loads the compiled kernels
    if theirs is not None:
        theirs()
    ours_ms, open3d_ms = [], []
    mask = theirs_mask = None
    for _ in range(repeats):  # interleaved, so both see the same machine load
        elapsed, mask = timed(ours)
        ours_ms.append(elapsed)
        if theirs is not None:
            elapsed, theirs_mask = timed(theirs)
            open3d_ms.append(elapsed)
    methods_ms, agreement = {}, {}
    for label, options in VARIANTS.items():
        samples = []
        for _ in range(variant_repeats):
            elapsed, result = timed(
                lambda o=options: hidden_point_removal(
                    frame["points"], frame["viewpoint"], frame["radius"], **o
                )
            )
            samples.append(elapsed)
        methods_ms[label] = round(statistics.median(samples), 2)
        agreement[label] = jaccard(result, frame["expected"])
    ours_median = statistics.median(ours_ms)
    open3d_median = statistics.median(open3d_ms) if open3d_ms else None
    return {
        "name": frame["name"],
        "points": len(frame["points"]),
        "ours_ms": round(ours_median, 2),
        "open3d_ms": None if open3d_median is None else round(open3d_median, 2),
        "speedup": None if open3d_median is None else round(open3d_median / ours_median, 2),
        "jaccard": jaccard(mask, frame["expected"]),
        "jaccard_open3d_now": None if theirs_mask is None else jaccard(mask, theirs_mask),
        "methods_ms": methods_ms,
        "methods_jaccard": agreement,
    }


def load_objects(directory: Path, quick: bool) -> list[dict]:
    """Object fixtures (points, viewpoint, radius, Open3D's answer), or synthetic objects."""
    paths = sorted(directory.glob("object*.npz")) if directory.is_dir() else []
    objects = []
    for path in paths[:3] if quick else paths:
        with np.load(path, allow_pickle=False) as data:
            visible = np.zeros(len(data["points"]), dtype=bool)
            visible[data["visible"]] = True
            objects.append(
                {
                    "points": np.ascontiguousarray(data["points"], dtype=np.float64),
                    "viewpoint": np.asarray(data["viewpoint"], dtype=np.float64),
                    "radius": float(data["radius"]),
                    "expected": visible,
                }
            )
    if not objects:
        rng = np.random.default_rng(0)
        for _ in range(3 if quick else 20):
            count = int(rng.integers(100, 1500))
            dims = rng.uniform([0.5, 0.5, 1.0], [5.0, 2.5, 3.0])
            local = rng.uniform(-0.5, 0.5, (count, 3)) * dims
            face = rng.integers(0, 3, count)
            local[np.arange(count), face] = rng.choice([-0.5, 0.5], count) * dims[face]
            centre = [rng.uniform(5.0, 50.0), rng.uniform(-20.0, 20.0), -1.0]
            objects.append(
                {
                    "points": local + centre,
                    "viewpoint": np.zeros(3),
                    "radius": 200.0 * float(np.linalg.norm(dims)),
                    "expected": None,
                }
            )
    return objects


def bench_objects(objects: list[dict], repeats: int) -> dict:
    """CPU ms per object: s-HPR's ``"reference"`` (certified hull) against Qhull alone."""

    def run_all() -> list[np.ndarray]:
        return [
            hidden_point_removal(o["points"], o["viewpoint"], o["radius"], method="reference")
            for o in objects
        ]

    kernel_max = hpr.HULL_KERNEL_MAX
    samples: dict[str, list[float]] = {"certified": [], "qhull": []}
    answers = {}
    try:
        for _ in range(repeats):  # interleaved, so both see the same machine load
            for label, limit in (("certified", kernel_max), ("qhull", 0)):
                hpr.HULL_KERNEL_MAX = limit
                start = time.process_time()
                answers[label] = run_all()
                samples[label].append((time.process_time() - start) * 1e3 / len(objects))
    finally:
        hpr.HULL_KERNEL_MAX = kernel_max
    certified, qhull = (statistics.median(samples[k]) for k in ("certified", "qhull"))
    return {
        "objects": len(objects),
        "mean_points": round(float(np.mean([len(o["points"]) for o in objects])), 1),
        "certified_ms": round(certified, 3),
        "qhull_ms": round(qhull, 3),
        "speedup": round(qhull / certified, 2),
        "same_as_qhull": all(
            np.array_equal(a, b)
            for a, b in zip(answers["certified"], answers["qhull"], strict=True)
        ),
        "same_as_fixture": None
        if objects[0]["expected"] is None
        else all(
            np.array_equal(a, o["expected"])
            for a, o in zip(answers["certified"], objects, strict=True)
        ),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="one frame, few repeats (smoke test)")
    parser.add_argument("--repeats", type=int, default=None, help="timed runs of ours and Open3D")
    parser.add_argument("--fixtures", type=Path, default=DEFAULT_FIXTURES)
    args = parser.parse_args()
    repeats = args.repeats or (2 if args.quick else 9)
    variant_repeats = 1 if args.quick else 3
    results = []
    for frame in load_frames(args.fixtures, args.quick):
        row = bench_frame(frame, repeats, variant_repeats)
        results.append(row)
        open3d = (
            "open3d not importable"
            if row["open3d_ms"] is None
            else (f"open3d {row['open3d_ms']:.1f} ms, speed-up {row['speedup']:.1f}x")
        )
        print(
            f"{row['name']}: {row['points']} points, ours {row['ours_ms']:.1f} ms, {open3d}, "
            f"Jaccard vs fixture {row['jaccard']}, vs Open3D now {row['jaccard_open3d_now']}"
        )
        for label, ms in row["methods_ms"].items():
            print(f"    {label:>18}: {ms:8.1f} ms  Jaccard {row['methods_jaccard'][label]}")
    objects = bench_objects(load_objects(args.fixtures, args.quick), 3 if args.quick else 15)
    print(
        f"objects (s-HPR): {objects['objects']} of {objects['mean_points']} points on average, "
        f"certified hull {objects['certified_ms']:.3f} ms, Qhull {objects['qhull_ms']:.3f} ms "
        f"CPU per object, speed-up {objects['speedup']:.1f}x; same as Qhull: "
        f"{objects['same_as_qhull']}, as the fixtures: {objects['same_as_fixture']}"
    )
    print(json.dumps({"frames": results, "objects": objects}))


if __name__ == "__main__":
    main()
