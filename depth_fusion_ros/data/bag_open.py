"""Opening a rosbag2 to play: the bag folder or one storage file, every failure said plainly.

Why: ``bag_replayer`` (and the launcher and the benchmark, which read a bag's topics before
starting it) take a user's path that may be the bag folder, a ``.mcap`` / ``.db3`` inside it,
a loose storage file or a crashed recording without ``metadata.yaml``; each wrong path gets one
error naming it instead of a rosbags traceback. The messages are prefixed with the replayer's
node name, as they are the replayer's parameter errors. No ROS import.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .bag_recovery import open_rosbag2, readable_rosbag2

#: The prefix of every error: the node that plays the bag (``nodes.bag_replayer.NODE_NAME``).
NODE_NAME = 'bag_replayer'


class BagError(ValueError):
    """A bag that cannot be played (missing, unknown storage, no playable topic)."""


def resolve_bag_path(path: str | Path) -> Path:
    """The path rosbags opens, or ``FileNotFoundError``/``BagError`` saying what is wrong.

    Accepts the bag folder or one storage file (``.mcap``, ``.db3``); a storage file inside a
    bag folder is opened through its folder so the metadata (QoS, counts) is used.
    """
    if not str(path):
        raise BagError(f'{NODE_NAME}: parameter "bag" is empty: give the rosbag2 folder to play')
    p = Path(path).expanduser()
    if not p.exists():
        raise FileNotFoundError(f'{NODE_NAME}: bag {p} does not exist')
    if p.is_dir():
        if not readable_rosbag2(p):
            raise BagError(f'{NODE_NAME}: {p} is a folder without metadata.yaml, not a rosbag2')
        return p  # without metadata.yaml: a crashed recording, see data.bag_recovery
    if p.suffix not in ('.mcap', '.db3'):
        raise BagError(
            f'{NODE_NAME}: {p}: unknown storage {p.suffix or "(no suffix)"!r}; '
            'expected a rosbag2 folder, a .mcap or a .db3 file'
        )
    if (p.parent / 'metadata.yaml').is_file():
        return p.parent
    return p


def open_bag(path: str | Path) -> Any:
    """An open ``rosbags.rosbag2.Reader``; every failure is a ``BagError`` naming the bag."""
    from rosbags.rosbag2 import ReaderError

    p = resolve_bag_path(path)
    try:
        reader = open_rosbag2(p)  # a truncated bag plays up to its last readable message
    except (ReaderError, KeyError, OSError) as exc:
        raise BagError(f'{NODE_NAME}: cannot read bag {p}: {exc}') from None
    return reader
