import dataclasses
import math
from importlib import resources
from pathlib import Path

import pytest
import yaml

from drcpo.config import (
    PIPELINE_PRESETS,
    PRESETS,
    AugmentConfig,
    DRCPOConfig,
    ExternalOcclusionConfig,
    load_config,
    per_class,
    preset_path,
)
from drcpo.config_fields import key_fields
from drcpo.construction import ConstructionConfig
from drcpo.errors import ConfigError
from drcpo.index import IndexConfig
from drcpo.placement import PlacementConfig


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
    assert (d.construction.coverage, d.construction.max_iterations) == (0.85, 20)
    assert d.construction.margin == 0.05
    assert d.placement.x_range == [0.0, 70.4] and d.placement.y_range == [-40.0, 40.0]
    assert d.placement.max_non_ground_points == 10 and d.placement.ground_tolerance == 0.2
    assert d.self_occlusion.radius_factor == 200.0 and d.self_occlusion.min_points == 5
    assert (d.external_occlusion.radius, d.external_occlusion.viewpoint_z) == (1e5, 0.0)
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
            "drcpo": {"construction": {"margin": 0.0}, "min_points": 7},
            "global_augmentation": {"scaling": {"range": [0.9, 1.1]}},
        }
    )
    assert config.pipeline == "cda" and config.drcpo.construction.margin == 0.0
    assert config.drcpo.min_points == {"default": 7}
    assert load_config(config.to_dict()) == config
    path = tmp_path / "cfg.yaml"
    path.write_text(config.to_yaml())
    assert load_config(path) == config
    assert load_config(str(path)) == config


@pytest.mark.parametrize("name", PRESETS)
def test_presets_load_and_set_the_e_hpr_setting(name):
    config = load_config(name)
    assert config.preset == name
    setting = config.drcpo.external_occlusion
    assert load_config(config.to_dict()) == config
    # A user's file names a preset and overrides some keys on top of it.
    mixed = load_config({"preset": name, "drcpo": {"sample": {"Car": 3}}})
    assert mixed.drcpo.external_occlusion == setting
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
        ({"global_augmentation": {"scaling": {"range": [0, 1]}}}, "scaling.range[0]", "(0, 10]"),
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
        ({"drcpo": {"placement": {"location": "magic"}}}, ["location", "random, source"]),
        ({"drcpo": {"external_occlusion": {"preset": "second"}}}, ["preset", "viewpoint_z"]),
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


def test_optional_keys_accept_null_and_numbers_and_the_others_numbers_only():
    config = load_config({"drcpo": {"external_occlusion": {"radius": 5e4, "viewpoint_z": 1.0}}})
    assert config.drcpo.external_occlusion.radius == 5e4
    with pytest.raises(ConfigError, match="external_occlusion.radius"):
        load_config({"drcpo": {"external_occlusion": {"radius": None}}})
    no_test = load_config({"drcpo": {"placement": {"occluded_fraction": None}}})
    assert no_test.drcpo.placement.occluded_fraction is None
    assert load_config({"drcpo": {"placement": {"heading_range": None}}}) == AugmentConfig()


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


# Misspelt class names ------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("data", "path"),
    [
        ({"drcpo": {"sample": {"Pedestrain": 10}}}, "drcpo.sample.Pedestrain"),
        ({"gt_sampling": {"targets": {"car": 20}}}, "gt_sampling.targets.car"),
        ({"drcpo": {"min_points": {"Cyclst": 5}}}, "drcpo.min_points.Cyclst"),
        ({"gt_sampling": {"min_points": {"Vann": 5}}}, "gt_sampling.min_points.Vann"),
        ({"drcpo": {"construction": {"mirror": ["Car", "Cylist"]}}}, "mirror[1]"),
        ({"drcpo": {"construction": {"grids": {"Cars": [10, 4, 3]}}}}, "grids.Cars"),
        # "default" is the fallback of the minimum-point maps only: in sample or targets it
        # would be read as a class named "default" and sample nothing.
        ({"drcpo": {"sample": {"default": 3}}}, "drcpo.sample.default"),
    ],
)
def test_unknown_class_names_the_key_and_lists_the_known_classes(data, path):
    with pytest.raises(ConfigError) as info:
        load_config(data)
    message = str(info.value)
    assert path in message and "unknown class" in message
    assert "Car, Cyclist, Misc, Pedestrian, Person_sitting, Tram, Truck, Van" in message
    assert "known_classes" in message  # says how to allow another data set's classes


