"""A once-per-camera check of ``multi_view_node`` (focal length, time offset, mount), off the callbacks.

The callbacks offer every posed frame; the check says what it needs of it (a pose comparison,
microseconds), and only that is queued; a daemon thread computes features and, once, the
estimate. A full queue drops the offered item (the next frame that moved far enough is taken
instead): a check never holds up the stream. A new camera (another size or calibration) is
checked anew. :attr:`CheckRunner.pending` says whether the thread has caught up with the stream.

The thread gives way to the node's keyframe path (:attr:`CheckRunner.busy`): before a
sample's work (features, matching, a pair's costs) it waits while the node has a keyframe or
a filter frame in hand, at most :data:`MAX_YIELD_S` a sample. A check is done once, within the
first seconds of a stream, exactly when the first keyframes are on their way: on 2 cores the
time offset check alone (about 0.5 s of CPU over TUM fr1_xyz's first second) doubled the
multi-view node's latency for those keyframes. A lower thread priority (nice +10) was tried
first and taken out: in a Python process a niced thread that holds the GIL while the kernel
deschedules it holds up the node's other threads, and on a loaded machine the graph then
fused fewer keyframes than at normal priority (docs/performance.md, "The calibration checks
yield to the keyframes").

So the checks' work runs in a process of its own where the node gives one (:attr:`CheckRunner.host`,
``check_process.py``): the thread then only hands each item over and waits on the pipe, and the
check the callbacks ask (:meth:`CheckRunner._item`) is a mirror that the process's replies keep
up to date (its result, the focal check's early look, the pairs it holds). Without a host, or
once the process is gone, the thread runs the check itself.
"""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

from ..camera import PinholeCamera
from ..data.sequence import Frame
from .check_process import CheckProcess, CheckProcessLostError
from .check_process_main import pairs_held
from .params import build_dataclass

#: How long a check's thread waits for the keyframe path at most before each sample (s): under
#: a load that never lets up, the check still takes a sample every half second.
MAX_YIELD_S = 0.5
#: How often it looks again while it waits (s).
YIELD_POLL_S = 0.005


def _never() -> bool:
    return False


