"""Writing drcpo's outputs safely: directories (a database, an index, an augmented or synthetic
KITTI root) through :func:`write_directory` (resumably: :func:`drcpo.staging.write_staged`),
single files through :func:`atomic_write_bytes`.

Rules every output directory ``NAME`` follows:

* It is built in a hidden sibling ``.NAME.tmp-PID-XXXXXXXX`` and moved into place only once
  complete, so ``NAME`` never holds a half-written output.
* ``overwrite`` replaces only an output drcpo wrote: a directory holding the JSON marker of its
  :class:`OutputKind` (``manifest.json`` of a database or an index, ``synth.json``,
  ``augment.json``; written last) or an empty directory. ``NAME`` may never be or contain one
  of the command's inputs.
* One writer at a time: a run holds an ``flock`` on ``.NAME.lock`` while its temporary exists, so
  a second run fails at once. Without ``overwrite`` the final rename cannot replace a directory
  that appeared meanwhile (``renameat2(RENAME_NOREPLACE)``).
* A replace swaps the two directories in one step (``renameat2(RENAME_EXCHANGE)``), so ``NAME``
  holds the old or the new output at every instant. Where the system lacks ``renameat2`` (not
  Linux, or a file system refusing the flag) the old output is first renamed to
  ``.NAME.old-PID-XXXXXXXX``; a run killed between the two renames leaves ``NAME`` missing until
  the next write of ``NAME`` renames the old output back.
* The next run writing ``NAME`` removes the temporaries of runs that died (their PID names no
  live process). While a temporary exists SIGTERM unwinds like Ctrl-C, removing it; the caller
  gets :class:`Interrupted`.
* An ``OSError`` while writing (permission denied, disk full) becomes an
  :class:`~drcpo.errors.OutputError` naming the path and the system's reason.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import fnmatch
import json
import os
import re
import secrets
import shutil
import signal
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from drcpo.errors import OutputError, OutputExistsError

__all__ = [
    "Interrupted",
    "OutputKind",
    "atomic_write_bytes",
    "check_output",
    "write_directory",
]

_AT_FDCWD = -100  # <fcntl.h>: paths relative to the working directory
_RENAME_NOREPLACE = 1  # <linux/fs.h>
_RENAME_EXCHANGE = 2
_UNSUPPORTED = (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP)  # flag or call not available


@dataclass(frozen=True)
class OutputKind:
    """A kind of directory drcpo writes, recognised by a JSON marker file naming its format.

    Writers write the marker last, so a directory holding it is a complete output of the kind.
    ``entries``: what the kind writes at its top level (``fnmatch`` patterns; ``{key}`` takes
    the marker's value of ``key``): ``--overwrite`` refuses an output holding anything else (a
    user's file, another output nested in it), naming it, so that it removes only what drcpo
    wrote. ``None``: not checked.
    """

    description: str  # for messages, e.g. "drcpo database"
    marker: str  # file name inside the output, e.g. "manifest.json"
    format: str  # the marker's "format" value
    entries: tuple[str, ...] | None = None

    def owns(self, path: str | os.PathLike) -> bool:
        """Whether directory ``path`` holds this kind's marker."""
        return _not_owned(Path(path), self) is None


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived while an output was written; its temporary was removed.

    A :class:`KeyboardInterrupt`, so code that lets Ctrl-C through lets this through too.
    ``complete`` tells whether the output had already been moved into place.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        signum: int,
        complete: bool = False,
        staging: str | os.PathLike | None = None,
    ) -> None:
        self.path = Path(path)
        self.signum = int(signum)
        self.complete = complete
        name = signal.Signals(self.signum).name
        if complete:
            message = f"{path}: interrupted by {name} after the output was complete"
        else:
            message = f"{path}: interrupted by {name}; nothing was written there"
            if staging is not None:  # a resumable output (write_staged)
                message += f" (the work done is kept in {staging}: the same command resumes it)"
        super().__init__(message)

    @property
    def exit_status(self) -> int:
        """The shell's status for a process ended by the signal: 128 + its number."""
        return 128 + self.signum


class _Terminated(KeyboardInterrupt):
    """Raised by the SIGTERM handler installed while a temporary exists."""

    signum = signal.SIGTERM


