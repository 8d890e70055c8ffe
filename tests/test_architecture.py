"""The package's shape, as docs/architecture.md states it: no import cycle, no import from a higher
layer, no module over 600 lines (split by concept, not squeezed). Imports are read from the sources
(every ``import`` statement, also those inside functions), so a cycle hidden by a lazy import
counts too."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
ARCHITECTURE = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"
MAX_LINES = 600

#: Layer of each module, by its dotted name or the longest listed prefix (bottom = 0); a module
#: may import from lower layers and, acyclically, from its own package.
LAYERS: dict[str, int] = {
    "drcpo.errors": 0,
    "drcpo._numba_cache": 0,
    "drcpo.frame": 1,
    "drcpo.geometry": 1,
    "drcpo.outputs": 1,
    "drcpo.staging": 1,
    "drcpo.config_fields": 1,
    "drcpo.partitions": 2,
    "drcpo.ground": 2,
    "drcpo.ground_plane": 2,
    "drcpo.collisions": 2,
    "drcpo.datasets": 2,
    "drcpo.datasets.nuscenes": 2,
    "drcpo.datasets.nuscenes_writer": 2,
    "drcpo.datasets.nuscenes_infos": 4,
    "drcpo.viz": 2,
    "drcpo.occlusion": 3,
    "drcpo.database": 3,
    "drcpo.synth": 3,
    "drcpo.synth.nuscenes": 3,
    "drcpo.evaluation": 3,
    "drcpo.construction": 4,
    "drcpo.construction_kernels": 4,
    "drcpo.index": 4,
    "drcpo.index_build": 4,
    "drcpo.similarity": 4,
    "drcpo.placement": 4,
    "drcpo.poses": 4,
    "drcpo.config": 5,
    "drcpo.transforms": 6,
    "drcpo.pipeline": 7,
    "drcpo.datasets.export": 7,
    "drcpo.warmup": 7,
    "drcpo.distributed": 8,
    "drcpo.integrations": 9,
    "drcpo.demo": 9,
    "drcpo.demo_figures": 9,
    "drcpo.cli": 9,
    "drcpo.cli_console": 9,
    "drcpo.cli_data": 9,
    "drcpo": 9,
}


def _modules() -> dict[str, Path]:
    modules = {}
    for path in (SRC / "drcpo").rglob("*.py"):
        parts = path.relative_to(SRC).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        modules[name] = path
    return modules


MODULES = _modules()


def _resolve(name: str) -> str:
    """The drcpo module an imported dotted name lives in (``from a.b import c``: a.b.c or a.b)."""
    while name not in MODULES:
        name = name.rpartition(".")[0]
    return name


def imports_of(path: Path) -> set[str]:
    """The drcpo modules ``path`` imports anywhere in it."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module.split(".")[0] == "drcpo":
                found |= {_resolve(f"{node.module}.{alias.name}") for alias in node.names}
        elif isinstance(node, ast.Import):
            found |= {_resolve(a.name) for a in node.names if a.name.split(".")[0] == "drcpo"}
    return found


GRAPH = {name: imports_of(path) - {name} for name, path in MODULES.items()}


def layer_of(module: str) -> int:
    prefix = module
    while prefix not in LAYERS:
        prefix = prefix.rpartition(".")[0]
    return LAYERS[prefix]


