"""Time HPR's methods side by side on inputs that crowd the per-point test's neighbourhoods.

A dense object far smaller than its HPR neighbourhoods (30,000 points on a 0.1 m sphere 10 m
away, R = 100) and 30,000 copies of one point: the per-point test ("local") is quadratic on
them, so "auto" sends them to one hull. Prints one line per input with the CPU seconds of each
method and whether their visible sets agree; ``--local`` adds the plain per-point test (tens of
seconds on a busy core).

Usage: ``python benchmarks/bench_hpr_crowded.py [--points 30000] [--local]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from drcpo.occlusion import hidden_point_removal


def scenes(count: int) -> dict[str, tuple[np.ndarray, float]]:
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    sphere = (directions * 0.1 + [10.0, 0.0, 0.0]).astype(np.float32)
    copies = np.tile(np.float32([[10.0, 2.0, -1.0]]), (count, 1))
    return {"tiny sphere, R=100": (sphere, 100.0), "copies of one point, R=100": (copies, 100.0)}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=30000)
    parser.add_argument("--local", action="store_true", help="also time method='local'")
    args = parser.parse_args(argv)
    methods = ["reference", "auto", *(["local"] if args.local else [])]
    hidden_point_removal(np.eye(4, 3) + 1.0, method="reference")  # compile outside the timing
    for name, (points, radius) in scenes(args.points).items():
        seconds, answers = {}, {}
        for method in methods:
            start = time.process_time()
            answers[method] = hidden_point_removal(points, radius=radius, method=method)
            seconds[method] = time.process_time() - start
        agree = all(np.array_equal(answers[m], answers["reference"]) for m in methods)
        timings = "  ".join(f"{m} {s:7.3f} s" for m, s in seconds.items())
        print(f"{name:28s} {len(points)} points  {timings}  same visible set: {agree}")


if __name__ == "__main__":
    main()
