"""One worker thread with a bounded queue: heavy work off the executor's callback path.

A subscription callback that runs a CNN or a plane sweep blocks the executor, so later
messages (poses, camera_info) queue up in DDS and are lost or delivered late. The nodes
therefore only decode and check a message in the callback and hand the heavy part to a
:class:`BoundedWorker`. The queue is bounded so memory stays flat whatever the input rate;
what happens when it is full is a policy:

* ``latest`` (default): the oldest waiting item is dropped and the new one queued, so the
  node always works on the freshest keyframe (what a live robot wants);
* ``drop_new``: the new item is dropped and the queue kept (first come, first served);
* ``block``: the caller waits for room (for offline replays where nothing may be lost and
  the producer can be slowed; the callback thread blocks, so use it with a multi-threaded
  executor or a producer that is not time critical).

Every drop goes through ``on_drop`` so the node counts and reports it.

``start`` runs once on the worker thread before its first item (items submitted meanwhile
wait): a warm-up belongs on the thread that does the work, because some state a first call
builds is the thread's own (on a GPU, the cuDNN and cuBLAS handles torch keeps per thread).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar('T')

POLICIES = ('latest', 'drop_new', 'block')

logger = logging.getLogger(__name__)


class BoundedWorker(Generic[T]):
    """Runs ``handle(item)`` for submitted items on its own thread, at most ``maxsize`` waiting."""

    def __init__(
        self,
        name: str,
        handle: Callable[[T], None],
        *,
        maxsize: int = 1,
        policy: str = 'latest',
        on_drop: Callable[[T, str], None] | None = None,
        on_error: Callable[[T, BaseException], None] | None = None,
        start: Callable[[], None] | None = None,
    ) -> None:
        if maxsize < 1:
            raise ValueError(f'worker {name}: queue size must be at least 1, got {maxsize}')
        if policy not in POLICIES:
            raise ValueError(f'worker {name}: unknown queue policy {policy!r}, expected one of {POLICIES}')
        self.name = name
        self.maxsize = maxsize
        self.policy = policy
        self._handle = handle
        self._on_drop = on_drop or (lambda item, reason: None)
        self._on_error = on_error or (lambda item, exc: logger.exception('worker %s failed', name))
        self._queue: deque[T] = deque()
        self._cond = threading.Condition()
        self._busy = False
        self._stopping = False
        self.handled = 0
        self.failed = 0
        self._start = start
        #: Set once ``start`` has run (at once without one).
        self.started = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f'{name}-worker', daemon=True)
        self._thread.start()

    def submit(self, item: T, timeout: float | None = None) -> bool:
        """Queue ``item``; returns ``False`` when it (not an older item) was dropped.

        With the ``block`` policy the call waits for room up to ``timeout`` seconds (forever
        when ``None``); an item that still finds no room, or arrives while stopping, is dropped.
        """
        dropped: list[tuple[T, str]] = []
        accepted = True
        with self._cond:
            if self._stopping:
                dropped.append((item, 'shutting_down'))
                accepted = False
            elif len(self._queue) < self.maxsize:
                self._queue.append(item)
            elif self.policy == 'latest':
                dropped.append((self._queue.popleft(), 'queue_full'))
                self._queue.append(item)
            elif self.policy == 'drop_new':
                dropped.append((item, 'queue_full'))
                accepted = False
            else:
                room = self._cond.wait_for(
                    lambda: self._stopping or len(self._queue) < self.maxsize, timeout=timeout
                )
                if room and not self._stopping:
                    self._queue.append(item)
                else:
                    dropped.append((item, 'shutting_down' if self._stopping else 'queue_full'))
                    accepted = False
            self._cond.notify_all()
        for old, reason in dropped:
            self._on_drop(old, reason)
        return accepted

    def _run(self) -> None:
        if self._start is not None:
            try:
                self._start()
            except Exception:  # a failed warm-up only costs the first item its speed
                logger.exception('worker %s: start-up failed', self.name)
        self.started.set()
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._stopping or bool(self._queue))
                if not self._queue:
                    return
                item = self._queue.popleft()
                self._busy = True
                self._cond.notify_all()
            try:
                self._handle(item)
                self.handled += 1
            except Exception as exc:  # a worker must survive any bad item
                self.failed += 1
                self._on_error(item, exc)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    @property
    def pending(self) -> int:
        """Items waiting (not counting the one being handled)."""
        with self._cond:
            return len(self._queue)

    def idle(self) -> bool:
        with self._cond:
            return not self._queue and not self._busy

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until the queue is empty and nothing is being handled (``False`` on timeout)."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._queue and not self._busy, timeout=timeout)

    def stop(self, timeout: float = 10.0, drain: bool = False) -> bool:
        """Stop the thread: finish the item in hand, drop (or with ``drain`` handle) the rest.

        Returns ``False`` if the thread did not end within ``timeout`` seconds (it is a daemon
        thread, so it cannot keep the process alive).
        """
        deadline = time.monotonic() + timeout
        if drain:
            self.wait_idle(timeout)
        with self._cond:
            self._stopping = True
            leftover = list(self._queue)
            self._queue.clear()
            self._cond.notify_all()
        for item in leftover:
            self._on_drop(item, 'shutting_down')
        if threading.current_thread() is not self._thread:
            self._thread.join(max(0.0, deadline - time.monotonic()))
        return not self._thread.is_alive()
