"""Imported by the fork server of ``depth-fusion run --processes`` only (``graph/forked.py``
preloads it): the server ignores SIGTERM and SIGHUP.

Why: the launcher learns each forked node's exit code from the server. A stop signal sent to
the whole process group (``timeout``, a systemd unit's stop, a closed terminal) reaches the
server too, and a server that died first would report every node still stopping as exit
255. Ignoring them costs nothing: the server ends by itself when the launcher does (its
``alive`` pipe closes, even on SIGKILL). It already ignores SIGINT (``multiprocessing``).
Each forked child takes the default handlers back before it runs its node
(``forked._run_node``).

Not under ``nodes/graph/``: importing that package imports rclpy, whose extension starts native
threads, which a fork would lose.
"""

from __future__ import annotations

import signal

#: The signals the server ignores and each child takes back.
IGNORED = (signal.SIGTERM, signal.SIGHUP)

for _signum in IGNORED:
    signal.signal(_signum, signal.SIG_IGN)
