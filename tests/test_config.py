import dataclasses
import math

import pytest
import yaml

from drcpo.config import (
    PRESETS,
    AugmentConfig,
    DRCPOConfig,
    load_config,
    per_class,
    preset_path,
)
from drcpo.errors import ConfigError


def test_default_yaml_spells_out_the_dataclass_defaults():
    assert load_config("default") == AugmentConfig() == load_config(None) == load_config({})
    on_disk = yaml.safe_load(preset_path("default").read_text())
    assert on_disk == AugmentConfig().to_dict()


def test_paper_defaults():
    config = AugmentConfig()
    d = config.drcpo
    assert config.pipeline == "drcpo"
    assert d.sample == {"Car": 10, "Pedestrian": 10, "Cyclist": 10}
    assert per_class(d.min_points, "Car") == per_class(d.min_points, "Van") == 5
    assert d.construction.mode == "partition"
    assert (d.construction.coverage, d.construction.max_iterations) == (0.85, 20)
    assert d.construction.margin == 0.05
    assert d.placement.x_range == [0.0, 70.4] and d.placement.y_range == [-40.0, 40.0]
    assert d.placement.height == "ground" and d.placement.max_non_ground_points == 10
    assert d.self_occlusion.radius_factor == 200.0 and d.self_occlusion.min_points == 5
    assert d.external_occlusion.preset == "pv_rcnn_plusplus"
    assert d.external_occlusion.scope == "inserted" and d.external_occlusion.mode == "hpr"
    assert d.min_points_after == 5
    assert config.gt_sampling.targets == {"Car": 20, "Pedestrian": 15, "Cyclist": 15}
    g = config.global_augmentation
    assert g.flip.probability == 0.5 and g.flip.axes == ["x"]
    assert g.rotation.range == pytest.approx([-math.pi / 4, math.pi / 4])
    assert g.scaling.range == [0.95, 1.05]


def test_round_trip_through_dict_and_yaml(tmp_path):
    config = load_config(
        {
            "pipeline": "cda",
            "drcpo": {"construction": {"mode": "whole"}, "min_points": 7},
            "global_augmentation": {"scaling": {"range": [0.9, 1.1]}},
        }
    )
    assert config.pipeline == "cda" and config.drcpo.construction.mode == "whole"
    assert config.drcpo.min_points == {"default": 7}
    assert load_config(config.to_dict()) == config
    path = tmp_path / "cfg.yaml"
    path.write_text(config.to_yaml())
    assert load_config(path) == config
    assert load_config(str(path)) == config


@pytest.mark.parametrize("name", PRESETS)
def test_presets_load_and_set_the_e_hpr_preset(name):
    config = load_config(name)
    assert config.preset == name
    assert config.drcpo.external_occlusion.preset == name
    assert load_config(config.to_dict()) == config
    # A user's file names a preset and overrides some keys on top of it.
    mixed = load_config({"preset": name, "drcpo": {"sample": {"Car": 3}}})
    assert mixed.drcpo.external_occlusion.preset == name
    assert mixed.drcpo.sample == {"Car": 3}


def test_config_is_frozen():
    config = AugmentConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.pipeline = "cda"  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.drcpo.construction.coverage = 0.5  # type: ignore[misc]


def test_mutable_defaults_are_not_shared():
    a, b = DRCPOConfig(), DRCPOConfig()
    a.sample["Car"] = 99
    assert b.sample["Car"] == 10


@pytest.mark.parametrize(
    ("data", "path", "allowed"),
    [
        ({"pipline": "cda"}, "pipline", "drcpo, global_augmentation, gt_sampling"),
        ({"drcpo": {"construction": {"coverag": 0.9}}}, "drcpo.construction.coverag", "coverage"),
        ({"drcpo": {"placement": {"z_range": [0, 1]}}}, "drcpo.placement.z_range", "x_range"),
        ({"global_augmentation": {"flip": {"p": 1}}}, "global_augmentation.flip.p", "probability"),
    ],
)
def test_unknown_key_names_its_path_and_the_allowed_keys(data, path, allowed):
    with pytest.raises(ConfigError) as info:
        load_config(data)
    message = str(info.value)
    assert f"'{path}'" in message and "unknown" in message
    assert allowed in message


