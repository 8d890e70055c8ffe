"""The curated public API in ``drcpo/__init__.py``."""

import importlib
import subprocess
import sys

import pytest

import drcpo


@pytest.mark.parametrize("name", drcpo.__all__)
def test_every_public_name_resolves_to_its_home_definition(name):
    value = getattr(drcpo, name)
    home = drcpo._LAZY.get(name)
    if home is not None:
        assert value is getattr(importlib.import_module(home), name)


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no_such_thing"):
        drcpo.no_such_thing  # noqa: B018


def test_the_users_names_are_exported():
    for name in (
        "Frame",
        "load_config",
        "build_pipeline",
        "GroundTruthDatabase",
        "build_index",
        "load_index",
        "hidden_point_removal",
        "DRCPO",
        "GroundTruthSampling",
    ):
        assert name in drcpo.__all__ and name in dir(drcpo)


def test_importing_drcpo_does_not_import_the_transforms():
    code = "import sys, drcpo; print('drcpo.transforms' in sys.modules, 'numba' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["False", "False"]
