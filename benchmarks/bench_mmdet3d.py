"""Per-sample time of MMDetection3D's KITTI training pipeline with its default augmentation
(``ObjectSample``) and with ``DRCPOAugment`` in its place, measured in the same run, as a data
loader worker runs it (one thread).

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_mmdet3d.py [--rounds 5]

Needs the MMDetection3D environment (.ci/run's third step) and ``../shared`` (KITTI sample).
Both pipelines are mmdet3d's KITTI 3-class train pipeline (tests/mmdet3d_support.py); ObjectSample
draws from an mmdet3d database written from the sample's OpenPCDet one, DRCPOAugment from the
drcpo import of it. The samples alternate between the two, each frame with the same seed.
"""
# ruff: noqa: NPY002

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads its BLAS

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import mmdet3d_support as support
import openpcdet_support as pcdet_support


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5, help="passes over the 6 sample frames")
    args = parser.parse_args()

    import torch

    torch.set_num_threads(1)
    support.install()
    from mmengine.registry import DefaultScope

    import drcpo.integrations.mmdet3d  # registers DRCPOAugment

    DefaultScope.get_instance("drcpo-bench", scope_name="mmdet3d")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        infos = support.write_mmdet3d_infos(support.KITTI_SAMPLE, tmp / "kitti_infos_train.pkl")
        db = pcdet_support.sample_database(tmp / "drcpo_db")
        default = support.dataset(infos, support.pipeline(support.object_sample(tmp)))
        start = time.perf_counter()
        drcpo = dict(type="DRCPOAugment", db_path=str(db), classes=support.CLASS_NAMES)
        ours = support.dataset(infos, support.pipeline(drcpo))
        built = time.perf_counter() - start
        times: dict[str, list[float]] = {"default": [], "drcpo": []}
        for round_ in range(args.rounds):
            for index in range(len(default)):
                for name, dataset in (("default", default), ("drcpo", ours)):
                    np.random.seed(1000 * round_ + index)
                    torch.manual_seed(1000 * round_ + index)
                    start = time.perf_counter()
                    dataset[index]
                    times[name].append(time.perf_counter() - start)
    ms = {k: 1000.0 * float(np.median(v)) for k, v in times.items()}
    print(f"samples per pipeline: {len(times['default'])} (OPENBLAS_NUM_THREADS=1, torch 1 thread)")
    print(f"median per sample, mmdet3d default augmentation (ObjectSample): {ms['default']:.1f} ms")
    print(f"median per sample, with DRCPOAugment in its place:             {ms['drcpo']:.1f} ms")
    print(f"building the DRCPOAugment dataset (with the warm-up): {built:.1f} s")


if __name__ == "__main__":
    main()