def _package(module: str) -> str:
    return module if MODULES[module].name == "__init__.py" else module.rpartition(".")[0]


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` (its modules in order, the first repeated), else None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt) :], nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        state[node] = 2
        path.pop()
        return None

    for start in sorted(graph):
        if start not in state and (cycle := visit(start)):
            return cycle
    return None


def test_no_import_cycle():
    assert find_cycle(GRAPH) is None, find_cycle(GRAPH)


def test_the_cycle_finder_finds_cycles():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_go_down_the_layers(module):
    """Lower layers never import higher ones; within a layer, only the module's own package."""
    wrong = []
    for target in sorted(GRAPH[module]):
        own, theirs = _package(module), _package(target)
        same_package = theirs == own or theirs.startswith(own + ".")
        if layer_of(target) > layer_of(module) or (
            layer_of(target) == layer_of(module) and not same_package
        ):
            wrong.append(f"{target} (layer {layer_of(target)})")
    assert not wrong, f"{module} (layer {layer_of(module)}) imports {wrong}"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_modules_stay_short(module):
    lines = len(MODULES[module].read_text().splitlines())
    assert lines <= MAX_LINES, f"{module}: {lines} lines; split it by concept"


def test_every_layered_package_is_in_the_architecture_document():
    text = ARCHITECTURE.read_text()
    for prefix in LAYERS:
        if prefix == "drcpo":
            continue
        name = prefix.removeprefix("drcpo.").replace(".", "/")
        package = (SRC / prefix.replace(".", "/")).is_dir()
        shown = f"{name}/" if package else f"{name}.py"
        assert shown in text or (not package and shown.split("/")[-1] in text), shown


def threads_started(path: Path) -> list[str]:
    """Where ``path`` starts threads: a thread pool or a ``threading.Thread``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call):
            name = ast.unparse(node.func)
            if name.split(".")[-1] in ("ThreadPoolExecutor", "Thread", "ThreadPool"):
                found.append(f"{path.name}:{node.lineno} {name}")
    return found


def test_no_threads_inside_a_call():
    # Parallelism comes from worker processes (data loaders, drcpo augment --workers, Ray).
    started = [where for path in MODULES.values() for where in threads_started(path)]
    assert started == []


def test_the_thread_finder_finds_threads(tmp_path):
    source = tmp_path / "threads.py"
    source.write_text(
        "import threading\nfrom concurrent.futures import ThreadPoolExecutor\n"
        "pool = ThreadPoolExecutor(2)\nworker = threading.Thread(target=print)\n"
    )
    assert threads_started(source) == [
        "threads.py:3 ThreadPoolExecutor", "threads.py:4 threading.Thread"
    ]  # fmt: skip


#: Most parameters a numba kernel takes: more travel as a few named structures (NamedTuples of
#: arrays, tuples of floats).
MAX_KERNEL_PARAMETERS = 8
#: Kernels over the limit: none is left (issue 32).
OVER_THE_LIMIT: set[str] = set()


def kernel_parameters(path: Path, module: str) -> dict[str, int]:
    """``{module.kernel: parameter count}`` of the numba-compiled functions of a source file."""
    counts = {}
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.FunctionDef) and any(
            "jit" in ast.unparse(decorator) for decorator in node.decorator_list
        ):
            arguments = node.args
            counts[f"{module}.{node.name}"] = len(arguments.posonlyargs + arguments.args) + len(
                arguments.kwonlyargs
            )
    return counts


def test_kernels_take_a_few_named_structures():
    counts = {
        name: count
        for module, path in MODULES.items()
        for name, count in kernel_parameters(path, module).items()
    }
    assert len(counts) > 50  # the finder finds the kernels
    over = {name for name, count in counts.items() if count > MAX_KERNEL_PARAMETERS}
    assert over == OVER_THE_LIMIT


def test_the_kernel_counter_counts_parameters(tmp_path):
    source = tmp_path / "k.py"
    source.write_text(
        "import numba\n@numba.njit(cache=True)\ndef f(a, b, *, c):\n    return a\n"
        "def g(a, b, c, d, e, f, g, h, i):\n    return a\n"
    )
    assert kernel_parameters(source, "m") == {"m.f": 3}


def test_every_kernel_family_names_an_existing_reference_test():
    # docs/architecture.md lists each numba kernel family with the test holding its naive
    # reference; the list must not name a test that was renamed or deleted.
    text = ARCHITECTURE.read_text()
    listed = text.split("Kernel families and their references", 1)[1].split("\n\n", 2)[1]
    named = re.findall(r"`(test_\w+\.py)::(test_\w+)`", listed)
    assert len(named) >= 20
    for file, test in named:
        source = (Path(__file__).parent / file).read_text()
        assert re.search(rf"^def {test}\(", source, re.MULTILINE), f"{file}::{test}"
