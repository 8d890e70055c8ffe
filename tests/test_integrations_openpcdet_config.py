"""drcpo's OpenPCDet augmentor without OpenPCDet: entry settings, data-dict handling, draws.

The tests that run it inside OpenPCDet's real pipeline are in test_integrations_openpcdet.py.
They seed numpy's global state, as OpenPCDet's worker_init_fn does: the augmentor draws its
generator's seed there.
"""
# ruff: noqa: NPY002

from __future__ import annotations

import pickle
import sys

import numpy as np
import pytest

from drcpo.datasets.kitti import read_calib
from drcpo.datasets.kitti_coordinates import Calibration
from drcpo.errors import ConfigError, DataError
from drcpo.integrations import openpcdet
from drcpo.transforms import GlobalFlip, GlobalRotation, GlobalScaling, Stats
from drcpo.warmup import warmup_frame


@pytest.fixture(scope="module")
def sample_db(tmp_path_factory):
    """A drcpo database (with its index) imported from the KITTI sample's OpenPCDet dbinfos."""
    from conftest import KITTI_SAMPLE

    if not KITTI_SAMPLE.is_dir():
        pytest.skip(f"KITTI sample not found at {KITTI_SAMPLE} (only CI and developers have it)")
    from drcpo.database.dbinfos import import_openpcdet
    from drcpo.index import IndexConfig
    from drcpo.index_build import build_index

    out = tmp_path_factory.mktemp("openpcdet") / "db"
    database = import_openpcdet(KITTI_SAMPLE / "kitti_dbinfos_train.pkl", out)
    build_index(database, IndexConfig(k=20)).save(out)
    return out


def _frame_dict(sample_db, rng):
    frame = warmup_frame(_open(sample_db)).to_dict()
    boxes = frame["gt_boxes"].astype(np.float32)
    names = frame["gt_names"]
    return {
        "frame_id": "000000",
        "points": frame["points"],
        "gt_boxes": boxes,
        "gt_names": names,
        "gt_boxes_mask": np.isin(names, ["Car", "Pedestrian"]),
        "extra": "kept",
    }


def _open(path):
    from drcpo.database import GroundTruthDatabase

    return GroundTruthDatabase.open(path)


def _augmentor(sample_db, **entry):
    entry = {"NAME": "drcpo", "DB_PATH": str(sample_db), "WARMUP": False, **entry}
    return openpcdet.OpenPCDetAugmentor(entry, "/", ["Car", "Pedestrian", "Cyclist"])


# Entry settings ----------------------------------------------------------------------------
def test_entry_layers_defaults_difficulty_stages_and_class_names():
    config = openpcdet.augment_config({"NAME": "drcpo"}, "/", ["Car", "Cyclist"])
    assert config.drcpo.enabled and not config.gt_sampling.enabled
    assert not config.global_augmentation.enabled
    assert config.drcpo.exclude_difficulty == [-1] == config.gt_sampling.exclude_difficulty
    assert set(config.drcpo.sample) == {"Car", "Cyclist"}
    assert set(config.gt_sampling.targets) == {"Car", "Cyclist"}
    assert not config.gt_sampling.use_road_plane

    given = openpcdet.augment_config(
        {
            "NAME": "drcpo",
            "PRESET": "second",
            "CONFIG": {"drcpo": {"exclude_difficulty": [], "sample": {"Car": 3}}},
            "STAGES": ["global_augmentation", "gt_sampling"],
            "USE_ROAD_PLANE": True,
        },
        "/",
        ["Car"],
    )
    assert given.drcpo.exclude_difficulty == [] and given.drcpo.sample == {"Car": 3}
    assert given.drcpo.external_occlusion.viewpoint_z == 2.0  # SECOND's in the paper
    assert given.gt_sampling.enabled and given.global_augmentation.enabled
    assert not given.drcpo.enabled and given.gt_sampling.use_road_plane