# Checks ---------------------------------------------------------------------------------------
def check_output(
    path: str | os.PathLike,
    kind: OutputKind,
    overwrite: bool = False,
    inputs: Iterable[str | os.PathLike] = (),
) -> Path:
    """Raise :class:`OutputError` unless ``path`` may be written as a ``kind`` output.

    Refused: ``path`` is empty, a symbolic link, or is or contains the working directory;
    ``path`` is, contains or lies inside one of ``inputs`` (an output beside its inputs is fine:
    it never replaces them; inside one, a later ``--overwrite`` of that input would take it
    along); ``path`` exists and
    ``overwrite`` is false (:class:`OutputExistsError`); ``path`` exists and is neither an empty
    directory nor a ``kind`` output. Cheap, so commands call it before their work. Returns
    ``path`` resolved (symbolic links followed).
    """
    if not str(path):
        raise OutputError("the output path is empty; name a directory")
    target = Path(path).resolve()
    if Path.cwd().resolve().is_relative_to(target):  # '' and '.' come here too
        raise OutputError(
            f"{path}: the output is or contains the working directory; name a new directory"
        )
    for item in inputs:
        source = Path(item).resolve()
        if target == source:
            relation = "is"
        elif source.is_relative_to(target):
            relation = "contains"
        elif target.is_relative_to(source) and source.is_dir():
            relation = "lies inside"
        else:
            continue
        raise OutputError(
            f"{path}: the output {relation} the input {item}; write it somewhere else"
        )
    if os.path.islink(path):  # written through, the output would land wherever it points
        raise OutputError(
            f"{path} is a symbolic link (to {os.readlink(path)}); drcpo never writes through "
            "one: give the real path"
        )
    _check_replaceable(target, kind, overwrite, Path(path))
    return target


def _check_replaceable(target: Path, kind: OutputKind, overwrite: bool, shown: Path) -> None:
    if not os.path.lexists(target):
        return
    if not overwrite:
        raise OutputExistsError(f"{shown} already exists (pass --overwrite to replace it)")
    reason = "is not a directory" if not target.is_dir() else _not_owned(target, kind)
    if reason is not None:
        raise OutputError(
            f"{shown} {reason}; --overwrite only replaces a {kind.description} that drcpo "
            "wrote (or an empty directory): remove it yourself or choose another path"
        )


def _not_owned(path: Path, kind: OutputKind) -> str | None:
    """Why directory ``path`` is not an empty directory or a ``kind`` output, or ``None``."""
    marker = path / kind.marker
    try:
        if not any(path.iterdir()):
            return None
        found = json.loads(marker.read_text())
    except FileNotFoundError:
        return f"is not a {kind.description} (it has no {kind.marker})"
    except OSError as exc:
        return f"cannot be checked ({_describe(exc)})"
    except (ValueError, RecursionError):
        return f"is not a {kind.description} ({marker} is not drcpo's JSON)"
    if not isinstance(found, dict) or found.get("format") != kind.format:
        shown = found.get("format") if isinstance(found, dict) else found
        return f"is not a {kind.description} ({marker} has format {shown!r}, not {kind.format!r})"
    if kind.entries is not None:
        fields = {k: v for k, v in found.items() if isinstance(v, str)}
        patterns = [kind.marker, *(p.format_map(_Blank(fields)) for p in kind.entries)]
        for entry in sorted(os.listdir(path)):
            if not any(fnmatch.fnmatchcase(entry, p) for p in patterns if p):
                return (
                    f"holds {path / entry}, which drcpo did not write as part of a "
                    f"{kind.description}"
                )
    return None


class _Blank(dict):
    """Marker fields for ``str.format_map``; a missing one matches nothing."""

    def __missing__(self, key: str) -> str:
        return ""


# Writing a directory --------------------------------------------------------------------------
@contextmanager
def _claimed(
    shown: Path, kind: OutputKind, overwrite: bool, inputs: Iterable[str | os.PathLike]
) -> Iterator[Path]:
    """The checked target of output ``shown``, held under its lock (SIGTERM unwinding, system
    errors named) for the ``with`` block: what every writer of a directory output runs in."""
    inputs = list(inputs)
    with _os_errors(shown):
        target = check_output(shown, kind, overwrite, inputs)
        target.parent.mkdir(parents=True, exist_ok=True)
        with _locked(target, shown), _sigterm_unwinds():
            _remove_stale(target)
            check_output(shown, kind, overwrite, inputs)  # a run may have finished meanwhile
            yield target


def write_directory(
    path: str | os.PathLike,
    write: Callable[[Path], None],
    kind: OutputKind,
    overwrite: bool = False,
    inputs: Iterable[str | os.PathLike] = (),
) -> Path:
    """Create directory ``path`` as a ``kind`` output: ``write(tmp)`` fills an empty temporary
    directory (and must write ``kind.marker`` last), which then replaces ``path`` in one step.

    Returns ``Path(path)``. Raises :class:`OutputError` (or :class:`OutputExistsError`) as
    :func:`check_output` does, when another run is writing ``path``, or when the system refuses
    a write; :class:`Interrupted` on SIGINT / SIGTERM. In every case but a completed one the
    temporary is removed and ``path`` is as it was.
    """
    shown = Path(path)
    committed = [False]
    try:
        with _claimed(shown, kind, overwrite, inputs) as target:
            _write_and_commit(target, write, kind, overwrite, shown, committed)
    except KeyboardInterrupt as exc:
        raise Interrupted(shown, getattr(exc, "signum", signal.SIGINT), committed[0]) from exc
    return shown