def test_unknown_class_suggests_the_close_match():
    with pytest.raises(ConfigError, match="did you mean 'Pedestrian'"):
        load_config({"drcpo": {"sample": {"Pedestrain": 10}}})


def test_known_classes_allow_another_data_sets_classes():
    data = {
        "known_classes": ["Vehicle", "Pedestrian"],
        "gt_sampling": {"targets": {"Vehicle": 4}},
        "drcpo": {
            "sample": {"Vehicle": 3},
            "min_points": {"Vehicle": 9, "default": 5},
            "construction": {"mirror": ["Vehicle"], "grids": {"Vehicle": [10, 4, 3]}},
        },
    }
    config = load_config(data)
    assert config.known_classes == ["Vehicle", "Pedestrian"]
    assert config.drcpo.sample == {"Vehicle": 3}
    assert load_config(config.to_dict()) == config
    # The default maps name Car: the message says which key to give.
    with pytest.raises(
        ConfigError,
        match=r"'gt_sampling\.targets\.Car' \(a default value\).*Pedestrian, Vehicle; set gt_samp",
    ):
        load_config({"known_classes": ["Vehicle", "Pedestrian"]})


def test_known_classes_apply_wherever_the_key_appears_in_a_file(tmp_path):
    path = tmp_path / "late.yaml"
    path.write_text(
        "drcpo:\n  sample: {Vehicle: 2}\n  construction: {mirror: []}\n"
        "known_classes: [Vehicle]\ngt_sampling:\n  targets: {Vehicle: 5}\n"
    )
    config = load_config(path)
    assert config.drcpo.sample == {"Vehicle": 2} and config.drcpo.construction.mirror == []


# Ranges and magnitudes -----------------------------------------------------------------------
def test_empty_placement_range_is_refused():
    with pytest.raises(ConfigError, match=r"drcpo\.placement\.x_range.*low must be below high"):
        load_config({"drcpo": {"placement": {"x_range": [200, 200]}}})


def test_absurd_radius_is_refused_naming_the_key():
    with pytest.raises(ConfigError, match=r"drcpo\.external_occlusion\.radius.*out of range"):
        load_config({"drcpo": {"external_occlusion": {"radius": 1e300}}})


def test_constant_rotation_and_scaling_stay_allowed():
    config = load_config(
        {"global_augmentation": {"rotation": {"range": [0, 0]}, "scaling": {"range": [1, 1]}}}
    )
    assert config.global_augmentation.rotation.range == [0.0, 0.0]


@pytest.mark.parametrize("value", [10**400, -(10**400)])
def test_huge_integers_are_config_errors(value):
    with pytest.raises(ConfigError, match=r"drcpo\.construction\.margin.*out of range"):
        load_config({"drcpo": {"construction": {"margin": value}}})
    with pytest.raises(ConfigError, match=r"drcpo\.min_points_after.*out of range"):
        load_config({"drcpo": {"min_points_after": value}})