def test_entry_config_file_relative_to_data_path(tmp_path):
    (tmp_path / "aug.yaml").write_text("drcpo:\n  sample: {Car: 4}\n")
    entry = {"NAME": "drcpo", "CONFIG_FILE": "aug.yaml", "CONFIG": {"drcpo": {"min_points": 9}}}
    config = openpcdet.augment_config(entry, tmp_path, ["Car"])
    assert config.drcpo.sample == {"Car": 4} and config.drcpo.min_points == {"default": 9}


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ({"NAME": "drcpo", "DB_PTH": "x"}, "unknown key(s) ['DB_PTH']"),
        ({"NAME": "drcpo", "CONFIG": {"drcpo": {"sampel": {}}}}, "sampel"),
        ({"NAME": "drcpo", "CONFIG": {"drcpo": {"min_points_after": -1}}}, "min_points_after"),
        ({"NAME": "drcpo", "STAGES": ["drcpo", "flip"]}, "STAGES"),
        ({"NAME": "drcpo", "STAGES": "drcpo"}, "STAGES must be a list"),
        ({"NAME": "drcpo", "PRESET": "second", "CONFIG_FILE": "a.yaml"}, "not both"),
        ({"NAME": "drcpo", "CONFIG_FILE": "missing.yaml"}, "missing.yaml not found"),
        ({"NAME": "drcpo", "PRESET": "nope"}, "nope"),
    ],
)
def test_entry_errors_name_the_culprit(entry, message, tmp_path):
    with pytest.raises(ConfigError) as info:
        openpcdet.augment_config(entry, tmp_path, ["Car"])
    assert message in str(info.value)


def test_augmentor_needs_a_database_for_drcpo_stages():
    with pytest.raises(ConfigError, match="DB_PATH"):
        openpcdet.OpenPCDetAugmentor({"NAME": "drcpo"}, "/", ["Car"])


# The data dict ---------------------------------------------------------------------------
def test_augmentor_keeps_dtypes_keys_and_the_mask_in_step(sample_db):
    augmentor = _augmentor(sample_db, CONFIG={"drcpo": {"exclude_difficulty": []}})
    data = _frame_dict(sample_db, np.random.default_rng(0))
    np.random.seed(1)
    out = augmentor(dict(data))
    assert set(out) == set(data)
    assert out["gt_boxes"].dtype == np.float32 and out["points"].dtype == np.float32
    assert len(out["gt_boxes"]) == len(out["gt_names"]) == len(out["gt_boxes_mask"])
    added = len(out["gt_boxes"]) - len(data["gt_boxes"])
    assert added > 0, "the sample database should give this frame new objects"
    mask = out["gt_boxes_mask"]
    assert mask[len(data["gt_boxes"]) :].all()  # inserted boxes
    assert not mask[np.flatnonzero(~data["gt_boxes_mask"])].any()  # original masked-out ones
    assert set(out["gt_names"][len(data["gt_boxes"]) :]) <= {"Car", "Pedestrian", "Cyclist"}
    assert out["extra"] == "kept"


def test_class_names_limit_what_is_inserted(sample_db):
    entry = {"NAME": "drcpo", "DB_PATH": str(sample_db), "WARMUP": False}
    augmentor = openpcdet.OpenPCDetAugmentor(entry, "/", ["Pedestrian"])
    data = _frame_dict(sample_db, np.random.default_rng(0))
    np.random.seed(3)
    out = augmentor(dict(data))
    new = out["gt_names"][len(data["gt_names"]) :]
    assert len(new) > 0 and set(new) == {"Pedestrian"}


def test_same_numpy_seed_same_output_and_pickled_augmentor_agrees(sample_db):
    augmentor = _augmentor(sample_db)
    data = _frame_dict(sample_db, np.random.default_rng(0))
    outs = []
    for a in (augmentor, pickle.loads(pickle.dumps(augmentor))):  # as spawned workers get it
        np.random.seed(5)
        outs.append(a(dict(data)))
    np.random.seed(6)
    other = augmentor(dict(data))
    assert np.array_equal(outs[0]["points"], outs[1]["points"])
    assert np.array_equal(outs[0]["gt_boxes"], outs[1]["gt_boxes"])
    assert not np.array_equal(outs[0]["points"], other["points"])


