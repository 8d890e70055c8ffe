"""The detection benchmark's paired statistics (benchmarks/detection/stats.py) on hand figures:
scores whose bootstrap distribution is known without running it."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from detection.stats import Difference, paired_bootstrap


def _per_frame(values: list[list[float]]):
    """A score that is the weighted mean of per-frame values ``values[seed][frame]``."""
    table = np.asarray(values, dtype=np.float64)

    def score(seed: int, weights: np.ndarray) -> np.ndarray:
        return np.array([table[seed] @ weights / weights.sum()])

    return score


def test_a_constant_lead_is_better_with_an_interval_of_its_size():
    base = [[10.0, 20.0, 30.0, 40.0], [12.0, 18.0, 33.0, 41.0]]
    lead = [[v + 2.0 for v in row] for row in base]
    [d] = paired_bootstrap(_per_frame(lead), _per_frame(base), 2, 4, np.random.default_rng(0))
    assert d.mean == pytest.approx(2.0) and d.low == pytest.approx(2.0)
    assert d.high == pytest.approx(2.0) and d.verdict == "better"
    [d] = paired_bootstrap(_per_frame(base), _per_frame(lead), 2, 4, np.random.default_rng(0))
    assert d.mean == pytest.approx(-2.0) and d.verdict == "worse"


def test_frames_that_disagree_give_no_difference():
    # frame differences +1, -1, +1, -1: the mean is 0, a draw of frames moves it either way
    base = [[10.0, 10.0, 10.0, 10.0]]
    mixed = [[11.0, 9.0, 11.0, 9.0]]
    [d] = paired_bootstrap(_per_frame(mixed), _per_frame(base), 1, 4, np.random.default_rng(1))
    assert d.mean == pytest.approx(0.0) and d.low < 0 < d.high
    assert d.verdict == "no difference" and -1.0 <= d.low and d.high <= 1.0
    # the 95 % range of the mean of 4 draws of +-1: both ends reached (all four alike: 1/8)
    assert d.low == pytest.approx(-1.0) and d.high == pytest.approx(1.0)


def test_seeds_that_disagree_give_no_difference_though_every_frame_agrees():
    base = [[10.0] * 5] * 3
    arm = [[13.0] * 5, [7.0] * 5, [10.5] * 5]  # seeds +3, -3, +0.5; every frame alike
    [d] = paired_bootstrap(_per_frame(arm), _per_frame(base), 3, 5, np.random.default_rng(2))
    assert d.mean == pytest.approx(0.5 / 3)
    assert d.low == pytest.approx(-3.0) and d.high == pytest.approx(3.0)  # all-one-seed draws
    assert d.verdict == "no difference"


def test_pairs_share_the_draw_so_shared_noise_cancels():
    # hard and easy frames swing both arms by 30 AP; the arm leads by 1 on every frame
    rng = np.random.default_rng(3)
    swing = rng.uniform(0, 30, size=50)
    base = [list(swing), list(swing + 5)]
    arm = [list(swing + 1), list(swing + 6)]
    [d] = paired_bootstrap(_per_frame(arm), _per_frame(base), 2, 50, np.random.default_rng(4))
    assert d.verdict == "better" and d.low == pytest.approx(1.0) and d.high == pytest.approx(1.0)


def test_several_quantities_and_bad_arguments():
    def score_a(seed, weights):
        return np.array([1.0, 0.0, -1.0])

    def score_b(seed, weights):
        return np.zeros(3)

    found = paired_bootstrap(score_a, score_b, 2, 3, np.random.default_rng(0), replicates=20)
    assert [d.verdict for d in found] == ["better", "no difference", "worse"]
    assert Difference(1.234, -0.5, 2.0).to_dict() == {
        "mean": 1.23, "low": -0.5, "high": 2.0, "verdict": "no difference"
    }  # fmt: skip
    with pytest.raises(ValueError, match="at least one seed"):
        paired_bootstrap(score_a, score_b, 0, 3, np.random.default_rng(0))