# One row per config key: a bad value -> ConfigError naming that key ---------------------------
BAD_VALUES = {
    "pipeline": "magic",
    "preset": "voxelnet",
    "known_classes": [],
    "gt_sampling.enabled": "yes",
    "gt_sampling.targets": {"Car": 1001},
    "gt_sampling.min_points": -1,
    "gt_sampling.exclude_difficulty": [3],
    "gt_sampling.use_road_plane": 1,
    "drcpo.enabled": 0,
    "drcpo.sample": {"Car": 1.5},
    "drcpo.min_points": 1e7,
    "drcpo.exclude_difficulty": "-1",
    "drcpo.min_points_after": -1,
    "drcpo.construction.coverage": 0,
    "drcpo.construction.max_iterations": 1001,
    "drcpo.construction.margin": 1.5,
    "drcpo.construction.mirror": "Car",
    "drcpo.construction.grids": {"Car": [0, 4, 3]},
    "drcpo.placement.x_range": [200, 200],
    "drcpo.placement.y_range": [10, -10],
    "drcpo.placement.location": "anywhere",
    "drcpo.placement.heading_range": 4.0,
    "drcpo.placement.max_non_ground_points": -1,
    "drcpo.placement.ground_tolerance": float("inf"),
    "drcpo.placement.occluded_fraction": 0,
    "drcpo.placement.camera_fov": "sometimes",
    "drcpo.self_occlusion.enabled": "true",
    "drcpo.self_occlusion.radius_factor": 1e300,
    "drcpo.self_occlusion.min_points": 10**7,
    "drcpo.external_occlusion.enabled": None,
    "drcpo.external_occlusion.radius": 1e300,
    "drcpo.external_occlusion.viewpoint_z": 1e3,
    "global_augmentation.enabled": "no",
    "global_augmentation.flip.probability": -0.1,
    "global_augmentation.flip.axes": ["x", "x"],
    "global_augmentation.rotation.range": [0, 7],
    "global_augmentation.scaling.range": [0.5, 1e300],
    "index.k": 0,
    "index.alpha": 0,
    "index.min_points": -1,
    "index.exclude_difficulty": [7],
    "index.classes": ["Cars"],
    "index.approximate_above": -1,
    "index.approx_factor": 0.5,
}
MORE_BAD_VALUES = [
    ("known_classes", ["Car", "Car"]),
    ("known_classes", ["default"]),
    ("known_classes", "Car"),
    ("gt_sampling.targets", {3: 4}),
    ("drcpo.sample", {"Car": True}),
    ("drcpo.construction.mirror", ["Car", "Car"]),
    ("drcpo.construction.grids", {"Car": [10, 4, 3, 1]}),
    ("drcpo.construction.grids", {5: [10, 4, 3]}),
    ("drcpo.placement.x_range", [0.0]),
    ("drcpo.placement.x_range", [0.0, 10.0, 20.0]),
    ("drcpo.placement.x_range", "0, 70"),
    ("drcpo.placement.y_range", [float("nan"), 1.0]),
    ("global_augmentation.rotation.range", [-0.1, float("inf")]),
    ("global_augmentation.flip.axes", "x"),
    ("drcpo.external_occlusion.radius", -1.0),
    ("drcpo.external_occlusion.viewpoint_z", "high"),
    ("gt_sampling.exclude_difficulty", [1.5]),
    ("index.k", 100_001),
    ("index.classes", "Car"),
    ("index.exclude_difficulty", -1),
]


def _nest(path: str, value):
    *sections, leaf = path.split(".")
    data = {leaf: value}
    for section in reversed(sections):
        data = {section: data}
    return data


def _leaf_keys(config, prefix=""):
    for f in key_fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            yield from _leaf_keys(value, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}"


def test_every_config_key_has_a_bad_value_row():
    assert sorted(BAD_VALUES) == sorted(_leaf_keys(AugmentConfig()))


@pytest.mark.parametrize(
    ("path", "value"), [*BAD_VALUES.items(), *MORE_BAD_VALUES], ids=lambda x: str(x)[:40]
)
def test_bad_value_names_its_key(path, value):
    with pytest.raises(ConfigError) as info:
        load_config(_nest(path, value))
    assert f"'{path}" in str(info.value)


# Files ---------------------------------------------------------------------------------------
def test_duplicate_yaml_key_names_the_key_and_line(tmp_path):
    path = tmp_path / "dup.yaml"
    path.write_text(
        "drcpo:\n"
        "  sample: {Car: 10}\n"
        "  min_points: 5\n"
        "  sample: {Car: 3}\n"  # line 4: the second sample silently won before
    )
    with pytest.raises(
        ConfigError, match=r"dup\.yaml:4: duplicate key 'sample' \(first on line 2\)"
    ):
        load_config(path)


def test_yaml_merge_keys_may_be_overridden(tmp_path):
    path = tmp_path / "merge.yaml"
    path.write_text(
        "base: &base {Car: 10, Pedestrian: 4}\ndrcpo:\n  sample:\n    <<: *base\n    Car: 2\n"
    )
    with pytest.raises(ConfigError, match="unknown config key 'base'"):
        load_config(path)  # the anchor's key is not a config key; the merge itself is fine
    path.write_text(
        "drcpo:\n  sample: &s {Car: 10}\ngt_sampling:\n  targets:\n    <<: *s\n    Car: 2\n"
    )
    assert load_config(path).gt_sampling.targets == {"Car": 2}