def test_fov_points_only_keeps_inserted_objects_in_the_camera_view(sample_db):
    from drcpo.placement import KITTI_FOV_HALF_ANGLE

    data = _frame_dict(sample_db, np.random.default_rng(0))
    for fov, check in ((True, True), (False, False)):
        entry = {"NAME": "drcpo", "DB_PATH": str(sample_db), "WARMUP": False}
        augmentor = openpcdet.OpenPCDetAugmentor(
            {**entry, "CONFIG": {"drcpo": {"sample": {"Car": 30, "Pedestrian": 30}}}},
            "/",
            ["Car", "Pedestrian"],
            fov_points_only=fov,
        )
        assert augmentor.fov_points_only is fov
        azimuths = []
        for seed in range(4):
            np.random.seed(seed)
            out = augmentor(dict(data))
            new = out["gt_boxes"][len(data["gt_boxes"]) :]
            azimuths.append(np.abs(np.arctan2(new[:, 1], new[:, 0])))
        inside = np.concatenate(azimuths) <= KITTI_FOV_HALF_ANGLE
        assert inside.all() if check else not inside.all()


def test_refuses_boxes_it_cannot_keep_consistent(sample_db):
    augmentor = _augmentor(sample_db)
    data = _frame_dict(sample_db, np.random.default_rng(0))
    wide = {**data, "gt_boxes": np.hstack([data["gt_boxes"], np.zeros((len(data["gt_boxes"]), 1))])}
    with pytest.raises(
        DataError, match=r"shape \(\d+, 8\); drcpo moves \(M, 7\) boxes and \(M, 9\)"
    ):
        augmentor(wide)
    with pytest.raises(DataError, match="gt_boxes2d"):
        augmentor({**data, "gt_boxes2d": np.zeros((len(data["gt_boxes"]), 4))})
    with pytest.raises(DataError, match="'points'"):
        augmentor({"gt_boxes": data["gt_boxes"], "gt_names": data["gt_names"]})


def test_nine_value_boxes_keep_their_velocities(sample_db):
    """nuScenes' gt_boxes (M, 9): split into boxes and velocities, joined on the way out; the
    frame's own boxes keep theirs, inserted ones get the database's (none here: 0), and the
    global rotation turns them as OpenPCDet's global_rotation does."""
    data = _frame_dict(sample_db, np.random.default_rng(0))
    m = len(data["gt_boxes"])
    velocity = np.random.default_rng(1).normal(0, 3, (m, 2)).astype(np.float32)
    nine = {**data, "gt_boxes": np.hstack([data["gt_boxes"], velocity])}
    augmentor = _augmentor(sample_db)
    out = augmentor(dict(nine), np.random.default_rng(2))
    seven = augmentor(dict(data), np.random.default_rng(2))
    assert out["gt_boxes"].shape == (len(seven["gt_boxes"]), 9)
    assert out["gt_boxes"].dtype == np.float32
    np.testing.assert_array_equal(out["gt_boxes"][:, :7], seven["gt_boxes"])
    np.testing.assert_array_equal(out["points"], seven["points"])
    for box in out["gt_boxes"]:
        own = np.flatnonzero((data["gt_boxes"] == box[:7]).all(axis=1))
        expected = velocity[own[0]] if len(own) else np.zeros(2, np.float32)
        np.testing.assert_array_equal(box[7:], expected)
    assert len(out["gt_boxes"]) > m  # inserted boxes were checked too
    rotating = _augmentor(sample_db, STAGES=["global_augmentation"])
    turned = rotating(dict(nine), np.random.default_rng(3))
    angle = turned.get("noise_rot", 0.0)
    flipped = turned.get("flip_x", False)
    expected = velocity.astype(np.float64)
    if flipped:
        expected[:, 1] = -expected[:, 1]
    c, s_ = np.cos(angle), np.sin(angle)
    expected = np.column_stack(
        [c * expected[:, 0] - s_ * expected[:, 1], s_ * expected[:, 0] + c * expected[:, 1]]
    )
    np.testing.assert_allclose(
        turned["gt_boxes"][:, 7:], expected * turned.get("noise_scale", 1.0), rtol=1e-5, atol=1e-5
    )


