"""nuScenes-style data end to end: a synthetic data set in the nuScenes layout, its database
(``drcpo build-db --nuscenes``, multi-sweep, 5-feature points, velocities), its index
(``drcpo index --config nuscenes``) and the ``nuscenes`` preset's DR.CPO pipeline on its frames."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from drcpo.cli import app
from drcpo.config import load_config
from drcpo.database import GroundTruthDatabase
from drcpo.datasets.nuscenes import NUSCENES_CLASSES, NuScenesDataset
from drcpo.frame import VELOCITY
from drcpo.pipeline import build_pipeline
from drcpo.synth.nuscenes import NuScenesSynthConfig, write_synthetic_nuscenes

VERSION = "v1.0-mini"
SWEEPS = 3


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    base = tmp_path_factory.mktemp("nuscenes_e2e")
    root, db = base / "nuscenes", base / "db"
    config = NuScenesSynthConfig(samples=4, sweeps_before=SWEEPS)
    write_synthetic_nuscenes(root, 2, seed=11, config=config, version=VERSION)
    runner = CliRunner()
    args = ["build-db", "--nuscenes", str(root), "--version", VERSION, "--sweeps", str(SWEEPS)]
    result = runner.invoke(app, [*args, "--out", str(db)])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["index", str(db), "--config", "nuscenes", "--k", "20"])
    assert result.exit_code == 0, result.output
    return root, GroundTruthDatabase.open(db)


def test_the_database_holds_five_feature_points_and_canonical_velocities(built):
    _, database = built
    assert database.point_features == ("intensity", "time_lag")
    assert database.points.shape[1] == 5
    assert set(database.classes) <= set(NUSCENES_CLASSES)
    assert database.velocity is not None and database.velocity.shape == (len(database), 2)
    # the synthetic world's moving actors: some stored objects move, parked ones do not
    speeds = np.linalg.norm(database.velocity, axis=1)
    assert (speeds > 0.5).any() and (speeds < 1e-6).any()
    lags = np.unique(database.points[:, 4])
    assert lags[0] == 0.0 and len(lags) > 1, "objects keep the points of the earlier sweeps"


def test_build_db_names_the_wrong_source_in_one_line(built, tmp_path):
    root, _ = built
    runner = CliRunner()
    both = ["build-db", "--kitti", str(root), "--nuscenes", str(root), "--out", str(tmp_path)]
    result = runner.invoke(app, both)
    assert result.exit_code != 0 and "exactly one of --kitti" in result.output
    result = runner.invoke(app, ["build-db", "--nuscenes", str(root), "--out", str(tmp_path / "x")])
    assert result.exit_code == 1 and "v1.0-trainval" in result.output and "missing" in result.output
    assert not (tmp_path / "x").exists()


def test_the_nuscenes_pipeline_runs_on_five_features_with_velocities(built):
    root, database = built
    dataset = NuScenesDataset(root, VERSION, sweeps=SWEEPS)
    pipeline = build_pipeline("nuscenes", database)
    added = 0
    for number, token in enumerate(dataset.frame_ids[:4]):
        frame = dataset.frame(token)
        result = pipeline(frame, np.random.default_rng(number))
        assert result.points.shape[1] == 5 and result.points.dtype == np.float32
        velocity = np.asarray(result.metadata[VELOCITY])
        assert velocity.shape == (len(result.boxes), 2) and np.isfinite(velocity).all()
        assert set(result.names) <= set(NUSCENES_CLASSES)
        added += len(result.boxes) - len(frame.boxes)
        assert "drcpo.construction" in result.metadata["augment_stats"]["stages"]
    assert added > 0, "the pipeline inserted nothing into four frames"


def test_drcpo_alone_keeps_the_features_of_untouched_points_bit_for_bit(built):
    root, database = built
    dataset = NuScenesDataset(root, VERSION, sweeps=SWEEPS)
    config = load_config("nuscenes").to_dict()
    config["global_augmentation"]["enabled"] = False
    pipeline = build_pipeline(config, database)
    frame = dataset.frame(dataset.frame_ids[1])
    result = pipeline(frame, np.random.default_rng(5))
    original = {row.tobytes() for row in frame.points}
    kept = np.array([row.tobytes() in original for row in result.points])
    assert kept.sum() > 0.5 * len(frame.points)
    inserted = result.points[~kept]
    assert len(inserted) > 0
    assert (inserted[:, 4] == 0.0).all(), "inserted points belong to the key sweep"
    lags = set(np.unique(frame.points[:, 4]).tolist())
    assert set(np.unique(result.points[kept, 4]).tolist()) <= lags