class CheckRunner:
    """Feeds one check per camera from the callbacks on its own thread; reports its result once.

    Subclasses say how a check is made (:meth:`_recipe`), what a frame gives it (:meth:`_item`,
    on the callback thread; ``None``: nothing) and which of its methods an item calls
    (:meth:`_call`, returning the result on the item that completes it).
    """

    #: The thread's name, and how many items may wait for it.
    name = 'check'
    queue_size = 2

    def __init__(self, config: Any, on_result: Callable[[PinholeCamera, Any], None]) -> None:
        self.config = config
        self._on_result = on_result
        self._check: Any = None
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=self.queue_size)
        self._thread: threading.Thread | None = None
        #: Set to end the current thread (each thread has its own)
        self._stopping = threading.Event()
        #: The pose of the last item queued as a sample of the current check (``None``: none
        #: yet): the check's next sample is counted from it, not from the last one the thread
        #: took, so a busy thread is never handed samples it would skip (:meth:`_sample_pose_of`).
        self._sample_pose: Any = None
        #: Whether the node's keyframe path has work in hand (set by the node; thread-safe,
        #: cheap): the thread waits while it does, before each sample (:meth:`_give_way`).
        self.busy: Callable[[], bool] = _never
        #: Seconds the thread waited for the keyframe path, over the runner's life.
        self.waited = 0.0
        #: CPU seconds the thread spent on its items (its own thread time), over the runner's
        #: life: what the check took from the node (docs/performance.md, "A slower machine").
        #: In the checks' process, the process's CPU on them.
        self.cpu = 0.0
        #: The checks' process (``None``: the thread runs the check itself); set by the node.
        self.host: CheckProcess | None = None
        #: ``(check, pairs)``: the pairs the check in the process holds, as its last reply said,
        #: and the mirror it is for (a reply to a check restarted meanwhile says nothing of the
        #: new one); ``None``: the check runs here, and says it itself
        self._remote_collected: tuple[Any, int] | None = None

    def _recipe(self, camera: PinholeCamera) -> tuple[type, tuple]:
        """The check for ``camera`` as ``(class, arguments)``: made here, and in the process."""
        raise NotImplementedError

    def _make(self, camera: PinholeCamera) -> Any:
        cls, args = self._recipe(camera)
        return cls(*args)

    def _item(self, check: Any, frame: Frame) -> Any:
        raise NotImplementedError

    def _call(self, item: Any) -> tuple[str, tuple]:
        """The check's method an item calls, and its arguments."""
        raise NotImplementedError

    def _feed(self, check: Any, item: Any) -> Any:
        method, args = self._call(item)
        return getattr(check, method)(*args)

    @property
    def collected(self) -> int:
        """The pairs the current check holds (0 before the first frame)."""
        check = self._check
        if check is None:
            return 0
        remote = self._remote_collected
        if remote is not None and remote[0] is check:
            return remote[1]
        return pairs_held(check)

    def _sample_pose_of(self, item: Any) -> Any:
        """The pose of ``item`` when it is a sample (``None``: not one): the reference of the next."""
        return None

    def _give_way(self, stopping: threading.Event) -> None:
        """Wait while the keyframe path is busy, at most :data:`MAX_YIELD_S`."""
        start = time.monotonic()
        deadline = start + MAX_YIELD_S
        while self.busy() and not stopping.is_set() and time.monotonic() < deadline:
            time.sleep(YIELD_POLL_S)
        self.waited += time.monotonic() - start

    @property
    def pending(self) -> int:
        """Items queued for the thread or in its hands, 0 once it has caught up with the stream or
        the check has its result (or the runner was closed). A test waits for 0 before the next
        frame: the check then takes the same samples however loaded the machine (a loaded one
        drops some, by design)."""
        if self._check is None or self._check.done or self._thread is None:
            return 0
        return self._queue.unfinished_tasks

    @property
    def camera(self) -> PinholeCamera | None:
        """The camera being checked (``None`` before the first frame)."""
        return None if self._check is None else self._check.camera

    @property
    def result(self) -> Any:
        """The current camera's result, once the check has it."""
        return None if self._check is None else self._check.result

    @property
    def settled(self) -> bool:
        """Whether the check is off or has its result (the poses it may correct stay as they are)."""
        return self.config.mode == 'off' or self.result is not None

    def offer(self, frame: Frame, camera: PinholeCamera) -> None:
        """A posed frame on the working grid (callback thread): queued when the check needs it."""
        if self.config.mode == 'off':
            return
        if self._check is None or self._check.camera != camera:  # a new camera: check it anew
            self._stop()
            self._check = self._make(camera)
            self._sample_pose = None
            self._queue = queue.Queue(maxsize=self.queue_size)
            self._stopping = threading.Event()
            args = (self._check, self._recipe(camera), self._queue, self._stopping)
            self._thread = threading.Thread(target=self._run, args=args, daemon=True)
            self._thread.name = self.name
            self._thread.start()
        if self._check.done:
            return
        item = self._item(self._check, frame)
        if item is None:
            return
        try:
            self._queue.put_nowait(item)
        except queue.Full:  # busy: a later frame is taken instead
            return
        pose = self._sample_pose_of(item)
        if pose is not None:  # only a sample that went into the queue moves the reference
            self._sample_pose = pose

    def restart(self) -> None:
        """Forget the current check and its result: the next frame starts a new one (the frames
        it read were posed otherwise than the ones to come)."""
        self._stop()
        self._check = None

    def close(self, timeout: float = 2.0) -> None:
        """Stop the thread and wait for it (at most ``timeout`` s); the result stays. A daemon
        thread still in OpenCV or numpy while the interpreter shuts down can take the process
        down with it, before its DDS shared memory is released."""
        thread = self._thread
        self._stop()
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)

    def _stop(self) -> None:
        """The thread ends before its next item, or at once when idle."""
        self._stopping.set()
        if self._thread is not None:
            with contextlib.suppress(queue.Full):  # full: it stops before its next item
                self._queue.put_nowait(None)
            self._thread = None

    def _run(
        self, check: Any, recipe: tuple[type, tuple], inbox: queue.Queue, stopping: threading.Event
    ) -> None:
        remote = _Remote(self.host, self.name, recipe)
        try:
            while True:
                item = inbox.get()
                if item is None or stopping.is_set():
                    return
                try:
                    # A sample costs real work (features, matching), so it waits for the
                    # keyframe path first; a pose alone does not.
                    if self._sample_pose_of(item) is not None:
                        self._give_way(stopping)
                    result = self._take(check, item, remote, stopping)
                finally:
                    inbox.task_done()
                if result is not None:
                    if not stopping.is_set():  # a check restarted meanwhile reports nothing
                        self._on_result(check.camera, result)
                    return
        finally:
            remote.drop()

    def _take(self, check: Any, item: Any, remote: _Remote, stopping: threading.Event) -> Any:
        """One item, in the process while there is one, else here; the result when it completes
        the check."""
        if remote.host is not None:
            try:
                return self._take_remote(check, item, remote)
            except CheckProcessLostError:
                remote.host = None
                mirrored = self._remote_collected
                if mirrored is not None and mirrored[0] is check:
                    self._remote_collected = None  # this check says its own from now on
                if stopping.is_set():
                    return None
                # Here from this item on: the mirror has none of the process's samples, so the
                # check starts over, on this thread (the loss was said once, by the node).
        started = time.thread_time()
        try:
            return self._feed(check, item)
        finally:
            self.cpu += time.thread_time() - started

    def _take_remote(self, check: Any, item: Any, remote: _Remote) -> Any:
        method, args = self._call(item)
        reply = remote.feed(method, args)
        self.cpu += float(reply[-1])
        if reply[0] == 'error':  # raised here, as the check would have raised on this thread
            raise RuntimeError(f'{self.name}: {reply[1]}')
        _, result, early, collected, _ = reply
        self._remote_collected = (check, int(collected))
        if early is not None:
            check.early = early
        if result is not None:
            check.result = result  # the mirror is done too: the callbacks queue no more
        return result


