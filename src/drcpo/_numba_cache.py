"""Where numba keeps drcpo's compiled kernels; :func:`configure` runs first in ``drcpo/__init__``.

numba caches an ``@njit(cache=True)`` function in the ``__pycache__`` beside its source, else in
``~/.cache/numba``; with neither writable (a read-only install used by someone without a home
cache, e.g. in a container), decorating the function raises ``RuntimeError: cannot cache
function ...: no locator available`` and ``import drcpo.pipeline`` fails. So, before any kernel
module is imported: when ``NUMBA_CACHE_DIR`` is unset and a package ``__pycache__`` is not
writable and neither is numba's own user-wide cache (``$XDG_CACHE_HOME/numba``, else
``~/.cache/numba``), ``NUMBA_CACHE_DIR`` is pointed at a private per-user directory in the
temporary directory. When that is not usable either, drcpo's kernels are compiled in every
process instead of cached, with one warning.

``NUMBA_CACHE_DIR`` applies to every numba function of the process, not only drcpo's; it is only
set where numba's own choice would fail for drcpo.
"""

from __future__ import annotations

import os
import stat
import sys
import tempfile
import warnings
from pathlib import Path

ENV = "NUMBA_CACHE_DIR"
_PACKAGE = Path(__file__).resolve().parent


def configure() -> Path | None:
    """Make sure numba can cache (or at least compile) drcpo's kernels.

    Returns the directory ``NUMBA_CACHE_DIR`` names afterwards, or ``None`` when numba's own
    locations are used or caching is off.
    """
    if os.environ.get(ENV):
        return Path(os.environ[ENV])  # the user's choice
    if all(_writable(directory / "__pycache__") for directory in _package_dirs()):
        return None
    if _writable(_numba_user_cache()):
        return None  # numba's own fallback (its user-wide cache) works: leave it its choice
    tried = []
    for candidate, private in _candidates():
        tried.append(str(candidate))
        if _writable(candidate, private):
            _use(candidate)
            return candidate
    _disable_caching(tried)
    return None


def _package_dirs() -> list[Path]:
    """drcpo's package directories (numba caches each module's kernels in its own)."""
    return [_PACKAGE, *(p.parent for p in sorted(_PACKAGE.glob("*/__init__.py")))]


def _numba_user_cache() -> Path:
    """The user-wide directory numba itself falls back on (its appdirs' user cache on POSIX)."""
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    try:
        return (Path(xdg) if os.path.isabs(xdg) else Path.home() / ".cache") / "numba"
    except (RuntimeError, KeyError):  # no home directory known
        return Path(os.devnull) / "numba"  # never writable


def _candidates() -> list[tuple[Path, bool]]:
    """Cache directories to try, best first, each with whether it must be private to us."""
    try:
        return [(Path(tempfile.gettempdir()) / f"drcpo-numba-{_user()}", True)]
    except OSError:  # no usable temporary directory
        return []


def _user() -> str:
    if hasattr(os, "getuid"):
        return str(os.getuid())
    return "".join(c for c in os.environ.get("USERNAME", "user") if c.isalnum()) or "user"


def _writable(directory: Path, private: bool = False) -> bool:
    """Whether numba could cache in ``directory``: the test its locators make (create the
    directory, write a temporary file there). A ``private`` one, in a directory shared by all
    users, must also be ours and writable by no one else: numba loads its cache files with
    pickle, so another user's files there would run their code in our process."""
    try:
        directory.mkdir(mode=0o700 if private else 0o777, parents=True, exist_ok=True)
        if private and hasattr(os, "getuid"):
            info = directory.lstat()
            mine = stat.S_ISDIR(info.st_mode) and info.st_uid == os.getuid()
            if not mine or info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
                return False
        tempfile.TemporaryFile(dir=directory).close()
    except OSError:
        return False
    return True


def _use(directory: Path) -> None:
    os.environ[ENV] = str(directory)
    config = sys.modules.get("numba.core.config")
    if config is not None:  # numba imported before drcpo: it has read the environment already
        config.CACHE_DIR = str(directory)


def _disable_caching(tried: list[str]) -> None:
    """Compile drcpo's kernels without caching them (other numba functions are untouched)."""
    from numba.core.dispatcher import Dispatcher

    warnings.warn(
        "drcpo: no writable directory for numba's kernel cache (tried the package's "
        f"__pycache__, {', '.join(tried) or 'no other'}); kernels are compiled anew in each "
        f"process. Set {ENV} to a writable directory to cache them.",
        RuntimeWarning,
        stacklevel=3,
    )
    enable_caching = Dispatcher.enable_caching

    def enable_caching_outside_drcpo(self: Dispatcher) -> None:
        module = getattr(self.py_func, "__module__", "") or ""
        if module != "drcpo" and not module.startswith("drcpo."):
            enable_caching(self)

    Dispatcher.enable_caching = enable_caching_outside_drcpo
