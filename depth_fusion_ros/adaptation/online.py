"""The Adapter on its own thread, off the inference path; accepted weights swapped atomically.

Inference must never wait for training. So training happens on a thread that owns the
:class:`~.adapter.Adapter` (torch releases the GIL inside its operators, so both threads
compute at once), samples reach it through a small bounded queue (``submit`` never blocks;
when training falls behind the oldest waiting keyframe is dropped and counted, and the
updates made meanwhile are the adapter's shorter ``behind`` ones: :func:`is_behind`), and each
accepted update produces a *new* predictor around a copy of the weights, published through a
:class:`WeightSlot`. Inference takes the slot's current predictor with one locked read and
runs it; training never touches a module that is predicting, and a swap never waits for a
prediction in flight. ``restart`` starts the training over from the loaded weights, on this
thread before the next keyframe, and lets go of the keyframes from before the poses changed.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..singleview.predictor import DepthPredictor
from .adapter import Adapter, UpdateReport
from .sample import AdaptSample

log = logging.getLogger(__name__)


def is_behind(waiting: bool, dropped_since: bool, last_update: float | None, interval: float | None) -> bool:
    """Whether the training thread's next update is a short one (the adapter's ``behind``).

    Behind: another keyframe ``waiting``, or keyframes dropped since the last one taken; or,
    before the queue shows it, the last update that trained took longer (``last_update``, s)
    than keyframes come (``interval``, s): keyframes that are not trained on (too few
    multi-view points) empty the queue without the thread keeping up; and the first update,
    before either is known: on a starved CPU a full first update lasts seconds and every
    keyframe meanwhile is predicted by the network as loaded (docs/adaptation.md, "On a CPU
    budget"). One rule for the node's thread and ``scripts/diag/adapt_budget.py``.
    """
    if waiting or dropped_since or last_update is None or interval is None:
        return True
    return last_update > interval


class WeightSlot:
    """The predictor inference uses now, and its version; ``swap`` replaces both at once."""

    def __init__(self, predictor: DepthPredictor, version: int = 0):
        self._lock = threading.Lock()
        self._predictor = predictor
        self._version = version

    def get(self) -> tuple[DepthPredictor, int]:
        with self._lock:
            return self._predictor, self._version

    def swap(self, predictor: DepthPredictor, version: int) -> None:
        with self._lock:
            self._predictor, self._version = predictor, version

    @property
    def version(self) -> int:
        with self._lock:
            return self._version


class OnlineAdaptation:
    """Runs ``adapter.observe`` on a background thread for each submitted sample.

    ``on_report`` (optional) is called on the training thread after every update with its
    :class:`~.adapter.UpdateReport` (for counters and logs). ``on_warm`` (optional) is called
    on it once, when the adapter's warm-up is over (or failed): the first keyframe it takes is
    trained on at once from then on.
    """

    def __init__(
        self,
        adapter: Adapter,
        slot: WeightSlot,
        queue_size: int = 2,
        on_report: Callable[[UpdateReport], None] | None = None,
        name: str = 'adaptation',
        on_warm: Callable[[], None] | None = None,
        nice: int = 0,
        clock: Callable[[], float] = time.monotonic,
    ):
        if queue_size < 1:
            raise ValueError(f'adaptation queue size must be >= 1, got {queue_size}')
        if not 0 <= nice <= 19:
            raise ValueError(f'adaptation nice must be in [0, 19], got {nice}')
        self.nice = int(nice)
        #: the niceness the training thread runs at (None until it started, or where unsupported)
        self.thread_nice: int | None = None
        self.adapter = adapter
        self.slot = slot
        self.on_report = on_report
        self.on_warm = on_warm
        self._queue: deque[AdaptSample] = deque()
        self._queue_size = int(queue_size)
        self._cond = threading.Condition()
        self._stop = False
        self._busy = False
        self.submitted = 0
        self.dropped = 0
        self.failed = 0
        #: ``dropped`` when the training thread last took a keyframe: more since means behind.
        self._dropped_at_take = 0
        self._clock = clock
        self._last_submit: float | None = None
        #: Seconds between the last two submitted keyframes (None before the second).
        self._interval: float | None = None
        #: Seconds the last update that trained took (None before the first).
        self._last_update: float | None = None
        #: A restart asked and not yet done: ``(first key of the new poses, reason)``.
        self._restart: tuple[int, str] | None = None
        #: Keyframes before the last restart's first key are not trained on (``stale``).
        self._from_key: int | None = None
        self.stale = 0
        #: An update was accepted since the start or the last restart.
        self.learnt = False
        #: The predictor of the loaded weights: inference goes back to it at once on a restart.
        self._loaded = slot.get()[0]
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, sample: AdaptSample) -> bool:
        """Queue a keyframe for training; never blocks. False when an older one was dropped.
        A keyframe from before the last restart's first key is not queued (counted ``stale``)."""
        with self._cond:
            if self._from_key is not None and sample.key < self._from_key:
                self.stale += 1
                return True
            now = self._clock()
            if self._last_submit is not None:
                self._interval = now - self._last_submit
            self._last_submit = now
            self.submitted += 1
            dropped = len(self._queue) >= self._queue_size
            if dropped:
                self._queue.popleft()
                self.dropped += 1
            self._queue.append(sample)
            self._cond.notify()
        return not dropped

    def restart(self, from_key: int, reason: str) -> int:
        """Start the training over from the loaded weights before the next keyframe it takes
        (``adapter.restart``), and never train on a keyframe before ``from_key``: its points
        came from the poses the restart is for. Returns the queued keyframes let go.

        Inference goes back to the loaded weights now, not once the training thread gets to
        it: an update in hand (seconds at idle priority on a busy 2-core machine) is asked to
        stop, and one that ends anyway is not swapped in. Waiting for it, the ``handheld``
        robot told its body frame was predicted by the learnt weights for 7 more keyframes
        (single view 1.4-1.8 m against 0.4-0.5 m)."""
        with self._cond:
            self._from_key = from_key if self._from_key is None else max(self._from_key, from_key)
            kept = [s for s in self._queue if s.key >= self._from_key]
            gone = len(self._queue) - len(kept)
            self._queue = deque(kept)
            self.stale += gone
            self._restart = (from_key, reason)
            self.slot.swap(self._loaded, self.slot.version)
            self._cond.notify()
        return gone

    def _lower_priority(self) -> None:
        """Make this (the training) thread and the torch worker threads it creates yield the CPU.

        On a small CPU the graph's real-time path (inference, multi-view, fusion) must not wait
        for training; with a niceness of 10 the scheduler gives this thread about a tenth of a
        contended core and all of an idle one. Linux keeps the nice value per thread and new
        threads inherit it, so it is set here, before the first torch op creates this thread's
        OpenMP team. Where the platform has no per-thread priority it is said once and ignored.
        """
        if self.nice == 0:
            self.thread_nice = 0
            return
        try:
            tid = threading.get_native_id()
            base = os.getpriority(os.PRIO_PROCESS, tid)
            os.setpriority(os.PRIO_PROCESS, tid, min(19, base + self.nice))
            self.thread_nice = os.getpriority(os.PRIO_PROCESS, tid)
        except (AttributeError, OSError) as exc:  # not Linux / not permitted
            log.warning(
                'adaptation: cannot lower the training thread priority (%s); it runs at normal priority', exc
            )

    def _run(self) -> None:
        self._lower_priority()
        try:
            self.adapter.warm_up()  # at the thread's priority, before the first keyframe comes
        except Exception:
            log.exception('adaptation warm-up failed (the first update pays for it)')
        if self.on_warm is not None:
            try:
                self.on_warm()
            except Exception:  # a warm line that fails must not end training
                log.exception('adaptation: on_warm failed')
        while True:
            with self._cond:
                while not self._queue and self._restart is None and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return
                restart, self._restart = self._restart, None
                if restart is None:
                    sample = self._queue.popleft()
                    behind = self._behind()
                    self._dropped_at_take = self.dropped
                self._busy = True
            try:
                if restart is not None:
                    report = self.adapter.restart(*restart)
                    self.learnt = False
                    self.slot.swap(self._loaded, self.adapter.version)  # the loaded weights, as they are
                else:
                    report = self._observe(sample, behind)
                if self.on_report is not None:
                    self.on_report(report)
            except Exception:  # a bad sample must not end adaptation
                self.failed += 1
                log.exception('adaptation update failed')
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def _observe(self, sample: AdaptSample, behind: bool) -> UpdateReport:
        report = self.adapter.observe(sample, abort=self._abort, behind=behind)
        if report.status != 'skipped':
            self._last_update = report.seconds
        if report.status == 'updated':
            predictor = self.adapter.predictor()
            with self._cond:  # a restart asked meanwhile has the last word (see restart)
                if self._restart is None:
                    self.learnt = True
                    self.slot.swap(predictor, self.adapter.version)
        return report

    def _abort(self) -> bool:
        """The update in hand stops: the node is shutting down, or a restart undoes it anyway."""
        return self._stop or self._restart is not None

    def _behind(self) -> bool:
        """:func:`is_behind` for the keyframe just taken (called holding the lock)."""
        return is_behind(
            bool(self._queue), self.dropped > self._dropped_at_take, self._last_update, self._interval
        )

    def wait_idle(self, timeout: float = 30.0) -> bool:
        """Block until nothing is queued or training (tests, flushing before a save)."""
        with self._cond:
            return self._cond.wait_for(
                lambda: not self._queue and self._restart is None and not self._busy, timeout
            )

    def stop(self, timeout: float = 30.0) -> bool:
        """Stop after the update in hand (queued samples are discarded); True when joined."""
        with self._cond:
            self._stop = True
            self._queue.clear()
            self._cond.notify_all()
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def save(self, path: str | Path, extra_info: dict[str, Any] | None = None) -> Path:
        """Write the weights inference uses now (the last accepted update) as a checkpoint;
        never waits for an update in progress."""
        from ..singleview.checkpoint import save_checkpoint
        from ..singleview.metadata import ModelMetadata

        predictor, version = self.slot.get()
        net = predictor.module.net  # MetricDepthHead around the log-depth network
        info = dict(self.adapter.metadata.info)
        info['adaptation'] = {
            'adapted_from': self.adapter.name,
            'version': version,
            'counters': self.adapter.counters.as_dict(),
            'config': dict(self.adapter.config.__dict__),
            **(extra_info or {}),
        }
        metadata = ModelMetadata.from_dict({**self.adapter.metadata.to_dict(), 'info': info})
        return save_checkpoint(Path(path).expanduser(), net, metadata)
