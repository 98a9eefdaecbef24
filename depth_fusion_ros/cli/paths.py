"""Output paths checked before any work: one shared helper for every subcommand.

Why: an unwritable output (a read-only file system, a path under a file, an existing bag)
used to surface as a Python traceback at the very end, after ``evaluate`` had computed for
minutes. :func:`check_output` runs first and raises :class:`OutputPathError` (a
``ValueError``, which ``depth-fusion`` prints as one line) saying what is wrong and what to do.

Writability is probed, not guessed from permission bits: a temporary file is created and
removed in the folder that would receive the output (or its nearest existing ancestor), which
catches read-only mounts, permissions, ACLs and full quota alike.

Bag outputs must not end in ``.bag``: rosbags' ``AnyReader`` (and most tools) take ``*.bag``
for a ROS 1 bag and then fail on the rosbag2 folder ("Is a directory"). We refuse such a name
with the name to use instead, rather than silently writing somewhere else.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


class OutputPathError(ValueError):
    """An output path that cannot be written; the message is one line for the user."""


def _nearest_existing(path: Path) -> Path:
    for candidate in (path, *path.parents):
        if candidate.exists() or candidate.is_symlink():
            return candidate
    return Path('/')


def _probe_writable(folder: Path, what: str, path: Path) -> None:
    try:
        fd, probe = tempfile.mkstemp(prefix='.depth_fusion_write_probe_', dir=folder)
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise OutputPathError(f'{what} {path}: cannot write in {folder}: {reason}') from None
    os.close(fd)
    os.unlink(probe)


def check_output(
    path: str | Path,
    what: str = 'output',
    *,
    folder: bool = True,
    exists_ok: bool = True,
    overwrite_flag: str | None = None,
    bag: bool = False,
) -> Path:
    """Check that ``path`` can be created (or replaced) before any work; returns it as a Path.

    ``what`` names the option in messages (``'--record'``, ``'OUT_BAG'``). ``folder``: the
    output is a folder (else a file). ``exists_ok=False``: an existing ``path`` is an error,
    naming ``overwrite_flag`` when there is one. ``bag``: a rosbag2 folder (no ``.bag`` suffix).
    """
    path = Path(path).expanduser()
    if not str(path) or str(path) == '.':
        raise OutputPathError(f'{what}: give a path')
    if bag and path.suffix.lower() == '.bag':
        raise OutputPathError(
            f'{what} {path}: a rosbag2 output must not end in .bag (tools take *.bag for a ROS 1 bag '
            f'and fail on the folder); use {path.with_suffix("")}'
        )
    if path.exists():
        if folder and not path.is_dir():
            raise OutputPathError(f'{what} {path} is a file, expected a folder')
        if not folder and path.is_dir():
            raise OutputPathError(f'{what} {path} is a folder, expected a file')
        if not exists_ok:
            hint = f' (pass {overwrite_flag} to replace it)' if overwrite_flag else '; choose a new name'
            raise OutputPathError(f'{what} {path} already exists{hint}')
        _probe_writable(path if path.is_dir() else path.parent, what, path)
        return path
    ancestor = _nearest_existing(path.parent)
    if not ancestor.is_dir():
        raise OutputPathError(f'{what} {path}: {ancestor} is a file, not a folder')
    _probe_writable(ancestor, what, path)
    return path


def check_new_file(path: str | Path, what: str, overwrite: bool) -> Path:
    """A file output that an existing file blocks unless ``--overwrite`` is given (a checkpoint,
    a model, a mesh: someone's result, kept by default)."""
    return check_output(path, what, folder=False, exists_ok=overwrite, overwrite_flag='--overwrite')


def check_new_model(path: str | Path, what: str, overwrite: bool) -> Path:
    """A model file and the YAML written beside it (``train --ship``), both checked. (``export``
    checks its YAML itself: the formats of one stem share it, see ``singleview/export.py``.)

    Why both: the YAML is half of the model (its input size and output kind); replacing one
    and not the other would leave a pair that loads and predicts wrongly.
    """
    path = Path(path).expanduser()
    for target in (path, path.with_suffix('.yaml')):
        check_new_file(target, what, overwrite)
    return path
