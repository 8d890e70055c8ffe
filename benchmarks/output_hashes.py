"""Fingerprint augmented outputs: sha256 of points, boxes and names of fixed-seed frames.

Run before and after a change that must not alter valid outputs; the printed digests must match.
The database is the quick synthetic one of ``bench_augment.py`` (indexed with a small K), the
frames the built-in synthetic world; frame ``i`` is augmented with seed ``i`` by the baseline
(CDA) and the DR.CPO pipeline, each with the paper defaults. With ``--source kitti``, frame
``i`` is KITTI sample frame ``i % 6`` (``../shared/data/kitti_sample``), cut to the camera's view.

Usage: ``python benchmarks/output_hashes.py [--frames 20] [--work DIR]``
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_augment import (
    QUICK_COUNTS,
    database_and_index,
    kitti_frames,
    synthetic_frames,
)

from drcpo.pipeline import build_pipeline


def digest(frame) -> str:
    """sha256 of the frame's points, boxes and names bytes (shapes and dtypes included)."""
    h = hashlib.sha256()
    for array in (frame.points, frame.boxes, frame.names):
        array = np.ascontiguousarray(array)
        h.update(f"{array.dtype.str}{array.shape}".encode())
        h.update(array.tobytes())
    return h.hexdigest()


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--work", type=Path, help="keep the database and index here")
    parser.add_argument(
        "--source", choices=("synth", "kitti"), default="synth", help="frames (kitti: 6 frames)"
    )
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="output_hashes_") as scratch:
        work = args.work or Path(scratch)
        work.mkdir(parents=True, exist_ok=True)
        database, index, _ = database_and_index(QUICK_COUNTS, 20, work)
        if args.source == "kitti":
            frames = kitti_frames(6)
            frames = [frames[i % len(frames)] for i in range(args.frames)]
        else:
            frames = synthetic_frames(args.frames)
        total = hashlib.sha256()
        for kind in ("cda", "drcpo"):
            pipeline = build_pipeline("default", database, index, kind=kind)
            for seed, frame in enumerate(frames):
                value = digest(pipeline(frame, np.random.default_rng(seed)))
                total.update(value.encode())
                print(f"{kind} frame {seed:2d} seed {seed:2d} {value}")
    print(f"all {total.hexdigest()}")
    return total.hexdigest()


if __name__ == "__main__":
    main()
