"""Paired comparison of two arms: mean AP difference with a 95 % bootstrap interval over seeds
and validation frames, and a verdict.

Both sources of noise are resampled together: each replicate draws seeds with replacement
(a run's initialisation, frame order and augmentation draws) and validation frames with
replacement (which objects the detectors are tested on), and scores both arms on the *same*
draws, so what the two arms share (hard frames, a lucky seed) cancels in the difference.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: ``score(seed_index, frame_weights) -> float (K,)``: an arm's AP (per class, ...) for one
#: seed's run on the validation frames drawn ``frame_weights[f]`` times each.
Score = Callable[[int, np.ndarray], np.ndarray]

CONFIDENCE = 0.95
VERDICTS = ("better", "no difference", "worse")


@dataclass(frozen=True)
class Difference:
    """``a - b`` for one quantity: the mean over seeds on every frame, the interval's ends and
    the verdict (``better``: the interval above 0, ``worse``: below, else ``no difference``)."""

    mean: float
    low: float
    high: float

    @property
    def verdict(self) -> str:
        if self.low > 0:
            return "better"
        if self.high < 0:
            return "worse"
        return "no difference"

    def to_dict(self) -> dict[str, float | str]:
        return {
            "mean": round(self.mean, 2),
            "low": round(self.low, 2),
            "high": round(self.high, 2),
            "verdict": self.verdict,
        }


def paired_bootstrap(
    score_a: Score,
    score_b: Score,
    seeds: int,
    frames: int,
    rng: np.random.Generator,
    replicates: int = 1000,
) -> list[Difference]:
    """Per quantity ``k``, the paired difference ``a - b`` (see the module docstring).

    Replicate ``r`` draws ``seeds`` seed indices and a multinomial count per frame (``frames``
    draws), then takes the mean over the drawn seeds of ``score_a - score_b``; the interval is
    the replicates' central :data:`CONFIDENCE` range.
    """
    if seeds < 1 or frames < 1 or replicates < 1:
        raise ValueError("paired_bootstrap needs at least one seed, frame and replicate")
    every = np.ones(frames, dtype=np.int64)
    delta = np.array([score_a(s, every) - score_b(s, every) for s in range(seeds)])
    point = delta.mean(axis=0)
    samples = np.empty((replicates, len(point)))
    uniform = np.full(frames, 1.0 / frames)
    for r in range(replicates):
        picked = rng.integers(0, seeds, size=seeds)
        weights = rng.multinomial(frames, uniform)
        cache: dict[int, np.ndarray] = {}
        for s in picked:
            if s not in cache:
                cache[s] = score_a(int(s), weights) - score_b(int(s), weights)
        samples[r] = np.mean([cache[s] for s in picked], axis=0)
    tail = (1 - CONFIDENCE) / 2 * 100
    low, high = np.percentile(samples, [tail, 100 - tail], axis=0)
    return [
        Difference(float(m), float(lo), float(hi))
        for m, lo, hi in zip(point, low, high, strict=True)
    ]
