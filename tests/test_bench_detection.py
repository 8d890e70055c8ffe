"""benchmarks/bench_detection.py: arms and their overrides, the run cache's key, and --quick:
the grid end to end on a few frames (synthetic data, databases and indexes per subset,
training, detection, KITTI evaluation, paired statistics and controls)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
SCRIPT = BENCHMARKS / "bench_detection.py"
sys.path.insert(0, str(BENCHMARKS))

import bench_detection as bench  # noqa: E402
from detection import arms  # noqa: E402

from drcpo.errors import ConfigError  # noqa: E402
from drcpo.frame import Frame  # noqa: E402
from drcpo.transforms import Compose  # noqa: E402


def test_arms_are_built_in_names_presets_files_and_overrides(tmp_path):
    assert arms.parse_arm("none").kind == "none" and arms.parse_arm("none").config is None
    cda, paper = arms.parse_arm("cda"), arms.parse_arm("paper")
    assert (cda.kind, paper.kind) == ("cda", "drcpo") and cda.config == paper.config
    changed = arms.parse_arm("paper:placement.occluded_fraction=null,placement.location=source")
    placement = changed.config["drcpo"]["placement"]
    assert placement["occluded_fraction"] is None and placement["location"] == "source"
    assert placement["max_non_ground_points"] == 10  # the rest of the preset stays
    full_path = arms.parse_arm("paper:drcpo.placement.max_non_ground_points=9")
    assert full_path.config["drcpo"]["placement"]["max_non_ground_points"] == 9
    assert changed.slug != paper.slug and "/" not in changed.slug and ":" not in changed.slug
    nuscenes = arms.parse_arm("nuscenes")
    assert nuscenes.kind == "drcpo" and "car" in nuscenes.config["drcpo"]["sample"]
    yaml_file = tmp_path / "mine.yaml"
    yaml_file.write_text("drcpo:\n  placement:\n    max_non_ground_points: 3\n")
    assert arms.parse_arm(str(yaml_file)).config["drcpo"]["placement"]["max_non_ground_points"] == 3


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("paper:placement.drop_hiden_added=false", "unknown key 'placement.drop_hiden_added'"),
        ("paper:placement.max_non_ground_points=-3", "max_non_ground_points"),
        ("paper:placement.max_non_ground_points", "is not KEY=VALUE"),
        ("paper:", "expected NAME or NAME:KEY=VALUE"),
        ("none:placement.location=source", "'none' takes no overrides"),
        ("realistic", "realistic"),
        ("paper:placement.x_range=[1", "arm 'paper:placement.x_range=[1'"),
    ],
)
def test_a_bad_arm_is_refused_naming_it_and_the_key(spec, message):
    with pytest.raises(ConfigError, match=message.replace("[", r"\[")) as caught:
        arms.parse_arm(spec)
    assert spec in str(caught.value)


def test_every_arm_of_the_ablation_script_is_a_valid_distinct_arm():
    text = (BENCHMARKS / "run_ablation.sh").read_text()
    body = text[text.index("arms=(") + len("arms=(") : text.index("\n)\n")]
    specs = [word for line in body.splitlines() for word in line.split("#")[0].split()]
    parsed = [arms.parse_arm(spec) for spec in specs]  # a key renamed or deleted fails here
    assert len(specs) >= 10 and {"cda", "paper"} <= set(specs)
    assert len({arm.slug for arm in parsed}) == len(specs)
    assert len({(arm.kind, repr(arm.config)) for arm in parsed}) == len(specs)  # none alike


def test_the_broken_control_moves_only_inserted_labels_along_their_heading():
    class Insert(arms.Transform):
        name = "insert"

        def apply(self, frame, rng, stats):
            box = np.array([[10.0, 2.0, -1.0, 4.0, 1.7, 1.5, np.pi / 2]])
            return frame.replace(
                boxes=np.concatenate([frame.boxes, box]), names=np.array([*frame.names, "Car"])
            )

        def to_config(self):
            return {"type": "Insert"}

    original = np.array([[5.0, 0.0, -1.0, 4.0, 1.7, 1.5, 0.0]])
    frame = Frame(points=np.zeros((3, 4), np.float32), boxes=original, names=np.array(["Car"]))
    out = Compose([arms.ShiftInsertedLabels(Insert(), 0.5)])(frame, np.random.default_rng(0))
    np.testing.assert_array_equal(out.boxes[0], original[0])
    np.testing.assert_allclose(out.boxes[1, :2], [10.0, 2.5], atol=1e-12)


def test_a_run_key_changes_with_what_the_run_depends_on():
    plan = bench.Plan()
    key = bench.run_key(plan, 60, 0, "samples", "trainer", "val")
    assert key == bench.run_key(plan, 60, 0, "samples", "trainer", "val")
    others = [
        bench.run_key(plan, 240, 0, "samples", "trainer", "val"),
        bench.run_key(plan, 60, 1, "samples", "trainer", "val"),
        bench.run_key(plan, 60, 0, "sample", "trainer", "val"),
        bench.run_key(plan, 60, 0, "samples", "trainers", "val"),
        bench.run_key(plan, 60, 0, "samples", "trainer", "vals"),
        bench.run_key(bench.Plan(steps=7), 60, 0, "samples", "trainer", "val"),
        bench.run_key(bench.Plan(device="cuda"), 60, 0, "samples", "trainer", "val"),
    ]
    assert key not in others and len(set(others)) == len(others)
    alias = bench.alias_key(plan, "cda", 60, 0, "abc")
    assert alias == bench.alias_key(plan, "cda", 60, 0, "abc")
    others = [
        bench.alias_key(plan, "paper", 60, 0, "abc"),
        bench.alias_key(plan, "cda", 60, 0, "abd"),
        bench.alias_key(bench.Plan(steps=7), "cda", 60, 0, "abc"),
    ]
    assert alias not in others and len(set(others)) == len(others)


def _row(mean: float, verdict: str) -> dict:
    return {"3d": {"mean": {"mean": mean, "verdict": verdict}}}


def test_the_default_is_the_best_arm_never_worse_than_cda():
    paired = {
        "paper - cda": {"24": _row(1.0, "no difference"), "240": _row(0.5, "no difference")},
        "bold - cda": {"24": _row(6.0, "better"), "240": _row(-3.0, "worse")},
        "shy - cda": {"24": _row(0.2, "no difference"), "240": _row(0.0, "no difference")},
        "none - cda": {"24": _row(9.0, "better"), "240": _row(9.0, "better")},  # never a default
    }
    decision = bench.decide(paired, ("none", "cda", "paper", "bold", "shy"))
    assert decision["chosen"] == "paper"
    assert decision["candidates"]["paper"]["mean_difference"] == 0.75
    assert decision["candidates"]["bold"]["worse_at"] == [240]
    assert decision["candidates"]["bold"]["better_at"] == [24]
    assert "none" not in decision["candidates"]
    # every arm below cda on average, or worse somewhere: cda stays; a tie goes to cda too
    paired["paper - cda"]["240"] = _row(-2.5, "no difference")
    paired["shy - cda"] = {"24": _row(0.0, "no difference")}
    assert bench.decide(paired, ("cda", "paper", "bold", "shy"))["chosen"] == "cda"


def test_comparisons_pair_each_arm_with_cda_and_drcpo_arms_with_paper():
    pairs = bench.comparisons(("none", "cda", "paper", "broken", "nuscenes"))
    assert pairs == [
        ("paper", "cda"), ("broken", "cda"), ("nuscenes", "cda"), ("nuscenes", "paper"),
        ("cda", "none"),
    ]  # fmt: skip


@pytest.mark.slow
def test_quick_grid_runs_end_to_end_and_reuses_finished_runs(tmp_path):
    pytest.importorskip("torch", reason="the detector needs torch (pip install -e '.[detection]')")
    out = tmp_path / "out"
    command = [sys.executable, str(SCRIPT), "--quick", "--work", str(tmp_path / "work")]
    done = subprocess.run(
        [*command, "--out", str(out)], capture_output=True, text=True, timeout=1200
    )
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    expected = {"none", "cda", "paper", "broken"}
    assert result["quick"] and set(result["ap"]) == expected
    for arm in expected:
        assert set(result["ap"][arm]) == {"6", "12"}  # the two subsets of the 12-frame pool
        ap = result["ap"][arm]["12"]["3d"]
        assert set(ap) == {"Car", "Pedestrian", "Cyclist", "mean"}
        assert all(0.0 <= ap[name]["mean"] <= 100.0 for name in ap)
    assert set(result["paired"]) == {"paper - cda", "broken - cda", "cda - none"}
    difference = result["paired"]["paper - cda"]["12"]["3d"]["mean"]
    assert difference["low"] <= difference["mean"] <= difference["high"]
    assert difference["verdict"] in ("better", "no difference", "worse")
    assert {(c["pair"], c["expected"]) for c in result["controls"]} == {
        ("cda - none", "better"), ("broken - cda", "worse")
    }  # fmt: skip
    per_arm = result["per_arm"]
    assert per_arm["none"]["12"]["added_per_frame"] == {}
    assert set(per_arm["cda"]["12"]["added_per_frame"]) == {"gt_sampling"}
    assert sum(per_arm["paper"]["12"]["added_per_frame"]["drcpo"].values()) > 0
    assert (
        per_arm["cda"]["12"]["labels_per_frame"]["Car"]
        > per_arm["none"]["12"]["labels_per_frame"]["Car"]
    )
    assert per_arm["cda"]["12"]["points_per_frame"] > 0
    assert set(result["environment"]) >= {"torch", "numpy", "numba", "torch_threads"}
    assert result["decision"]["chosen"] in ("cda", "paper")  # never none nor broken
    assert set(result["decision"]["candidates"]) == {"cda", "paper"}
    assert result["revision"]["code"] and result["runs_cached"] == 0
    assert (out / "detection.png").stat().st_size > 0
    runs = json.loads((out / "detection.json").read_text())["runs"]
    assert len(runs) == 16 and all(r["seconds"]["step_per_step"] > 0 for r in runs)
    assert all(r["environment"]["torch_threads"] == 1 for r in runs)
    # the results the evaluator scored are KITTI result files, one per validation frame
    [paper_run] = (tmp_path / "work" / "runs").glob("paper-12-s0-*")
    results = sorted((paper_run / "detections").glob("*.txt"))
    assert len(results) == result["plan"]["val_frames"]
    # a rerun takes every finished run from the cache and reports the same figures
    again = subprocess.run(
        [*command, "--out", str(tmp_path / "again")], capture_output=True, text=True, timeout=600
    )
    assert again.returncode == 0, again.stderr[-3000:]
    second = json.loads(again.stdout.strip().splitlines()[-1])
    assert second["runs_cached"] == 16 and second["ap"] == result["ap"]
    assert second["paired"] == result["paired"]
    # a run is known by its samples: without the aliases, and under another arm's name that
    # augments alike, the finished runs are found again (here by augmenting, not training)
    shutil.rmtree(tmp_path / "work" / "runs" / "aliases")
    alike = "cda:gt_sampling.enabled=true"
    third = subprocess.run(
        [*command, "--out", str(tmp_path / "third"), "--arms", "cda", alike, "--seeds", "0"],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert third.returncode == 0, third.stderr[-3000:]
    runs = json.loads((tmp_path / "third" / "detection.json").read_text())["runs"]
    assert len(runs) == 4 and all(r["cached"] and r["trained_as"] == "cda" for r in runs)
    assert {r["key"] for r in runs if r["arm"] == alike} == {
        r["key"] for r in runs if r["arm"] == "cda"
    }


def test_an_unknown_arm_fails_at_once_naming_it(tmp_path):
    command = [sys.executable, str(SCRIPT), "--quick", "--work", str(tmp_path / "work")]
    done = subprocess.run(
        [*command, "--arms", "none", "paper_typo"], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 1 and "paper_typo" in done.stderr
    assert "Traceback" not in done.stderr and not (tmp_path / "work").exists()
