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
from drcpo.cli import app
from drcpo.demo import inserted_mask
from drcpo.frame import Frame

#: Every stage of the demo, in order: all of them must run.
STAGES = [
    "synthetic world",
    "database",
    "candidate index",
    "ground-truth sampling first call",
    "ground-truth sampling",
    "DR.CPO first call",
    "DR.CPO",
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
    assert set(summary["figures"]) == {"bev", "density", "construction"}
    for path in summary["figures"].values():
        _assert_not_blank(Path(path))
    assert "points per frame" in first.stdout and "milliseconds per stage" in first.stdout
    assert summary["points_per_frame"]["original"] > 1000
    assert set(summary["points_per_frame"]) == {"original", "gt sampling", "dr.cpo"}
    assert (out / "kitti" / "training" / "velodyne" / "000001.bin").is_file()
    # the first call (kernels loaded or compiled) is timed apart from the per-frame figures
    ms = summary["ms"]
    for name in ("ground-truth sampling", "DR.CPO"):
        frames = summary["augmented_frames"]
        assert ms[f"{name} first call"] > 0
        assert ms[f"{name} per frame"] == pytest.approx(ms[name] / frames)


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
    args = ["demo", "--out", str(out), "--frames", "2", "--augment-frames", "1"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 1, result.output
    text = result.output.strip()
    assert "Traceback" not in text and isinstance(result.exception, SystemExit), text
    # one line, last, naming the stage and the cause
    errors = [line for line in text.splitlines() if line.startswith("error:")]
    assert errors == [text.splitlines()[-1]], text
    assert "demo stage 'DR.CPO first call' failed: RuntimeError: injected failure" in errors[0]
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
