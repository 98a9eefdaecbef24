"""What the package's helper processes share: their environment and their messages.

Two nodes start a helper process of their own with ``python -m MODULE FD ...`` and talk to it
over a socket pair (``multiprocessing.connection``): ``single_view_node``'s adaptation
(``adaptation/trainer_process.py``) and ``multi_view_node``'s calibration checks
(``nodes/check_process_main.py``). Standard library only: a child imports this before it
lowers its priority.
"""

from __future__ import annotations

import os
import pickle
from multiprocessing.connection import Connection
from pathlib import Path


def child_environment() -> dict[str, str]:
    """This environment, with the directory this package was imported from first on the
    child's ``PYTHONPATH``: the child runs the same code as the node (a source tree, a
    worktree, a colcon install), whatever the child's own default path would find."""
    root = str(Path(__file__).resolve().parents[1])
    path = os.environ.get('PYTHONPATH', '')
    return {**os.environ, 'PYTHONPATH': os.pathsep.join(p for p in (root, path) if p)}


def send(conn: Connection, message: tuple) -> None:
    """``conn.send`` with the standard pickler: ``Connection.send`` uses multiprocessing's,
    for which torch registers tensor reducers that share memory through multiprocessing's
    resource sharer, and that needs a ``multiprocessing`` child (its authentication key):
    these children are not. Pickled plainly a tensor travels by value (2 MB a set of weights)."""
    conn.send_bytes(pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL))


def receive(conn: Connection) -> tuple:
    return pickle.loads(conn.recv_bytes())