def test_non_utf8_file_names_the_file(tmp_path):
    path = tmp_path / "latin1.yaml"
    path.write_bytes("# Fußgänger\ndrcpo: {enabled: true}\n".encode("latin-1"))
    with pytest.raises(ConfigError, match=r"latin1\.yaml: not UTF-8 text \(byte 0xdf at offset 4"):
        load_config(path)


def test_exponent_without_dot_reads_as_a_number(tmp_path):
    # YAML 1.1 (PyYAML) reads 5e4 as a string; the config loader reads it as YAML 1.2 does.
    path = tmp_path / "exp.yaml"
    path.write_text("drcpo:\n  external_occlusion: {radius: 5e4, viewpoint_z: -1E0}\n")
    occlusion = load_config(path).drcpo.external_occlusion
    assert (occlusion.radius, occlusion.viewpoint_z) == (5e4, -1.0)


def test_deeply_nested_yaml_is_a_config_error(tmp_path):
    path = tmp_path / "deep.yaml"
    path.write_text("drcpo: " + "[" * 100_000 + "]" * 100_000 + "\n")
    with pytest.raises(ConfigError, match="deep.yaml"):
        load_config(path)


@pytest.mark.parametrize("source", [5, 2.5, b"default", ["default"], "a\0b", "x" * 5000])
def test_bad_sources_are_config_errors(source):
    with pytest.raises(ConfigError):
        load_config(source)


@pytest.mark.parametrize(
    "text",
    [
        "a: 2001-13-45",
        "a: !!float abc",
        "a: !!int abc",
        "a: !!bool maybe",
        "a: !!timestamp x",
        "a: " + "1" * 5000,
    ],
)
def test_values_pyyaml_cannot_construct_are_config_errors(tmp_path, text):
    path = tmp_path / "odd.yaml"
    path.write_text(text + "\n")
    with pytest.raises(ConfigError, match=r"odd\.yaml: not valid YAML"):
        load_config(path)


def test_integer_past_the_digit_limit_is_named_not_printed():
    with pytest.raises(ConfigError, match=r"min_points_after' = <an int of \d+ bits> is out"):
        load_config({"drcpo": {"min_points_after": 10**5000}})


# One class per stage, composed -------------------------------------------------------------
def test_the_stage_sections_are_the_stage_modules_classes():
    config = AugmentConfig()
    assert type(config.drcpo.construction) is ConstructionConfig
    assert type(config.drcpo.placement) is PlacementConfig
    assert type(config.index) is IndexConfig
    assert config.index == IndexConfig()  # the paper defaults of `drcpo index`


def test_a_stage_config_built_in_code_is_checked_as_a_file_would_be():
    with pytest.raises(ConfigError, match=r"'drcpo\.construction\.coverage' = 2 is out of range"):
        ConstructionConfig(coverage=2)
    with pytest.raises(ConfigError, match=r"'drcpo\.placement\.max_non_ground_points' = -1 is out"):
        PlacementConfig(max_non_ground_points=-1)
    with pytest.raises(ConfigError, match=r"'index\.k' = 0 is out of range; allowed range: \[1,"):
        IndexConfig(k=0)
    # Normalised as a file's values: lists, floats.
    assert PlacementConfig(x_range=(0, 12)).x_range == [0.0, 12.0]
    assert ConstructionConfig(mirror=("Car",)).mirror == ["Car"]


def test_index_section_round_trips_through_yaml(tmp_path):
    path = tmp_path / "index.yaml"
    path.write_text(
        "index:\n  k: 32\n  alpha: 0.5\n  min_points: 9\n  exclude_difficulty: [-1]\n"
        "  classes: [Car, Pedestrian]\n  approximate_above: 1000\n  approx_factor: 2\n"
    )
    config = load_config(path)
    assert config.index == IndexConfig(
        k=32,
        alpha=0.5,
        min_points=9,
        exclude_difficulty=[-1],
        classes=["Car", "Pedestrian"],
        approximate_above=1000,
        approx_factor=2.0,
    )
    again = tmp_path / "again.yaml"
    again.write_text(config.to_yaml())
    assert load_config(again) == config
    assert yaml.safe_load(config.to_yaml())["index"] == {
        "k": 32,
        "alpha": 0.5,
        "min_points": 9,
        "exclude_difficulty": [-1],
        "classes": ["Car", "Pedestrian"],
        "approximate_above": 1000,
        "approx_factor": 2.0,
    }