def _write_and_commit(
    target: Path,
    write: Callable[[Path], None],
    kind: OutputKind,
    overwrite: bool,
    shown: Path,
    committed: list[bool],
) -> None:
    tmp = _make_temporary(target)
    try:
        write(tmp)
        if _not_owned(tmp, kind) is not None:
            raise RuntimeError(f"drcpo bug: a {kind.description} was written without its marker")
        with _signals_deferred():
            _check_replaceable(target, kind, overwrite, shown)
            _commit(tmp, target, kind, overwrite, shown)
            committed[0] = True
    finally:
        _remove(tmp)  # after a commit it holds the old output, or nothing at all


def _commit(tmp: Path, target: Path, kind: OutputKind, overwrite: bool, shown: Path) -> None:
    """Move ``tmp`` to ``target``; a replaced ``target`` ends up at ``tmp``'s name."""
    if not overwrite or not os.path.lexists(target):
        if _rename2(tmp, target, _RENAME_NOREPLACE):
            return
        if os.path.lexists(target):  # no renameat2: only our lock excludes other writers
            raise OutputExistsError(f"{shown} appeared while this run wrote it; it was left as is")
        os.rename(tmp, target)
        return
    if _rename2(tmp, target, _RENAME_EXCHANGE):
        if _not_owned(tmp, kind) is not None:  # another program put something else there
            _rename2(tmp, target, _RENAME_EXCHANGE)
            raise OutputError(f"{shown} changed while this run wrote it; it was left as is")
        return
    old = target.with_name(tmp.name.replace(".tmp-", ".old-", 1))
    os.rename(target, old)
    try:
        os.rename(tmp, target)
    except BaseException:
        os.rename(old, target)
        raise
    os.rename(old, tmp)  # the old output goes where the caller removes it


def _make_temporary(target: Path) -> Path:
    while True:
        tmp = target.with_name(f".{target.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}")
        try:
            tmp.mkdir(0o777)  # the umask applies, as for any new directory
            return tmp
        except FileExistsError:
            continue


def _remove(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)


# Stale temporaries ----------------------------------------------------------------------------
def _temporary_pattern(name: str) -> re.Pattern[str]:
    """Names of the temporaries (``tmp``) and moved-away old outputs (``old``) of ``name``."""
    return re.compile(rf"\.{re.escape(name)}\.(tmp|old)-(\d+)-[0-9a-f]{{8}}")


def _remove_stale(target: Path) -> None:
    """Remove the temporaries of dead runs next to ``target`` (called holding its lock).

    Every run holds the lock for as long as its temporaries exist, so whatever matches while we
    hold it was left by a run that died (whatever its PID is now: PIDs are reused). An old
    output whose run died between its two renames goes back to ``target`` when ``target`` is
    missing.
    """
    pattern = _temporary_pattern(target.name)
    found = [(pattern.fullmatch(entry.name), entry) for entry in target.parent.iterdir()]
    ours = [(match, entry) for match, entry in found if match is not None]
    for match, entry in sorted(ours, key=lambda item: item[0][1] != "old"):
        if match[1] == "old" and not os.path.lexists(target):
            os.rename(entry, target)
        else:
            _remove(entry)


# Locking, signals, errors ---------------------------------------------------------------------
@contextmanager
def _locked(target: Path, shown: Path) -> Iterator[None]:
    """Hold an exclusive ``flock`` on ``.NAME.lock`` beside ``target``; fail if another has it.

    The kernel drops the lock when its holder dies, so a killed run never blocks the next one.
    The lock is never opened through a symbolic link: a link of that name (planted, or left
    by anything) would have us write our pid over whatever it points at.
    """
    lock = target.with_name(f".{target.name}.lock")
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW, 0o666)
        except OSError as exc:
            if exc.errno != errno.ELOOP:
                raise
            raise OutputError(
                f"{shown}: its lock {lock} is a symbolic link; drcpo never writes through one "
                "(remove it if no drcpo run is using this output)"
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise OutputError(
                f"{shown}: another drcpo run is writing it (it holds {lock}); "
                "wait for it to finish or choose another path"
            ) from None
        except BaseException:
            os.close(fd)
            raise
        if _same_file(fd, lock):
            break
        os.close(fd)  # its holder removed that file after we opened it; lock the new one
    try:
        os.write(fd, f"{os.getpid()}\n".encode())
        yield
    finally:
        lock.unlink(missing_ok=True)  # still holding it, so no one else holds the removed file
        os.close(fd)


def _same_file(fd: int, path: Path) -> bool:
    try:
        on_disk = os.lstat(path)
    except FileNotFoundError:
        return False
    held = os.fstat(fd)
    return (held.st_dev, held.st_ino) == (on_disk.st_dev, on_disk.st_ino)


@contextmanager
def _sigterm_unwinds() -> Iterator[None]:
    """SIGTERM raises like Ctrl-C while a temporary exists, so it is removed.

    Only in the main thread, and only where SIGTERM has its default action (a program with its
    own handler keeps it).
    """
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL
    ):
        yield
        return

    def handler(signum: int, frame: object) -> None:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second one must not stop the clean-up
        _TERMINATED.set()
        raise _Terminated

    previous_hook = sys.unraisablehook

    def unraisable(info: Any) -> None:
        # a _Terminated a C callback could not raise is handled through _TERMINATED: printing
        # it would put a traceback before the one-line report
        if not isinstance(info.exc_value, _Terminated):
            previous_hook(info)

    _TERMINATED.clear()
    signal.signal(signal.SIGTERM, handler)
    sys.unraisablehook = unraisable
    try:
        yield
        _raise_if_terminated()
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        sys.unraisablehook = previous_hook
        _TERMINATED.clear()


