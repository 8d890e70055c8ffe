"""``drcpo demo`` from a clean environment, at a tiny size, as the README runs it."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread
from typer.testing import CliRunner

import drcpo.demo
import drcpo.demo_figures
from drcpo.cli import app
from drcpo.demo import DEFAULT_PRESETS
from drcpo.demo_figures import closest_match, inserted_mask
from drcpo.errors import DrcpoError
from drcpo.frame import Frame

#: Every stage of the demo, in order: all of them must run.
STAGES = [
    "presets",
    "synthetic world",
    "database",
    "candidate index",
    "ground-truth sampling first call",
    "ground-truth sampling",
    "DR.CPO paper first call",
    "DR.CPO paper",
    "figures",
    "construction figure",
]


def _drcpo_command() -> list[str]:
    script = Path(sys.executable).with_name("drcpo")
    if script.is_file():
        return [str(script)]
    found = shutil.which("drcpo")
    return [found] if found else [sys.executable, "-m", "drcpo.cli"]


def _run_demo(out: Path, home: Path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MPL", "DRCPO", "PYTHONPATH"))}
    env.update(HOME=str(home), MPLCONFIGDIR=str(home / "mpl"))  # no user matplotlib settings
    command = [
        *_drcpo_command(),
        "demo",
        "--out",
        str(out),
        "--frames",
        "2",
        "--augment-frames",
        "1",
    ]
    return subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)


def _assert_not_blank(path: Path) -> None:
    image = imread(path)
    assert image.shape[0] >= 200 and image.shape[1] >= 200
    grey = image[..., :3].mean(axis=2)
    assert grey.std() > 0.03, path
    assert (grey < 0.5).mean() > 0.001, path


# Runs the demo twice, about 10 s on 2 cores: the tests using it are marked slow.
@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    base = tmp_path_factory.mktemp("demo")
    (base / "home").mkdir()
    first = _run_demo(base / "out", base / "home")
    second = _run_demo(base / "out", base / "home")
    return base / "out", first, second


@pytest.mark.slow
def test_demo_runs_every_stage_and_writes_non_blank_figures(demo_run):
    out, first, _ = demo_run
    assert first.returncode == 0, first.stdout + first.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stages"] == STAGES
    assert set(summary["figures"]) == {"bev", "density", "side_view", "construction"}
    for path in summary["figures"].values():
        _assert_not_blank(Path(path))
    assert Path(summary["figures"]["side_view"]) == out / "side_view.png"
    # side by side: a real object and one of each preset (here one), two views each
    side_view = imread(out / "side_view.png")
    assert side_view.shape[1] > 1.1 * side_view.shape[0]
    assert "points per frame" in first.stdout and "milliseconds per stage" in first.stdout
    assert "dr.cpo paper" in first.stdout
    assert summary["points_per_frame"]["original"] > 1000
    groups = {"original", "gt sampling", *DEFAULT_PRESETS}
    assert set(summary["points_per_frame"]) == set(summary["objects_per_frame"]) == groups
    assert (out / "kitti" / "training" / "velodyne" / "000001.bin").is_file()
    # the first call (kernels loaded or compiled) is timed apart from the per-frame figures
    ms = summary["ms"]
    frames = summary["augmented_frames"]
    for name in ("ground-truth sampling", "DR.CPO paper"):
        assert ms[f"{name} first call"] > 0
        assert ms[f"{name} per frame"] == pytest.approx(ms[name] / frames)
    # each preset's own entry: its figures, the same as the tables'
    assert list(summary["presets"]) == list(DEFAULT_PRESETS)
    for label, entry in summary["presets"].items():
        assert entry["config"] == label
        assert entry["points_per_frame"] == summary["points_per_frame"][label] > 1000
        assert entry["objects_per_frame"] == summary["objects_per_frame"][label]
        assert entry["ms_per_frame"] == ms[f"DR.CPO {label} per frame"] > 0
        assert entry["first_call_ms"] == ms[f"DR.CPO {label} first call"]
        inserted = entry["inserted_per_frame"]
        assert set(inserted) == {"Car", "Pedestrian", "Cyclist"}
        assert sum(inserted.values()) > 0
        for name, count in inserted.items():
            original = summary["objects_per_frame"]["original"][name]
            # DR.CPO may drop original boxes left too sparse, never add more than it inserted
            assert entry["objects_per_frame"][name] <= original + count + 1e-9


@pytest.mark.slow
def test_demo_reuses_its_synthetic_frames(demo_run):
    _, first, second = demo_run
    assert second.returncode == 0, second.stdout + second.stderr
    assert "reusing synthetic frames" in second.stderr
    assert "reusing" not in first.stderr


@pytest.mark.slow
def test_a_failing_stage_fails_the_demo_naming_it(demo_run, tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("injected failure")

    monkeypatch.setattr(drcpo.demo.DRCPO, "apply", broken)
    out = tmp_path / "out"
    shutil.copytree(demo_run[0] / "kitti", out / "kitti")  # reused: no ray-casting
    shutil.copy(demo_run[0] / "demo.json", out / "demo.json")  # an earlier demo's directory
    args = ["demo", "--out", str(out), "--frames", "2", "--augment-frames", "1"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 1, result.output
    text = result.output.strip()
    assert "Traceback" not in text and isinstance(result.exception, SystemExit), text
    # one line, last, naming the stage and the cause
    errors = [line for line in text.splitlines() if line.startswith("error:")]
    assert errors == [text.splitlines()[-1]], text
    assert (
        "demo stage 'DR.CPO paper first call' failed: RuntimeError: injected failure" in errors[0]
    )
    assert "reusing synthetic frames" in text and "augmenting 1 frames with ground-truth" in text
    assert not (out / "summary.json").exists()


def test_inserted_mask_finds_new_boxes():
    original = Frame(np.zeros((1, 4)), np.array([[1, 2, 3, 4, 2, 1.5, 0.1]]), np.array(["Car"]))
    new_box = [5, 5, -1, 0.8, 0.6, 1.7, 0.0]
    augmented = Frame(
        np.zeros((1, 4)), np.vstack([new_box, original.boxes]), np.array(["Pedestrian", "Car"])
    )
    np.testing.assert_array_equal(inserted_mask(original, augmented), [True, False])
    empty = Frame(np.zeros((1, 4)))
    np.testing.assert_array_equal(inserted_mask(empty, augmented), [True, True])


def _closest_match_naive(reference, candidates):
    """Every reference distance, each group's nearest by a plain loop; the least worst gap."""
    best = None
    for i, r in enumerate(reference):
        picks = []
        for group in candidates:
            gaps = [abs(c - r) for c in group]
            picks.append(gaps.index(min(gaps)))
        worst = max((abs(g[j] - r) for g, j in zip(candidates, picks, strict=True)), default=0.0)
        if best is None or worst < best[0]:
            best = (worst, i, picks)
    return best[1], best[2]


