"""A fixed-seed fingerprint of augmented output, to prove that a change keeps behaviour.

Augments the KITTI sample (cut to the camera's view, when ``../shared`` is present) and frames
of the built-in synthetic world with every pipeline (``drcpo`` and ``cda``, the paper defaults)
over fixed seeds, and hashes each output's points, boxes, names and statistics (milliseconds
left out: they are timings, not behaviour). Record the hash before a change and compare after.

The database is bench_augment's synthetic one (small counts), so this needs no data set. The
last stdout line is one JSON object: ``{"hash": ..., "frames": n, "per_pipeline": {...}}``.

``--configs nuscenes my.yaml ...`` adds the fingerprints of more configs (presets or YAML files),
each in ``per_config`` (the ``hash`` stays that of the two pipelines).

Usage: ``python benchmarks/output_hash.py [--work DIR] [--seeds N] [--configs NAME ...]``
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_augment import (
    KITTI_SAMPLE,
    QUICK_COUNTS,
    database_and_index,
    kitti_frames,
    synthetic_frames,
)

from drcpo.pipeline import build_pipeline
from drcpo.transforms.base import without_timings


def fingerprint(frame) -> bytes:
    """The bytes that define one augmented frame: points, boxes, names and its statistics."""
    stats = without_timings(frame.metadata.get("augment_stats", {}))
    parts = [
        np.ascontiguousarray(frame.points).tobytes(),
        np.ascontiguousarray(frame.boxes).tobytes(),
        "\n".join(map(str, frame.names)).encode(),
        json.dumps(stats, sort_keys=True).encode(),
    ]
    return b"".join(hashlib.sha256(part).digest() for part in parts)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=None, help="keep the database here")
    parser.add_argument("--seeds", type=int, default=20, help="seeds per frame")
    parser.add_argument("--configs", nargs="*", default=[], help="presets or YAML files too")
    args = parser.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="drcpo_hash_"))
    database, index, _ = database_and_index(QUICK_COUNTS, 64, work)
    frames = synthetic_frames(6, seed=7)
    if KITTI_SAMPLE.is_dir():
        frames = kitti_frames(6) + frames

    def digest_of(pipeline) -> bytes:
        digest = hashlib.sha256()
        for number, frame in enumerate(frames):
            for seed in range(args.seeds):
                out = pipeline(frame, np.random.default_rng([seed, number]))
                digest.update(fingerprint(out))
        return digest.digest()

    total = hashlib.sha256()
    per_pipeline = {}
    for kind in ("drcpo", "cda"):
        digest = digest_of(build_pipeline(None, database, index, kind=kind))
        per_pipeline[kind] = digest.hex()[:16]
        total.update(digest)
    per_config = {
        name: digest_of(build_pipeline(name, database, index)).hex()[:16] for name in args.configs
    }
    result = {
        "hash": total.hexdigest()[:16],
        "frames": len(frames) * args.seeds,
        "kitti_sample": KITTI_SAMPLE.is_dir(),
        "per_pipeline": per_pipeline,
        **({"per_config": per_config} if per_config else {}),
    }
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
