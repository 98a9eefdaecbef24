"""What the fork server of ``depth-fusion run --processes`` does once its imports are done
(``graph/forked.py`` preloads this module last; nothing else imports it).

* **It ignores SIGTERM and SIGHUP.** The launcher learns each forked node's exit code from
  the server. A stop signal sent to the whole process group (``timeout``, a systemd unit's
  stop, a closed terminal) reaches the server too, and a server that died first would report
  every node still stopping as exit 255. Ignoring them costs nothing: the server ends by
  itself when the launcher does (its ``alive`` pipe closes, even on SIGKILL). It already
  ignores SIGINT (``multiprocessing``). Each forked child takes the default handlers back
  before it runs its node (``forked._run_node``).
* **It moves what it imported out of the garbage collector's reach** (``gc.freeze``, as the
  ``gc`` documentation advises before a fork). A node's full collections then skip torch's
  and numpy's module objects, and they do not write to those objects' pages, which the
  children share with the server copy-on-write.

Not under ``nodes/graph/``: importing that package imports rclpy, whose extension starts native
threads, which a fork would lose.
"""

from __future__ import annotations

import gc
import signal

#: The signals the server ignores and each child takes back.
IGNORED = (signal.SIGTERM, signal.SIGHUP)

for _signum in IGNORED:
    signal.signal(_signum, signal.SIG_IGN)
gc.freeze()
