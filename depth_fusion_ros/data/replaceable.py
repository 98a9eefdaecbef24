"""Which existing output ``overwrite`` (``--overwrite``) may replace: only what this package
wrote, or an empty folder.

Why: ``synth OUT --overwrite`` replaced whatever folder OUT named (a mistyped name deleted the
user's files, a downloaded dataset included), and ``convert SRC OUT --overwrite`` any rosbag2,
a robot's recording included, which nothing can bring back. Each writer marks what it writes
(``tum_writer``: a file in the folder; ``bag_writer``: the bag's ``custom_data``) and says, for
an existing path, why it is not one of its own.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path


def check_replaceable(path: Path, overwrite: bool, not_ours: Callable[[Path], str | None]) -> None:
    """``ValueError`` unless ``path`` is new, or ``overwrite`` and it is an empty folder or one
    for which ``not_ours`` (the writer's test) gives no reason to keep it."""
    if not (path.exists() or path.is_symlink()):
        return
    if not overwrite:
        raise ValueError(f'{path} already exists (pass --overwrite to replace it)')
    if path.is_symlink() or not path.is_dir():
        raise ValueError(f'{path} exists and is not a folder: refusing to overwrite it')
    if not any(path.iterdir()):
        return  # nothing in it to lose
    reason = not_ours(path)
    if reason:
        raise ValueError(f'{path} {reason}: refusing to overwrite it')
