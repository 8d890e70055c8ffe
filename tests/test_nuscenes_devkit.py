"""What drcpo writes in nuScenes layout opens in the official nuscenes-devkit (1.2.0, in an
environment of its own: its numpy < 2 pin; .ci/run's nuScenes step). Every call a user makes on
a data set works, and the devkit's boxes and velocities are drcpo's reader's."""

from __future__ import annotations

import os

import numpy as np
import pytest

from drcpo.datasets.nuscenes import NuScenesDataset
from drcpo.synth.nuscenes import NuScenesSynthConfig, write_synthetic_nuscenes

VERSION = "v1.0-mini"

if os.environ.get("DRCPO_REQUIRE_NUSCENES_DEVKIT") == "1":
    import nuscenes  # noqa: F401  (a missing devkit fails here, as CI asks)
devkit = pytest.importorskip(
    "nuscenes.nuscenes",
    reason="nuscenes-devkit is not installed (pip install -e '.[nuscenes-devkit]')",
)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("nuscenes") / "data"
    write_synthetic_nuscenes(
        root, 2, seed=3, config=NuScenesSynthConfig(samples=3), version=VERSION
    )
    return root


def test_the_devkit_opens_it_and_every_user_call_works(data, tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    nusc = devkit.NuScenes(version=VERSION, dataroot=str(data), verbose=False)
    assert len(nusc.scene) == 2 and len(nusc.sample) == 6
    nusc.list_scenes()
    starts = sorted(nusc.get("sample", s["first_sample_token"])["timestamp"] for s in nusc.scene)
    assert starts[0] < starts[1]  # scenes follow one another in time
    sample = nusc.sample[1]
    lidar = sample["data"]["LIDAR_TOP"]
    path, boxes, _ = nusc.get_sample_data(lidar)
    assert os.path.isfile(path) and boxes
    velocities = np.array([nusc.box_velocity(ann) for ann in sample["anns"]])
    assert np.isfinite(velocities).all() and (np.abs(velocities).max(axis=1) > 0).any()
    nusc.render_sample_data(lidar, out_path=str(tmp_path / "render.png"), verbose=False)
    assert (tmp_path / "render.png").stat().st_size > 0


def test_the_devkits_boxes_and_velocities_are_drcpos_readers(data):
    from pyquaternion import Quaternion

    nusc = devkit.NuScenes(version=VERSION, dataroot=str(data), verbose=False)
    ours = NuScenesDataset(data, VERSION, keep_empty=True)
    for token in ours.frame_ids:
        frame = ours.frame(token)
        lidar = nusc.get("sample_data", nusc.get("sample", token)["data"]["LIDAR_TOP"])
        _, boxes, _ = nusc.get_sample_data(lidar["token"])
        by_token = {b.token: b for b in boxes}
        sensor = nusc.get("calibrated_sensor", lidar["calibrated_sensor_token"])
        ego = nusc.get("ego_pose", lidar["ego_pose_token"])
        to_lidar = (Quaternion(ego["rotation"]) * Quaternion(sensor["rotation"])).inverse
        for row, ann in enumerate(frame.metadata["annotation_tokens"]):
            box = by_token[ann]
            np.testing.assert_allclose(frame.boxes[row, :3], box.center, atol=1e-6)
            np.testing.assert_allclose(frame.boxes[row, 3:6], box.wlh[[1, 0, 2]], atol=1e-6)
            velocity = to_lidar.rotate(nusc.box_velocity(ann))  # the devkit's: global frame
            np.testing.assert_allclose(
                frame.metadata["velocity"][row], velocity[:2], atol=1e-9, equal_nan=True
            )
