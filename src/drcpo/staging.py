"""Resumable outputs: an output directory built in a staging directory that a failed or killed
run leaves behind, so that the next run of the same parameters continues its work
(:func:`write_staged`; the augmented KITTI root of ``drcpo augment``).

The staging directory of output ``NAME`` is ``.NAME.staging`` beside it (:func:`staging_path`),
marked by its ``staging.json`` (format :data:`STAGING_FORMAT`, the run's parameters). The output
is claimed, locked and moved into place as :mod:`drcpo.outputs` does for every output directory.
"""

from __future__ import annotations

import json
import os
import re
import signal
from collections.abc import Callable, Iterable
from pathlib import Path

from drcpo.errors import OutputError
from drcpo.outputs import (
    Interrupted,
    OutputKind,
    _check_replaceable,
    _claimed,
    _commit,
    _make_temporary,
    _not_owned,
    _remove,
    _signals_deferred,
)

__all__ = ["STAGING_FORMAT", "staging_path", "write_staged"]

#: The ``format`` of ``staging.json``, the marker of a staging directory (:func:`write_staged`).
STAGING_FORMAT = "drcpo-staging"
_STAGING_MARKER = "staging.json"
_STAGED_OUTPUT = "output"  # the staging directory's subdirectory that becomes the output
_TEMPORARY_FILE = re.compile(r"\..+\.tmp-\d+-[0-9a-f]{8}")  # atomic_write_bytes' temporaries


def staging_path(path: str | os.PathLike) -> Path:
    """The staging directory of output ``path``: ``.NAME.staging`` beside it."""
    path = Path(path)
    return path.with_name(f".{path.name}.staging")


def write_staged(
    path: str | os.PathLike,
    write: Callable[[Path], None],
    kind: OutputKind,
    run: dict,
    overwrite: bool = False,
    inputs: Iterable[str | os.PathLike] = (),
) -> Path:
    """Create directory ``path`` as a ``kind`` output, resumably: like :func:`write_directory`,
    but built in a staging directory (:func:`staging_path`) that a failed or killed run leaves
    behind, so that the next run with the same ``run`` parameters continues its work.

    ``write(staging)`` gets the staging directory, possibly holding what an earlier run of the
    same parameters wrote (files it wrote there through :func:`atomic_write_bytes` are whole;
    the temporaries of killed writers are removed before and after ``write``); it must leave
    the complete output, ``kind.marker`` written last, in ``staging / "output"``, which then
    replaces ``path`` in one step (as :func:`write_directory` does) and the staging directory
    goes. ``write`` may keep its own resume state elsewhere in ``staging``.

    ``staging.json`` inside the staging directory records ``run`` (JSON values). A staging
    directory of other parameters is refused, or with ``overwrite`` discarded and started
    anew; one without drcpo's ``staging.json`` is never touched. The lock of ``path`` is held
    throughout, so processes ``write`` starts may write into the staging directory meanwhile.
    Raises as :func:`write_directory` does.
    """
    shown = Path(path)
    run = json.loads(json.dumps(run))  # as read back from staging.json
    committed = [False]
    try:
        with _claimed(shown, kind, overwrite, inputs) as target:
            staging = _open_staging(target, run, overwrite, shown)
            _remove_temporary_files(staging)
            write(staging)
            _remove_temporary_files(staging)
            output = staging / _STAGED_OUTPUT
            if _not_owned(output, kind) is not None:
                raise RuntimeError(f"drcpo bug: a {kind.description} was staged unfinished")
            with _signals_deferred():
                _check_replaceable(target, kind, overwrite, shown)
                # Under a temporary's name: a replaced output lands there, or beside it.
                tmp = _make_temporary(target)
                os.replace(output, tmp)
                try:
                    _commit(tmp, target, kind, overwrite, shown)
                except BaseException:
                    os.replace(tmp, output)  # kept for the next run
                    raise
                committed[0] = True
            _remove(tmp)
            _remove(staging)
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", signal.SIGINT)
        kept = staging_path(shown) if os.path.lexists(staging_path(shown)) else None
        raise Interrupted(shown, signum, committed[0], kept) from exc
    return shown


def _open_staging(target: Path, run: dict, overwrite: bool, shown: Path) -> Path:
    """The staging directory of ``target`` for ``run``: the existing one when it was made for
    the same parameters, else a new one (holding only ``staging.json``)."""
    staging = staging_path(target)
    if os.path.lexists(staging):
        found = _staging_run(staging)
        if found is None:
            raise OutputError(
                f"{staging_path(shown)} is in the way of the staging directory of {shown} and is "
                f"not drcpo's (no {_STAGING_MARKER} of format {STAGING_FORMAT!r}): remove it "
                "yourself or choose another output path"
            )
        if found == run:
            return staging
        if not overwrite:
            keys = sorted(k for k in {*found, *run} if found.get(k) != run.get(k))
            raise OutputError(
                f"{staging_path(shown)} holds an unfinished run with other parameters (differing "
                f"in: {', '.join(keys)}): rerun that command to finish it, or pass --overwrite "
                "to discard it"
            )
        _remove(staging)
    tmp = _make_temporary(target)  # a stale temporary if we die before the rename
    marker = {"format": STAGING_FORMAT, "run": run}
    (tmp / _STAGING_MARKER).write_text(json.dumps(marker, indent=2, sort_keys=True) + "\n")
    os.rename(tmp, staging)
    return staging


def _staging_run(staging: Path) -> dict | None:
    """The ``run`` parameters in a staging directory's marker; ``None`` if it is not drcpo's."""
    try:
        found = json.loads((staging / _STAGING_MARKER).read_text())
    except (OSError, ValueError, RecursionError):
        return None
    if not isinstance(found, dict) or found.get("format") != STAGING_FORMAT:
        return None
    return found.get("run")


def _remove_temporary_files(directory: Path) -> None:
    """Remove what writers killed inside :func:`atomic_write_bytes` left under ``directory``."""
    for parent, _, files in os.walk(directory):
        for name in files:
            if _TEMPORARY_FILE.fullmatch(name):
                os.unlink(os.path.join(parent, name))
