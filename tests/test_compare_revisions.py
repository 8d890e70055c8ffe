"""benchmarks/compare_revisions.py: the per-pair ratios it reports, and its refusals."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "compare_revisions.py"
_spec = importlib.util.spec_from_file_location("compare_revisions", SCRIPT)
compare = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(compare)


def run(cda: float, paper: float, stages: dict[str, float]) -> dict:
    return {"cda_ms": cda, "drcpo_ms": paper, "stages_ms": stages}


def test_ratios_are_head_over_base_pair_by_pair() -> None:
    base = [run(1.0, 10.0, {"a": 2.0, "b": 1.0}), run(2.0, 20.0, {"a": 4.0, "b": 0.0})]
    head = [run(1.0, 12.0, {"a": 1.0, "b": 1.0}), run(1.0, 20.0, {"a": 3.0, "b": 1.0})]
    ratios = compare._ratios(base, head)
    assert set(ratios["pipelines"]) == {"paper", "cda"}
    assert ratios["pipelines"]["paper"] == [1.2, 1.0]
    assert ratios["pipelines"]["cda"] == [1.0, 0.5]
    # a stage's median of its pairs' ratios; one that took no time in a base run is left out
    assert ratios["stages"] == {"a": pytest.approx((0.5 + 0.75) / 2)}


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(SystemExit):  # (argparse's error, before any worktree)
        compare.main(["HEAD", "--pairs", "0"])
    with pytest.raises(SystemExit, match="no-such-commit"):
        compare.main(["no-such-commit"])
