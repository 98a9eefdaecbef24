"""Where a recording is written until it is complete, and what an earlier run left there.

``depth-fusion run --record OUT`` records into ``OUT.partial`` and renames the bag to ``OUT``
once it is complete. A run that fails leaves its unfinished recording in ``OUT.partial``. A
later run with the same ``OUT`` used to remove that folder with a warning; the recording is
the user's, so the later run now refuses to start instead (the CLI before any node starts,
the recorder node itself as the backstop). Free of ROS imports: the CLI checks it first.
"""

from __future__ import annotations

from pathlib import Path


def staging_folder(output: Path) -> Path:
    """``OUT.partial`` beside ``OUT``."""
    output = Path(output)
    return output.with_name(output.name + '.partial')


def check_no_unfinished_recording(output: Path) -> None:
    """``ValueError`` (one line) when an earlier run left its unfinished recording for ``output``."""
    staging = staging_folder(output)
    if staging.exists() or staging.is_symlink():
        raise ValueError(
            f'{staging} holds the unfinished recording of an earlier run: move it away or remove it, '
            'or choose another output'
        )
