"""Lower the scheduling priority of the calling thread (Linux keeps a niceness per thread).

Why: on a small CPU the graph's real-time path (posing, the filter, inference, fusion) must
not wait for work that can come later: the online adaptation's training, the calibration
checks' feature matching. A niceness of 10 gives such a thread about a tenth of a contended
core and all of an idle one. Threads created afterwards by this one (an OpenMP team) inherit
it. Where the platform has no per-thread priority, nothing changes and the caller says so.
"""

from __future__ import annotations

import os
import threading


def lower_this_thread(nice: int) -> int | None:
    """Add ``nice`` (capped at 19) to the calling thread's niceness; the niceness it then runs
    at, or ``None`` where that cannot be done (not Linux, not permitted). 0 changes nothing."""
    try:
        tid = threading.get_native_id()
        if nice > 0:
            os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + nice))
        return os.getpriority(os.PRIO_PROCESS, tid)
    except (AttributeError, OSError):
        return None