class _Remote:
    """A runner thread's check in the checks' process: made there with its first item."""

    def __init__(self, host: CheckProcess | None, name: str, recipe: tuple[type, tuple]) -> None:
        self.host = host
        self.recipe = recipe
        self.key = None if host is None else host.key(name)
        self.made = False

    def feed(self, method: str, args: tuple) -> tuple:
        if not self.made:
            self.host.make(self.key, *self.recipe)
            self.made = True
        return self.host.feed(self.key, method, args)

    def drop(self) -> None:
        if self.made and self.host is not None:
            self.host.drop(self.key)


class PairedCheckRunner(CheckRunner):
    """A runner of a check fitted to image pairs (``multiview/paired_check.py``: the focal length
    and mount checks): only the frames it wants as its next sample are queued, grey image and
    pose, the grey image made only then.

    "Next" counts from the last frame queued, not the last the thread took: a thread still busy
    with one sample would otherwise be handed the very next frames too, each far from the last
    it took but not from one another, and skip them on arrival, while they filled the queue.
    """

    #: The check (a ``PairedCheck``), its config dataclass and its parameter section.
    check_type: type
    config_type: type
    section: str

    @classmethod
    def from_parameters(cls, params: dict[str, Any], on_result: Callable[[PinholeCamera, Any], None]) -> Any:
        return cls(build_dataclass(cls.config_type, params, cls.section), on_result)

    def _recipe(self, camera: PinholeCamera) -> tuple[type, tuple]:
        return self.check_type, (camera, self.config)

    def _item(self, check: Any, frame: Frame) -> tuple[Any, Any] | None:
        return (frame.gray, frame.pose) if check.wants(frame.pose, self._sample_pose) else None

    def _sample_pose_of(self, item: tuple[Any, Any]) -> Any:
        return item[1]  # every item is a sample

    def _call(self, item: tuple[Any, Any]) -> tuple[str, tuple]:
        return 'add', item
