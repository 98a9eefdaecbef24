"""rcl's error text as one line a user can read.

rcl's messages end with where in its C sources they were raised (``..., at
/project/src/rcl/arguments.c:380``), a remap it cannot parse with an empty ``Error: error not
set``, and rclpy's name checks add a caret drawing on further lines. The console nodes
(``console.py``) and the CLI's topic checks (``cli/topic_names.py``) both show such errors.
"""

from __future__ import annotations


def rcl_message(exc: BaseException) -> str:
    """The first line of ``exc``'s text without rcl's source location and empty detail."""
    return str(exc).splitlines()[0].split(', at /')[0].removesuffix('. Error: error not set')