def test_the_index_takes_construction_grids_and_mirror():
    config = load_config(
        {"drcpo": {"construction": {"grids": {"Car": [5, 2, 3]}, "mirror": ["Cyclist"]}}}
    )
    assert config.index.grids == {"Car": [5, 2, 3]} and config.index.mirror == ["Cyclist"]
    assert config.index.grid("Car") == config.drcpo.construction.grid("Car") == (5, 2, 3)
    # Also when the tree is built in code.
    built = AugmentConfig(
        drcpo=DRCPOConfig(construction=ConstructionConfig(grids={"Van": [2, 2, 2]}, mirror=[]))
    )
    assert built.index.grids == {"Van": [2, 2, 2]} and built.index.mirror == []


@pytest.mark.parametrize(
    ("key", "source"),
    [("grids", "drcpo.construction.grids"), ("mirror", "drcpo.construction.mirror")],
)
def test_index_grids_and_mirror_are_not_keys_of_their_own(key, source):
    with pytest.raises(ConfigError) as info:
        load_config({"index": {key: {"Car": [5, 2, 3]} if key == "grids" else ["Car"]}})
    message = str(info.value)
    assert f"'index.{key}' is not set in a config file" in message and source in message


def test_a_wrong_index_key_names_the_file_and_the_key(tmp_path):
    path = tmp_path / "my.yaml"
    path.write_text("index:\n  kk: 20\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and "unknown config key 'index.kk'" in message
    assert "approx_factor, approximate_above, classes, exclude_difficulty, k," in message
    path.write_text("index:\n  k: 0\n")
    with pytest.raises(ConfigError, match=r"my\.yaml: config key 'index\.k' = 0 is out of range"):
        load_config(path)


def test_per_call_placement_fields_are_not_config_keys():
    with pytest.raises(ConfigError, match=r"'drcpo\.placement\.fov_only' is not set in a config"):
        load_config({"drcpo": {"placement": {"fov_only": True}}})
    assert "clearance" not in AugmentConfig().to_dict()["drcpo"]["placement"]


# Detector presets ------------------------------------------------------------------------------
PAPERS_E_HPR = {
    "second": (300000.0, 2.0),
    "pointrcnn": (300000.0, 1.0),
    "pv_rcnn": (100000.0, 0.0),
    "pv_rcnn_plusplus": (100000.0, 0.0),
}


def test_detector_presets_are_yaml_files_with_the_papers_e_hpr_settings():
    configs = resources.files("drcpo") / "configs"
    files = {Path(str(f)).stem for f in configs.iterdir() if str(f).endswith(".yaml")}
    assert files == {*PRESETS, *PIPELINE_PRESETS}  # every preset a file, every file a preset
    settings = {name: load_config(name).drcpo.external_occlusion for name in PRESETS}
    assert {k: (v.radius, v.viewpoint_z) for k, v in settings.items()} == PAPERS_E_HPR
    # the defaults are PV-RCNN++'s, the paper's reference configuration
    assert load_config().drcpo.external_occlusion == settings["pv_rcnn_plusplus"]


@pytest.mark.parametrize("name", PRESETS)
def test_keys_given_with_a_preset_override_its_radius_and_viewpoint(name):
    own = load_config({"preset": name, "drcpo": {"external_occlusion": {"radius": 5.0}}})
    setting = own.drcpo.external_occlusion
    assert (setting.radius, setting.viewpoint_z) == (5.0, PAPERS_E_HPR[name][1])
    assert ExternalOcclusionConfig(radius=5.0, viewpoint_z=-1.0).viewpoint_z == -1.0


def test_configs_are_hashable_and_equal_by_value():
    a = load_config({"drcpo": {"sample": {"Car": 1, "Cyclist": 2}}})
    b = load_config({"drcpo": {"sample": {"Cyclist": 2, "Car": 1}}})
    assert a == b and hash(a) == hash(b) and len({a, b, AugmentConfig()}) == 2
    assert a != AugmentConfig() and a.drcpo != a  # another class is never equal
    assert hash(ConstructionConfig(grids={"Car": [4, 2, 2]})) != hash(ConstructionConfig())
