"""The numba kernel cache falls back to a writable directory (drcpo._numba_cache).

Each test imports a copy of the package in a fresh interpreter. Tests run as root, where file
modes do not stop writes, so unwritable locations are made by putting them under a regular
file (``__pycache__`` itself is a regular file; ``HOME`` is one): creating a directory there
fails for every user. Where the temporary directory has to be unusable too, the child sets
``tempfile.tempdir`` (the module's documented override) to such a path.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import drcpo

PACKAGE = Path(drcpo.__file__).resolve().parent
# Import the package, maybe run one small kernel, report where numba caches it.
CHILD = """
import json, os, warnings
warnings.simplefilter("always")
{prelude}
import numpy as np
import drcpo.{module}
from drcpo.geometry import _rotate_rows  # test seam: one small cached kernel

out = np.zeros((2, 2))
if {call}:
    _rotate_rows(np.ones((2, 3)), 0.0, 1.0, out)
print(json.dumps({{
    "package": drcpo.__file__,
    "cache_dir": os.environ.get("NUMBA_CACHE_DIR"),
    "result": out.tolist(),
    "cached": type(_rotate_rows._cache).__name__,
}}))
"""
KERNEL_RESULT = [[-1.0, 1.0], [-1.0, 1.0]]


def _run(
    tmp_path: Path,
    *,
    read_only=True,
    home_is_file=True,
    env=None,
    prelude="",
    module="geometry",
    call=True,
):
    package = tmp_path / "site" / "drcpo"
    if not package.exists():
        shutil.copytree(PACKAGE, package, ignore=shutil.ignore_patterns("__pycache__"))
        if read_only:
            for init in package.rglob("__init__.py"):
                (init.parent / "__pycache__").write_text("")  # mkdir here fails, even as root
    home = tmp_path / "home"
    if home_is_file:
        home.write_text("")
    else:
        home.mkdir(exist_ok=True)
    (tmp_path / "tmp").mkdir(exist_ok=True)
    child_env = {
        key: value
        for key, value in os.environ.items()
        if key not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME", "PYTHONPATH")
    }
    child_env.update(
        HOME=str(home),
        TMPDIR=str(tmp_path / "tmp"),
        PYTHONPATH=str(tmp_path / "site"),
        PYTHONDONTWRITEBYTECODE="1",
        **(env or {}),
    )
    code = CHILD.format(prelude=prelude, module=module, call=call)
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env=child_env,
        cwd=tmp_path,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["package"] == str(package / "__init__.py")  # the copy, not the checkout
    assert report["result"] == (KERNEL_RESULT if call else [[0.0, 0.0], [0.0, 0.0]])
    return report, done.stderr


def _cache_files(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.rglob("*.nbi")) if directory.is_dir() else []


def test_read_only_install_without_home_cache_imports_and_caches_in_tmp(tmp_path):
    # Before: RuntimeError: cannot cache function ...: no locator available, on import.
    report, stderr = _run(tmp_path, module="pipeline")
    private = tmp_path / "tmp" / f"drcpo-numba-{os.getuid()}"
    assert report["cache_dir"] == str(private) and report["cached"] == "FunctionCache"
    assert any(name.startswith("geometry._rotate_rows-") for name in _cache_files(private))
    assert private.stat().st_mode & 0o777 == 0o700
    assert "Warning" not in stderr


def test_numba_own_user_cache_is_left_to_numba(tmp_path):
    # A read-only install with a writable XDG cache: numba falls back on $XDG_CACHE_HOME/numba
    # itself, so drcpo leaves the process's NUMBA_CACHE_DIR alone.
    report, _ = _run(tmp_path, env={"XDG_CACHE_HOME": str(tmp_path / "xdg")})
    assert report["cache_dir"] is None and report["cached"] == "FunctionCache"
    assert _cache_files(tmp_path / "xdg" / "numba")


def test_home_cache_is_left_to_numba(tmp_path):
    report, _ = _run(tmp_path, home_is_file=False)
    assert report["cache_dir"] is None
    assert _cache_files(tmp_path / "home" / ".cache" / "numba")


def test_a_cache_dir_the_user_set_is_kept(tmp_path):
    report, _ = _run(tmp_path, env={"NUMBA_CACHE_DIR": str(tmp_path / "mine")})
    assert report["cache_dir"] == str(tmp_path / "mine") and _cache_files(tmp_path / "mine")


def test_writable_package_leaves_numba_to_cache_in_place(tmp_path):
    report, _ = _run(tmp_path, read_only=False)
    assert report["cache_dir"] is None
    assert _cache_files(tmp_path / "site" / "drcpo")


def test_numba_imported_before_drcpo_still_gets_the_fallback(tmp_path):
    report, _ = _run(tmp_path, prelude="import numba", call=False)
    assert report["cache_dir"] == str(tmp_path / "tmp" / f"drcpo-numba-{os.getuid()}")
    assert report["cached"] == "FunctionCache"


@pytest.mark.parametrize("why", ["no temporary directory", "someone else's directory"])
def test_nothing_writable_compiles_without_caching_and_warns_once(tmp_path, why):
    if why == "no temporary directory":
        (tmp_path / "blocked").write_text("")
        prelude = f"import tempfile; tempfile.tempdir = {str(tmp_path / 'blocked' / 'tmp')!r}"
    else:
        # A per-user directory anyone may write to could hold another user's pickles.
        shared = tmp_path / "tmp" / f"drcpo-numba-{os.getuid()}"
        shared.mkdir(parents=True)
        shared.chmod(0o777)
        prelude = ""
    report, stderr = _run(tmp_path, prelude=prelude)
    assert report["cache_dir"] is None and report["cached"] == "NullCache"
    assert stderr.count("RuntimeWarning") == 1 and "no writable directory" in stderr
    assert not list(tmp_path.rglob("*.nbi"))