@pytest.mark.parametrize(
    ("data", "path", "allowed"),
    [
        ({"drcpo": {"construction": {"coverage": 1.5}}}, "drcpo.construction.coverage", "(0, 1]"),
        ({"drcpo": {"construction": {"coverage": 0}}}, "drcpo.construction.coverage", "(0, 1]"),
        ({"drcpo": {"construction": {"max_iterations": -1}}}, "max_iterations", "[0, 1000]"),
        ({"gt_sampling": {"targets": {"Car": -2}}}, "gt_sampling.targets.Car", "[0, 1000]"),
        ({"drcpo": {"self_occlusion": {"radius_factor": 0}}}, "radius_factor", "(0, "),
        ({"global_augmentation": {"flip": {"probability": 2}}}, "flip.probability", "[0, 1]"),
        ({"global_augmentation": {"scaling": {"range": [0, 1]}}}, "scaling.range[0]", "(0, inf]"),
        ({"drcpo": {"placement": {"x_range": [0, 500]}}}, "x_range[1]", "[-200, 200]"),
    ],
)
def test_out_of_range_names_the_key_and_the_allowed_range(data, path, allowed):
    with pytest.raises(ConfigError) as info:
        load_config(data)
    message = str(info.value)
    assert path in message and "out of range" in message and allowed in message


@pytest.mark.parametrize(
    ("data", "words"),
    [
        ({"drcpo": {"construction": {"mode": "magic"}}}, ["mode", "partition, whole"]),
        ({"drcpo": {"external_occlusion": {"scope": "all"}}}, ["scope", "inserted, frame"]),
        ({"drcpo": {"external_occlusion": {"preset": "voxelnet"}}}, ["second", "pv_rcnn"]),
        ({"preset": "voxelnet"}, ["preset", "pointrcnn"]),
        ({"drcpo": {"enabled": "yes"}}, ["drcpo.enabled", "true or false"]),
        ({"drcpo": {"min_points": 2.5}}, ["drcpo.min_points", "integer"]),
        ({"drcpo": {"sample": [10, 10]}}, ["drcpo.sample", "mapping"]),
        ({"drcpo": {"construction": {"margin": None}}}, ["margin", "null"]),
        ({"drcpo": {"construction": {"grids": {"Car": [10, 4]}}}}, ["grids.Car", "[nx, ny, nz]"]),
        ({"global_augmentation": {"rotation": {"range": [1, -1]}}}, ["rotation.range", "low"]),
        ({"global_augmentation": {"flip": {"axes": ["z"]}}}, ["axes[0]", "x, y"]),
        ({"drcpo": 5}, ["drcpo", "mapping"]),
        ({"drcpo": {"construction": {"coverage": float("nan")}}}, ["coverage", "finite"]),
    ],
)
def test_bad_values_name_the_key(data, words):
    with pytest.raises(ConfigError) as info:
        load_config(data)
    for word in words:
        assert word in str(info.value)


def test_optional_overrides_accept_null_and_numbers():
    config = load_config({"drcpo": {"external_occlusion": {"radius": 5e4, "viewpoint_z": 1.0}}})
    assert config.drcpo.external_occlusion.radius == 5e4
    assert load_config({"drcpo": {"external_occlusion": {"radius": None}}}) == AugmentConfig()


def test_file_errors_name_the_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.yaml")
    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_text("drcpo: [unclosed\n")
    with pytest.raises(ConfigError, match="bad.yaml.*not valid YAML"):
        load_config(bad_yaml)
    not_mapping = tmp_path / "list.yaml"
    not_mapping.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="list.yaml.*mapping"):
        load_config(not_mapping)
    bad_key = tmp_path / "key.yaml"
    bad_key.write_text("drcpo:\n  construction:\n    coverage: 3\n")
    with pytest.raises(ConfigError, match=r"key\.yaml: .*drcpo\.construction\.coverage"):
        load_config(bad_key)
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    assert load_config(empty) == AugmentConfig()


def test_unknown_preset_name():
    with pytest.raises(ConfigError, match="unknown preset"):
        preset_path("voxelnet")


def test_per_class_lookup():
    assert per_class({"Car": 3, "default": 7}, "Car") == 3
    assert per_class({"Car": 3, "default": 7}, "Van") == 7
    assert per_class({"Car": 3}, "Van", fallback=0) == 0
