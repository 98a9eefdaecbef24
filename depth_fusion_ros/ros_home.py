"""``$ROS_HOME``: where a ROS node keeps what outlives a run (ROS 2's logs go there too).

ROS 2 resolves ``ROS_HOME`` to ``~/.ros`` when it is unset; a container or a robot with a
read-only home sets it to a writable disk. The map archive and the adapted single-view weights
follow it, so a node never writes to a home the user moved away from.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

#: ``$ROS_HOME`` or ``${ROS_HOME}`` at the start of a path parameter.
_ROS_HOME_PREFIX = re.compile(r'^\$(\{ROS_HOME\}|ROS_HOME)(?=/|$)')


def ros_home() -> Path:
    """``$ROS_HOME``, else ``~/.ros`` (rcl's rule)."""
    return Path(os.environ.get('ROS_HOME') or Path.home() / '.ros').expanduser()


def expand_ros_home(path: str) -> Path:
    """``path`` with a leading ``$ROS_HOME`` (or ``${ROS_HOME}``) and ``~`` expanded."""
    return Path(_ROS_HOME_PREFIX.sub(lambda _: str(ros_home()), path)).expanduser()