def test_closest_match_picks_the_least_distant_set(rng):
    # the reference at 20 m has a candidate within 0.5 m in each group; at 10 m only in one
    reference = np.array([10.0, 20.0, 45.0])
    candidates = [np.array([30.0, 10.2, 19.5]), np.array([20.4, 60.0])]
    assert closest_match(reference, candidates) == (1, [2, 0])
    assert closest_match(reference, []) == (0, [])  # no group: the first reference
    for _ in range(200):
        reference = rng.uniform(0, 70, rng.integers(1, 8)).round(1)
        groups = [rng.uniform(0, 70, rng.integers(1, 6)).round(1) for _ in range(2)]
        got = closest_match(reference, groups)
        assert got == _closest_match_naive(reference.tolist(), [g.tolist() for g in groups])
        # no other choice of one per group has a smaller largest gap
        i, js = got
        worst = max(abs(g[j] - reference[i]) for g, j in zip(groups, js, strict=True))
        brute = min(
            max(abs(a - r), abs(b - r)) for r in reference for a in groups[0] for b in groups[1]
        )
        assert worst == pytest.approx(brute)


def test_closest_match_needs_a_distance_in_every_group():
    with pytest.raises(ValueError, match="every group"):
        closest_match(np.array([5.0]), [np.array([1.0]), np.array([])])
    with pytest.raises(ValueError, match="every group"):
        closest_match(np.array([]), [np.array([1.0])])


@pytest.mark.parametrize(
    ("presets", "message"),
    [
        (("default", "default"), "preset default: its name 'default' is already taken"),
        (("original",), "its name 'original' is already taken"),
        (("default", "missing.yaml"), "missing.yaml: config file not found"),
        ((), "no DR.CPO preset given"),
    ],
)
def test_a_bad_preset_stops_the_demo_before_any_work(tmp_path, presets, message):
    out = tmp_path / "out"
    with pytest.raises(drcpo.demo.DemoError, match="demo stage 'presets' failed") as failure:
        drcpo.demo.run_demo(out, frames=2, augment_frames=1, presets=presets)
    assert message in str(failure.value)
    assert not out.exists()  # nothing ray-cast, nothing written


def _pool(names, distance, points):
    return {
        "names": np.array(names),
        "distance": np.array(distance, dtype=float),
        "points": np.array(points),
    }


def test_side_view_picks_a_class_every_pool_has_and_a_dense_real_object():
    real = _pool(["Car", "Car", "Pedestrian"], [20.0, 31.0, 12.0], [10, 300, 80])
    paper = _pool(["Car", "Pedestrian"], [21.0, 13.0], [6, 9])
    other = _pool(["Car", "Car", "Cyclist"], [30.0, 19.5, 8.0], [250, 90, 40])
    # the real Car at 20 m is nearer both, but too sparse: the one at 31 m (and the inserted
    # nearest it, however sparse the paper's is)
    assert drcpo.demo_figures._side_view_picks([real, paper, other]) == ("Car", [1, 0, 0])
    # no Car inserted by one preset: the next class every pool has
    no_car = _pool(["Pedestrian"], [14.0], [30])
    assert drcpo.demo_figures._side_view_picks([real, paper, no_car]) == ("Pedestrian", [2, 1, 0])
    # no real object dense enough: the sparse ones
    sparse = _pool(["Car", "Car"], [40.0, 21.5], [3, 5])
    assert drcpo.demo_figures._side_view_picks([sparse, paper, other]) == ("Car", [1, 0, 1])
    with pytest.raises(DrcpoError, match="side view"):
        drcpo.demo_figures._side_view_picks([real, _pool(["Cyclist"], [5.0], [50])])
