"""benchmarks/bench_cluster.py's side of local worker processes (``drcpo augment --workers 2``,
no Ray) runs end to end on a few frames and writes the bytes of one process."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_cluster.py"


def test_processes_side_runs_and_matches_one_process(tmp_path):
    command = [sys.executable, str(SCRIPT), "--frames", "3", "--sides", "processes"]
    done = subprocess.run(
        [*command, "--work", str(tmp_path / "work")], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert set(result) >= {"one", "processes", "identical", "speedup", "speedup_with_startup"}
    assert "cluster" not in result  # not asked for: no Ray needed
    assert result["compared"] == "processes" and result["identical"] is True
    one, processes = result["one"], result["processes"]
    assert one["frames"] == processes["frames"] == 3
    assert len(processes["workers"]) == 2
    for side in (one, processes):
        assert side["startup_s"] > 0 and side["augment_s"] > 0
        assert side["total_s"] >= side["startup_s"] + side["augment_s"] - 0.02  # rounding
    assert processes["speedup"] == round(processes["frames_per_s"] / one["frames_per_s"], 2)
    assert processes["speedup_with_startup"] == round(one["total_s"] / processes["total_s"], 2)
