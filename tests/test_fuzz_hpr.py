"""Property-based fuzzing of hidden point removal on random and degenerate geometry.

Every method either answers (a ``bool (N,)`` mask, the same set as every other method where
they are meant to agree: ``R`` within :data:`AGREE_RATIO` of the ranges, which keeps Qhull's
flipped coordinates precise) or raises :class:`DataError` / :class:`ConfigError` on invalid
input; never a crash or another exception. Cases per test: ``DRCPO_FUZZ_EXAMPLES``
(``fuzz_settings.py``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from fuzz_settings import FUZZ
from hypothesis import given
from hypothesis import strategies as st

from drcpo import occlusion
from drcpo.errors import ConfigError, DataError
from drcpo.occlusion import HPR_METHODS, hidden_point_removal, self_occlusion

AGREE_RATIO = 1e6  # R / largest range up to which Qhull (reference) and the exact tests agree
# Nearly degenerate sets (collinear or coplanar up to rounding): whether a point sits a hair
# off a common line or plane, within Qhull's roundoff, decides its verdict, and the methods
# may settle such a tie differently. Only the outcome's form is checked on them; exactly
# degenerate sets (integer lattices, exact rays, the plane z = 0) must agree.
ROUNDED = ("collinear", "ray", "coplanar")
KINDS = (
    "random",
    "duplicates",
    *ROUNDED,
    "exact_ray",
    "flat_with_viewpoint",
    "lattice",
    "tiny",
    "huge",
    "dense_blob",
    "at_viewpoint",
)


def _geometry(kind: str, rng: np.random.Generator, n: int) -> np.ndarray:
    """``(n, 3)`` float64 points of one kind of (often degenerate) geometry."""
    if kind == "duplicates":
        base = rng.normal(0, 5, (max(1, n // 4), 3))
        return base[rng.integers(0, len(base), n)]
    if kind == "collinear":
        return rng.normal(0, 5, 3) + np.outer(rng.uniform(-3, 3, n), rng.normal(size=3))
    if kind == "ray":  # collinear with the viewpoint (the origin)
        return np.outer(rng.uniform(0.5, 20, n), rng.normal(size=3))
    if kind == "exact_ray":  # integer multiples of an integer direction: exactly collinear
        return np.outer(rng.integers(1, 9, n), rng.integers(-3, 4, 3)).astype(np.float64)
    if kind == "coplanar":
        u, v = rng.normal(size=(2, 3))
        return (
            rng.normal(0, 5, 3) + np.outer(rng.normal(size=n), u) + np.outer(rng.normal(size=n), v)
        )
    if kind == "flat_with_viewpoint":  # the plane z = 0 holds the viewpoint too
        return np.column_stack([rng.normal(5, 3, (n, 2)), np.zeros(n)])
    if kind == "lattice":
        return rng.integers(-3, 4, (n, 3)).astype(np.float64)
    if kind == "tiny":
        return rng.normal(size=(n, 3)) * 1e-6 + rng.normal(0, 1e-5, 3)
    if kind == "huge":
        return rng.normal(size=(n, 3)) * 1e12
    if kind == "dense_blob":
        return rng.normal(size=(n, 3)) * 1e-3 + [10.0, 0.0, 0.0]
    if kind == "at_viewpoint":
        points = rng.normal(0, 5, (n, 3))
        points[rng.random(n) < 0.3] = 0.0
        return points
    return rng.normal(0, 5, (n, 3)) * rng.uniform(0.1, 3, 3) + rng.normal(0, 5, 3)


@st.composite
def hpr_cases(draw):
    kind = draw(st.sampled_from(KINDS))
    n = draw(st.integers(0, 80))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    points = _geometry(kind, rng, n)
    if draw(st.booleans()):
        points = np.column_stack([points, rng.random(n)])  # a feature column (ignored)
    dtype = draw(st.sampled_from([np.float64, np.float32]))
    points = points.astype(dtype)
    bad = draw(st.sampled_from([None] * 6 + ["nan", "inf", "-inf"]))
    if bad and n:
        points[rng.integers(0, n), rng.integers(0, 3)] = float(bad)
    reach = float(np.linalg.norm(points[:, :3].astype(np.float64), axis=1).max(initial=0.0))
    special = draw(st.sampled_from([None] * 8 + [0.0, -1.0, math.nan, math.inf]))
    if special is None:
        radius = max(reach, 1e-3) * 10 ** draw(st.floats(-0.5, 8.0))
    else:
        radius = special
    return kind, points, float(radius), bad


def _expected_error(points: np.ndarray, radius: float) -> type[Exception] | None:
    if not np.isfinite(points[:, :3]).all():
        return DataError
    if not (math.isfinite(radius) and 0 < radius <= occlusion.MAX_RADIUS):
        return ConfigError
    return None


@FUZZ
@given(case=hpr_cases(), query_seed=st.integers(0, 2**16))
def test_hpr_methods_agree_or_refuse(case, query_seed):
    kind, points, radius, _ = case
    error = _expected_error(points, radius)
    answers = {}
    for method in HPR_METHODS:
        if error is not None:
            with pytest.raises(error):
                hidden_point_removal(points, radius=radius, method=method)
            continue
        visible = hidden_point_removal(points, radius=radius, method=method)
        assert visible.dtype == bool and visible.shape == (len(points),), (kind, method)
        answers[method] = visible
    if error is not None:
        return
    reach = float(np.linalg.norm(points[:, :3].astype(np.float64), axis=1).max(initial=0.0))
    if radius <= AGREE_RATIO * max(reach, 1e-300) and kind not in ROUNDED:
        for method, visible in answers.items():
            assert np.array_equal(visible, answers["reference"]), (kind, method, radius)
    # a query decides only the asked points, each as the whole-set answer does
    query = np.random.default_rng(query_seed).random(len(points)) < 0.5
    for method in ("auto", "local"):
        got = hidden_point_removal(points, radius=radius, method=method, query=query)
        assert got[~query].all()
        assert np.array_equal(got[query], answers[method][query]), (kind, method)


@FUZZ
@given(case=hpr_cases(), factor=st.floats(1.0, 1e4))
def test_self_occlusion_answers_or_refuses(case, factor):
    _, points, _, bad = case
    box = np.array([0.0, 0.0, 0.0, 2.0, 1.0, 1.5, 0.3])
    if bad and len(points):
        with pytest.raises(DataError):
            self_occlusion(points, box, factor)
        return
    visible = self_occlusion(points, box, factor)
    assert visible.dtype == bool and visible.shape == (len(points),)
    with pytest.raises(DataError, match="no extent"):
        self_occlusion(points, np.zeros(7), factor)
