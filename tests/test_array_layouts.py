"""Array layouts at the transform boundary: a :class:`~drcpo.frame.Frame` holds C-contiguous,
writeable points and boxes whatever layout a framework hands over (Fortran-ordered, sliced,
float64, read-only), so the compiled kernels are only ever called with the one layout that
:func:`drcpo.warmup` loads, and the output does not depend on the layout."""

from __future__ import annotations

import json
import multiprocessing
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from kernel_support import loaded_kernels
from test_pipeline import synthetic_database, synthetic_frame

import drcpo
from drcpo.frame import Frame
from drcpo.index import IndexConfig
from drcpo.index_build import build_index
from drcpo.pipeline import build_pipeline


def _read_only(values: np.ndarray) -> np.ndarray:
    out = values.copy()
    out.flags.writeable = False
    return out


def _sliced(values: np.ndarray) -> np.ndarray:
    """The same values as a strided view: every other row of a wider array, first columns."""
    wide = np.zeros((2 * len(values), values.shape[1] + 2), dtype=values.dtype)
    wide[::2, : values.shape[1]] = values
    return wide[::2, : values.shape[1]]


#: The layouts a framework may hand over, each with the same values as the C-ordered original.
LAYOUTS = {
    "fortran": np.asfortranarray,
    "sliced": _sliced,
    "float64": lambda a: a.astype(np.float64),
    "read_only": _read_only,
}


def _variant(frame: Frame, layout: str) -> dict:
    """``frame`` as an OpenPCDet-style dict with points and boxes in ``layout``."""
    convert = LAYOUTS[layout]
    return {
        **frame.metadata,
        "points": convert(frame.points),
        "gt_boxes": convert(frame.boxes),
        "gt_names": frame.names,
    }


@pytest.fixture(scope="module")
def pipeline():
    db = synthetic_database(np.random.default_rng(7), {"Car": 40, "Pedestrian": 20, "Cyclist": 10})
    return build_pipeline("default", db, build_index(db, IndexConfig(k=10)))


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_frames_hold_c_contiguous_writeable_arrays(layout, rng):
    frame = synthetic_frame(rng)
    made = Frame.from_dict(_variant(frame, layout))
    for array, dtype in ((made.points, np.float32), (made.boxes, np.float64)):
        assert array.flags.c_contiguous and array.flags.writeable and array.dtype == dtype
    np.testing.assert_array_equal(made.points, frame.points)
    np.testing.assert_array_equal(made.boxes, frame.boxes)


def test_c_contiguous_input_is_not_copied(rng):
    frame = synthetic_frame(rng)
    assert Frame(frame.points, frame.boxes, frame.names).points is frame.points
    assert Frame(frame.points, frame.boxes, frame.names).boxes is frame.boxes


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_drcpo_pipeline_output_is_bit_identical_for_any_layout(pipeline, layout, rng):
    frame = synthetic_frame(rng, objects=3)
    expected = pipeline(frame.to_dict(), np.random.default_rng(11))
    got = pipeline(_variant(frame, layout), np.random.default_rng(11))
    assert got["points"].dtype == np.float32 and got["gt_boxes"].dtype == np.float64
    # Bit for bit: compare the raw bytes, so that even a -0.0 against 0.0 would count.
    assert got["points"].tobytes() == expected["points"].tobytes()
    assert got["gt_boxes"].tobytes() == expected["gt_boxes"].tobytes()
    assert list(got["gt_names"]) == list(expected["gt_names"])


# Workers -------------------------------------------------------------------------------------
def _kernels_loaded_by_first_calls(pipeline, frame, queue):
    before = loaded_kernels()
    for seed, layout in enumerate(sorted(LAYOUTS)):
        pipeline(_variant(frame, layout), np.random.default_rng(seed))
    queue.put(loaded_kernels() - before)


def kernels_loaded_in_worker(warmup: bool) -> int:
    """In a fresh process: the kernels a forked worker's first calls (one per layout of
    :data:`LAYOUTS`) load, after :func:`drcpo.warmup` in the parent or without it."""
    db = synthetic_database(np.random.default_rng(7), {"Car": 40, "Pedestrian": 20, "Cyclist": 10})
    pipeline = build_pipeline("default", db, build_index(db, IndexConfig(k=10)))
    if warmup:
        drcpo.warmup(pipeline)
    frame = synthetic_frame(np.random.default_rng(3), objects=3)
    context = multiprocessing.get_context("fork")
    queue = context.Queue()
    worker = context.Process(target=_kernels_loaded_by_first_calls, args=(pipeline, frame, queue))
    worker.start()
    loaded = queue.get(timeout=300)
    worker.join(timeout=60)
    return loaded


def _in_fresh_process(warmup: bool) -> int:
    code = (
        "import json, sys; sys.path.insert(0, sys.argv[1]);"
        "import test_array_layouts as t;"
        "print(json.dumps(t.kernels_loaded_in_worker(sys.argv[2] == '1')))"
    )
    args = [sys.executable, "-c", code, str(Path(__file__).parent), str(int(warmup))]
    done = subprocess.run(args, capture_output=True, text=True, timeout=600, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_forked_worker_after_warmup_loads_no_kernel_for_other_layouts():
    """After the warm-up (on C-ordered arrays), a forked worker's first calls with Fortran-ordered,
    sliced, float64 and read-only arrays load no kernel: each would otherwise load its own
    specialisation (mmdet3d's points are Fortran-ordered). Without the warm-up the same calls
    load several, so the count is live. (In a fresh process each, so that no earlier test has
    loaded any kernel.)"""
    assert _in_fresh_process(warmup=True) == 0
    assert _in_fresh_process(warmup=False) > 0