def test_road_plane_and_openpcdet_calibration_kept_from_the_pre_hook(sample_db, kitti_sample):
    class OpenPCDetCalib:  # OpenPCDet's attribute names
        def __init__(self, calib):
            self.P2, self.R0, self.V2C = calib.P2, calib.R0_rect, calib.Tr_velo_to_cam

    calib = read_calib(kitti_sample / "training" / "calib" / "000000.txt")
    converted = openpcdet.drcpo_calibration(OpenPCDetCalib(calib))
    assert isinstance(converted, Calibration)
    assert np.array_equal(converted.R0_rect, calib.R0_rect)
    with pytest.raises(DataError, match="P2, R0, V2C"):
        openpcdet.drcpo_calibration(object())

    entry = {"USE_ROAD_PLANE": True, "STAGES": ["gt_sampling"]}
    augmentor = _augmentor(sample_db, **entry, CONFIG={"gt_sampling": {"exclude_difficulty": []}})
    data = _frame_dict(sample_db, np.random.default_rng(0))
    # A plane 1 m lower than the frame's ground (camera y points down).
    plane = np.array([0.0, -1.0, 0.0, 1.73 + 1.0])
    hooked = augmentor.remember({**data, "calib": OpenPCDetCalib(calib), "road_plane": plane})
    del hooked["calib"], hooked["road_plane"]  # as OpenPCDet's gt_sampling removes them
    np.random.seed(2)
    out = augmentor(hooked)
    np.random.seed(2)
    flat = augmentor(dict(data))
    assert openpcdet.CONTEXT_KEY not in out
    start = len(data["gt_boxes"])
    new, new_flat = out["gt_boxes"][start:], flat["gt_boxes"][start:]
    assert len(new) and np.array_equal(new[:, :2], new_flat[:, :2])
    assert not np.allclose(new[:, 2], new_flat[:, 2])  # on the road plane, not the source height


# Global stages: their draws as OpenPCDet's keys --------------------------------------------
def test_global_stages_record_their_draws_and_openpcdet_keys():
    frame = warmup_frame()
    stats = Stats()
    rng = np.random.default_rng(0)
    for t in (GlobalFlip(1.0, ["x", "y"]), GlobalRotation(), GlobalScaling(), GlobalRotation()):
        frame = t.apply(frame, rng, stats)
    stages = stats.to_dict()["stages"]
    assert stages["global_flip"]["flipped"] == [["x", "y"]]
    assert len(stages["global_rotation"]["angle"]) == 2
    keys = openpcdet.openpcdet_draws(stages, ["x", "y"])
    assert keys["flip_x"] is np.True_ and keys["flip_y"] is np.True_
    assert keys["noise_rot"] == pytest.approx(sum(stages["global_rotation"]["angle"]))
    assert keys["noise_scale"] == stages["global_scaling"]["scale"][0]
    assert openpcdet.openpcdet_draws({}, ["x"]) == {}


def test_global_stage_output_unchanged_by_recording_draws():
    """The draws are only recorded: the same generator still gives the same frame."""
    frame = warmup_frame()
    rng = np.random.default_rng(4)
    angle = rng.uniform(-np.pi / 4, np.pi / 4)
    out = GlobalRotation()(frame, np.random.default_rng(4))
    assert out.metadata["augment_stats"]["stages"]["global_rotation"]["angle"] == [angle]


def test_runner_usage_without_a_script(capsys):
    with pytest.raises(SystemExit) as info:
        openpcdet.main([])
    assert info.value.code == 2 and "usage" in capsys.readouterr().out
    with pytest.raises(SystemExit) as info:
        openpcdet.main(["no_such_script.py"])
    assert info.value.code == 2


def test_runner_without_openpcdet_says_so_in_one_line(tmp_path, monkeypatch, capsys):
    script = tmp_path / "train.py"
    script.write_text("raise SystemExit('the script must not run')\n")
    # `import pcdet...` raises ImportError, also where another test module imported it.
    for name in ["pcdet", *(m for m in sys.modules if m.startswith("pcdet."))]:
        monkeypatch.setitem(sys.modules, name, None)
    with pytest.raises(SystemExit) as info:
        openpcdet.main([str(script)])
    assert info.value.code == 1
    err = capsys.readouterr().err
    assert err.startswith("error: cannot import OpenPCDet") and err.count("\n") == 1
