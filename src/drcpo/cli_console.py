"""What the command line tells its user on stderr: errors and progress.

On bad input a command prints one line naming the culprit and exits with status 1: any
:class:`drcpo.errors.DrcpoError`, out of memory, or an operating system error (the path and the
reason: permission denied, disk full, ...); Ctrl-C prints "interrupted" and exits with 130
(SIGINT or SIGTERM while an output is written: 128 + the signal number, after removing the
unfinished output). :func:`safety_net` does this around every command of :mod:`drcpo.cli`. Set
``DRCPO_DEBUG=1`` to get the traceback instead.

Long work shows a rich progress bar (:func:`progress_bar`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import NoReturn

import typer
from rich.console import Console
from rich.text import Text

from drcpo.errors import DrcpoError
from drcpo.outputs import Interrupted

__all__ = ["console", "fail", "os_error_message", "progress_bar", "safety_net", "say_error"]

#: The commands' stderr: errors, progress bars (their results go to stdout).
console = Console(stderr=True)


def say_error(message: str) -> None:
    """Print ``error: message`` on stderr as one line."""
    # Not wrapped (paths stay whole for copying) and not read as markup (paths may hold "[").
    console.print(Text.assemble(("error:", "bold red"), " ", message), soft_wrap=True)


def fail(message: str) -> None:
    """Print an error message and exit with status 1."""
    say_error(message)
    raise typer.Exit(1)


@contextmanager
def safety_net() -> Iterator[None]:
    """Turn the errors a user can meet into one line on stderr and an exit status (no traceback).

    :class:`DrcpoError`, :class:`MemoryError` and :class:`OSError` exit with 1,
    :class:`KeyboardInterrupt` with 130. Anything else is a bug in drcpo and keeps its traceback;
    with ``DRCPO_DEBUG=1`` every exception does.
    """
    if os.environ.get("DRCPO_DEBUG") == "1":
        yield
        return
    try:
        yield
    except DrcpoError as exc:
        _exit(str(exc))
    except Interrupted as exc:  # SIGINT/SIGTERM while an output was being written
        console.print(Text.assemble(("interrupted:", "bold red"), " ", str(exc)), soft_wrap=True)
        raise SystemExit(exc.exit_status) from None
    except KeyboardInterrupt:
        console.print("interrupted", soft_wrap=True, markup=False)
        raise SystemExit(130) from None
    except MemoryError as exc:
        _exit(f"out of memory ({exc})" if str(exc) else "out of memory")
    except BrokenPipeError:
        raise  # stdout closed early (`drcpo info --json | head`): typer exits quietly
    except OSError as exc:
        _exit(os_error_message(exc))


def _exit(message: str) -> NoReturn:
    say_error(message)
    raise SystemExit(1) from None


def os_error_message(exc: OSError) -> str:
    """``path: reason`` (``source -> target: reason`` for a rename or link) of an OS error."""
    reason = exc.strerror or str(exc) or type(exc).__name__
    paths = [str(path) for path in (exc.filename, exc.filename2) if path is not None]
    return f"{' -> '.join(paths)}: {reason}" if paths else reason


@contextmanager
def progress_bar(description: str) -> Iterator[Callable[[int, int], None]]:
    """A rich progress bar on stderr; yields a ``progress(done, total)`` callback."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    columns = (*Progress.get_default_columns()[:1], BarColumn(), MofNCompleteColumn())
    with Progress(*columns, TimeElapsedColumn(), console=console) as bar:
        task = bar.add_task(description, total=None)
        yield lambda done, total: bar.update(task, completed=done, total=total)
