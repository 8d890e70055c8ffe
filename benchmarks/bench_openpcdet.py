"""Per-sample time of OpenPCDet's KITTI training pipeline with its default augmentation and with
a ``drcpo`` entry, measured in the same run, as a DataLoader worker runs it (one thread).

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_openpcdet.py [--rounds 5] [--db DIR]

Needs the framework environment (``pip install -e ".[test,openpcdet]"``) and ``../shared``
(OpenPCDet snapshot, KITTI sample); OpenPCDet's CUDA ops run as the tests' CPU stand-ins. The
samples alternate between the two pipelines, each frame with the same numpy seed. Also reports
drcpo's first call in freshly forked workers after the warm-up the augmentor does when built.
"""
# ruff: noqa: NPY002

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads its BLAS

import argparse
import logging
import multiprocessing
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import openpcdet_support as support


def _dataset(entry):
    from pcdet.datasets.kitti.kitti_dataset import KittiDataset

    cfg = support.dataset_config(entry)
    return KittiDataset(
        cfg, support.CLASS_NAMES, True, support.KITTI_SAMPLE, logging.getLogger("bench")
    )


def _timed_drcpo(dataset, spent: list[float]) -> None:
    from drcpo.integrations.openpcdet import OpenPCDetAugmentor

    queue = dataset.data_augmentor.data_augmentor_queue
    for i, augmentor in enumerate(queue):
        if isinstance(augmentor, OpenPCDetAugmentor):

            def timed(data_dict, augmentor=augmentor):
                start = time.perf_counter()
                out = augmentor(data_dict=data_dict)
                spent.append(time.perf_counter() - start)
                return out

            queue[i] = timed


def _child(dataset, queue) -> None:
    import torch

    torch.set_num_threads(1)
    spent: list[float] = []
    _timed_drcpo(dataset, spent)
    np.random.seed(0)
    dataset[0]
    queue.put(spent[0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5, help="passes over the 6 sample frames")
    parser.add_argument("--workers", type=int, default=3, help="forked workers to time")
    parser.add_argument("--db", type=Path, default=None, help="drcpo database of the sample")
    parser.add_argument("--no-warmup", action="store_true", help="build the entry with WARMUP off")
    args = parser.parse_args()

    import torch

    torch.set_num_threads(1)
    support.install()
    from drcpo.integrations import openpcdet

    openpcdet.register()
    with tempfile.TemporaryDirectory() as tmp:
        db = args.db or support.sample_database(Path(tmp) / "drcpo_db")
        default = _dataset(None)
        start = time.perf_counter()
        ours = _dataset({"NAME": "drcpo", "DB_PATH": str(db), "WARMUP": not args.no_warmup})
        built = time.perf_counter() - start
        context = multiprocessing.get_context("fork")
        firsts = []
        for _ in range(args.workers):
            queue = context.Queue()
            worker = context.Process(target=_child, args=(ours, queue))
            worker.start()
            firsts.append(queue.get(timeout=300))
            worker.join()
        drcpo_spent: list[float] = []
        _timed_drcpo(ours, drcpo_spent)
        times: dict[str, list[float]] = {"default": [], "drcpo": []}
        for round_ in range(args.rounds):
            for index in range(len(default)):
                for name, dataset in (("default", default), ("drcpo", ours)):
                    np.random.seed(1000 * round_ + index)
                    start = time.perf_counter()
                    dataset[index]
                    times[name].append(time.perf_counter() - start)
    ms = {k: 1000.0 * float(np.median(v)) for k, v in times.items()}
    print(f"samples per pipeline: {len(times['default'])} (OPENBLAS_NUM_THREADS=1, torch 1 thread)")
    print(f"median per sample, OpenPCDet default augmentation: {ms['default']:.1f} ms")
    print(f"median per sample, with the drcpo entry:           {ms['drcpo']:.1f} ms")
    print(
        f"median of the drcpo augmentor call alone:          {1000 * np.median(drcpo_spent):.1f} ms"
    )
    print(f"augmentor built (incl. warm-up) in {built:.2f} s")
    print(
        f"first drcpo call in a freshly forked worker ({'no ' if args.no_warmup else ''}warm-up): "
        + ", ".join(f"{1000 * s:.1f} ms" for s in firsts)
    )


if __name__ == "__main__":
    main()
