"""benchmarks/bench_detection.py --quick: the data-efficiency grid end to end on a few frames
(synthetic data, databases and indexes per subset, training, detection, KITTI evaluation)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_detection.py"


@pytest.mark.slow
def test_quick_grid_runs_end_to_end(tmp_path):
    pytest.importorskip("torch", reason="the detector needs torch (pip install -e '.[detection]')")
    out = tmp_path / "out"
    command = [sys.executable, str(SCRIPT), "--quick", "--work", str(tmp_path / "work")]
    done = subprocess.run(
        [*command, "--out", str(out)], capture_output=True, text=True, timeout=1200
    )
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["quick"] and set(result["ap"]) == {"none", "cda", "paper"}
    for arm in ("none", "cda", "paper"):
        assert set(result["ap"][arm]) == {"6", "12"}  # the two subsets of the 12-frame pool
        ap = result["ap"][arm]["12"]["3d"]
        assert set(ap) == {"Car", "Pedestrian", "Cyclist", "mean"}
        assert all(0.0 <= ap[name]["mean"] <= 100.0 for name in ap)
    assert set(result["paired"]) == {"cda-none", "paper-cda", "paper-none"}
    added = result["added_per_frame"]
    assert added["none"] == {} and set(added["cda"]) == {"gt_sampling"}
    assert sum(added["paper"]["drcpo"].values()) > 0
    assert (out / "detection.png").stat().st_size > 0
    runs = json.loads((out / "detection.json").read_text())["runs"]
    assert len(runs) == 6 and all(r["seconds"]["step_per_step"] > 0 for r in runs)
    # the results the evaluator scored are KITTI result files, one per validation frame
    results = sorted((tmp_path / "work" / "results" / "paper-1-0").glob("*.txt"))
    assert len(results) == result["plan"]["val_frames"]


def test_an_unknown_arm_fails_at_once_naming_it(tmp_path):
    command = [sys.executable, str(SCRIPT), "--quick", "--work", str(tmp_path / "work")]
    done = subprocess.run(
        [*command, "--arms", "none", "realistic_typo"], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 1 and "realistic_typo" in done.stderr
    assert "Traceback" not in done.stderr and not (tmp_path / "work").exists()
