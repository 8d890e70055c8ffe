"""Property-based fuzzing of :func:`drcpo.config.load_config`.

Random documents (the default config with random keys replaced by random values, random YAML
text, random bytes, random non-path sources) must each give a valid config, which reads back
unchanged, or a :class:`ConfigError`; any other exception is a bug. The number of cases per test
is ``DRCPO_FUZZ_EXAMPLES`` (default 200), through the hypothesis profile ``drcpo-fuzz``
(``fuzz_settings.py``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest
import yaml
from fuzz_settings import FUZZ
from hypothesis import given
from hypothesis import strategies as st

from drcpo.config import KITTI_CLASSES, PRESETS, AugmentConfig, load_config
from drcpo.config_fields import key_fields
from drcpo.errors import ConfigError

DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


def _key_paths(config: Any, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """Every section and leaf key of the config tree, as tuples of names."""
    paths = []
    for f in key_fields(config):
        path = (*prefix, f.name)
        paths.append(path)
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            paths.extend(_key_paths(value, path))
    return paths


KEY_PATHS = _key_paths(AugmentConfig())
WORDS = sorted(
    {name for path in KEY_PATHS for name in path}
    | set(KITTI_CLASSES)
    | set(PRESETS)
    | {"default", "Pedestrain", "x", "y", "hpr", "ground", "source", "auto"}
)

scalars = (
    st.none()
    | st.booleans()
    | st.integers(-5, 2000)
    | st.integers()
    | st.floats(-300, 300)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.sampled_from(WORDS)
    | st.text(max_size=8)
)
values = st.recursive(
    scalars,
    lambda inner: (
        st.lists(inner, max_size=4)
        | st.dictionaries(st.sampled_from(WORDS) | scalars, inner, max_size=4)
    ),
    max_leaves=12,
)


@st.composite
def documents(draw: st.DrawFn) -> dict[str, Any]:
    """The defaults (or nothing) with a few keys, known or made up, set to random values."""
    doc: dict[str, Any] = AugmentConfig().to_dict() if draw(st.booleans()) else {}
    for _ in range(draw(st.integers(0, 5))):
        path = list(draw(st.sampled_from(KEY_PATHS)))
        if draw(st.integers(0, 9)) == 0:
            path[-1] = draw(st.sampled_from(WORDS))  # a key that may not exist there
        node = doc
        for name in path[:-1]:
            if not isinstance(node.get(name), dict):
                node[name] = {}
            node = node[name]
        node[path[-1]] = draw(values)
    return doc


def _valid_or_config_error(load) -> None:
    try:
        config = load()
    except ConfigError as error:
        assert str(error)  # a message, naming the culprit
        return
    assert isinstance(config, AugmentConfig)
    assert load_config(config.to_dict()) == config


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


@FUZZ
@given(documents())
def test_random_mappings(doc):
    _valid_or_config_error(lambda: load_config(doc))


@FUZZ
@given(documents(), st.sampled_from(["block", "flow"]))
def test_random_documents_as_yaml_files(workdir, doc, style):
    path = workdir / "doc.yaml"
    text = yaml.dump(doc, Dumper=DUMPER, default_flow_style=style == "flow", allow_unicode=True)
    path.write_text(text)
    _valid_or_config_error(lambda: load_config(path))


yaml_tokens = st.sampled_from(
    [*WORDS, ": ", "\n", "\n  ", "- ", "[", "]", "{", "}", ", ", "&a ", "*a", "<<: ", "!!int ",
     "!!float ", "!!str ", "!!binary ", "!!set ", "? ", "'", '"', "#", "1e5", "-.inf", ".nan",
     "0x1f", "0o17", "1_000", "2001-12-14", "~", "null", "yes", "|\n  ", "%YAML 1.1\n---\n",
     "\t", "\\u0000"]
)  # fmt: skip


@FUZZ
@given(st.lists(yaml_tokens | st.text(max_size=3), max_size=40).map("".join))
def test_random_yaml_text(workdir, text):
    path = workdir / "text.yaml"
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    _valid_or_config_error(lambda: load_config(path))


@FUZZ
@given(st.binary(max_size=200))
def test_random_bytes(workdir, data):
    path = workdir / "bytes.yaml"
    path.write_bytes(data)
    _valid_or_config_error(lambda: load_config(path))


@FUZZ
@given(values.filter(lambda v: not isinstance(v, str | dict)))
def test_random_sources(source):
    # Strings are file paths (covered above through files); everything else is a value.
    _valid_or_config_error(lambda: load_config(source))