# Set by _sigterm_unwinds' handler: its exception is lost when the signal lands in a ctypes
# callback (numba compiling), so the write checks it again before anything is moved into place.
_TERMINATED = threading.Event()


def _raise_if_terminated() -> None:
    if _TERMINATED.is_set():
        raise _Terminated


@contextmanager
def _signals_deferred() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back while the output is moved into place, then deliver them.

    Done with Python handlers rather than a signal mask: the kernel may hand a signal to any
    thread (a progress bar's, numba's), but Python runs handlers in the main thread only.
    """
    _raise_if_terminated()
    if threading.current_thread() is not threading.main_thread():
        yield  # signals interrupt only the main thread, never this one
        return
    pending: list[int] = []
    # A handler installed from C reads back as None and could not be restored: leave it be.
    numbers = [n for n in (signal.SIGINT, signal.SIGTERM) if signal.getsignal(n) is not None]
    previous = {n: signal.signal(n, lambda signum, frame: pending.append(signum)) for n in numbers}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
        for number in pending:  # also when the move failed: a Ctrl-C is never lost
            signal.raise_signal(number)  # now handled as it would have been


@contextmanager
def _os_errors(shown: Path) -> Iterator[None]:
    try:
        yield
    except OutputError:
        raise
    except OSError as exc:
        raise OutputError(f"cannot write {shown}: {_describe(exc)}") from exc


def save_array(path: Path, array: np.ndarray) -> None:
    """``np.save`` (no pickles) naming ``path`` in any error: numpy's short write under a
    file-size limit or a full disk says neither which file nor why."""
    try:
        np.save(path, np.ascontiguousarray(array), allow_pickle=False)
    except OSError as exc:
        reason = exc.strerror or str(exc)
        if exc.errno is None and "requested and" in reason:
            reason = f"short write ({reason}): the disk is full or a file-size limit was reached"
        raise OSError(exc.errno or errno.EIO, reason, os.fspath(path)) from None


def _describe(exc: OSError) -> str:
    """``file: reason`` of an ``OSError``, a temporary's name replaced by its output's."""
    reason = exc.strerror or str(exc)
    if exc.filename is None:
        return reason
    name = re.sub(r"\.([^/]+)\.(?:tmp|old)-\d+-[0-9a-f]{8}", r"\1", os.fsdecode(exc.filename))
    return f"{name}: {reason}"


@cache
def _renameat2() -> Callable[..., int] | None:
    if not sys.platform.startswith("linux"):
        return None
    function = getattr(ctypes.CDLL(None, use_errno=True), "renameat2", None)  # glibc >= 2.28
    if function is not None:
        function.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p]
        function.argtypes += [ctypes.c_uint]
        function.restype = ctypes.c_int
    return function


def _rename2(source: Path, target: Path, flags: int) -> bool:
    """``renameat2(source, target, flags)``; ``False`` where the system does not offer it."""
    function = _renameat2()
    if function is None:
        return False
    if function(_AT_FDCWD, os.fsencode(source), _AT_FDCWD, os.fsencode(target), flags) == 0:
        return True
    code = ctypes.get_errno()
    if code in _UNSUPPORTED:
        return False
    if code == errno.EEXIST:
        raise OutputExistsError(f"{target} appeared while this run wrote it; it was left as is")
    raise OSError(code, os.strerror(code), os.fspath(source), None, os.fspath(target))


# Single files ---------------------------------------------------------------------------------
def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same directory, then rename.

    Raises :class:`OutputError` naming the file when the system refuses the write.
    """
    path = Path(path)
    with _os_errors(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}")
        # O_EXCL: never write through a file or link someone else put there; 0o666: umask applies.
        handle = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666)
        try:
            with os.fdopen(handle, "wb") as file:
                file.write(data)
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
    return path
