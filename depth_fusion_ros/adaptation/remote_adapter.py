"""An Adapter whose training runs in a process of its own (``trainer_process.py``).

:class:`RemoteAdapter` answers what :class:`~.online.OnlineAdaptation` and the node ask of an
:class:`~.adapter.Adapter` (``observe``, ``predictor``, ``warm_up``, ``name``, ``metadata``,
``config``, ``counters``, ``version``), so the training thread, the weight slot, the save
service and the summary work unchanged. The thread now only waits on a pipe (no GIL held)
while the child trains at its own priority; why that matters: ``trainer_process.py``.

The parent keeps a copy of the network for inference: after each accepted update the child
sends the new weights (about 2 MB for the shipped network), the parent copies them into its
copy, and ``predictor()`` hands out eval copies of it exactly as the Adapter does.

Faults: a child that cannot build its adapter, or dies later, ends training for the run
(every later keyframe is reported ``skipped``, ``trainer_stopped``, and the error is logged
once); inference goes on with the last accepted weights.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from multiprocessing.connection import Connection

import torch

from ..child_process import child_environment, receive, send
from ..singleview.predictor import DepthPredictor, predictor_from_network, resolve_device
from .adapter import AdapterCounters, UpdateReport, load_adaptable
from .config import AdaptConfig
from .inference_copies import InferenceCopies
from .sample import AdaptSample

log = logging.getLogger(__name__)

#: Seconds between the waiting thread's looks at ``abort`` while the child trains.
POLL_S = 0.05


class RemoteAdapter:
    """The Adapter's interface over a training process; ``close()`` ends the process."""

    def __init__(
        self,
        spec: str,
        config: AdaptConfig | None = None,
        device: str | torch.device = 'cpu',
        nice: int = 10,
        threads: int | None = None,
        idle: bool = False,
    ):
        self.config = config or AdaptConfig()
        self.config.validate()
        self.device = resolve_device(device)
        # Loaded here too, for the inference copies and so that a bad model is the node's
        # start-up error, as with the in-process Adapter (the same checks: load_adaptable).
        self.net, self.metadata, self.name = load_adaptable(spec, self.device)
        self.net.eval()
        for p in self.net.parameters():
            p.requires_grad_(False)
        #: The loaded weights (``state_dict`` order), for a restart without the child.
        self._loaded = [t.detach().clone() for t in self.net.state_dict().values()]
        self._copies = InferenceCopies(self.net)
        self.counters = AdapterCounters()
        self.version = 0
        self.nice = int(nice)
        #: Whether the process was asked to run under ``SCHED_IDLE`` (``priority.idle_policy``).
        self.idle = bool(idle)
        self._error: str | None = None
        self._ready = False
        self._closing = False
        ours, theirs = socket.socketpair()
        n_threads = torch.get_num_threads() if threads is None else int(threads)
        self._proc = subprocess.Popen(
            [
                sys.executable,
                '-m',
                'depth_fusion_ros.adaptation.trainer_process',
                str(theirs.fileno()),
                str(self.nice),
                str(n_threads),
                str(int(self.idle)),
            ],
            pass_fds=(theirs.fileno(),),
            env=child_environment(),
        )
        theirs.close()
        self._conn = Connection(ours.detach())
        send(self._conn, ('init', str(spec), self.config, str(self.device)))

    @property
    def pid(self) -> int:
        return self._proc.pid

    @property
    def ready(self) -> bool:
        """The child has built its adapter and takes keyframes."""
        return self._ready

    # --- what OnlineAdaptation asks -------------------------------------------------------------

    def warm_up(self) -> None:
        """Wait until the child has built its adapter (the training thread calls this first)."""
        if self._ready or self._error is not None:
            return
        reply = self._receive(None)
        if reply is None:  # gone, or closing before it was ready
            return
        if reply[0] == 'error':
            self._fail(f'the training process could not start: {reply[1]}')
            return
        self._ready = True

    def observe(
        self, sample: AdaptSample, abort: Callable[[], bool] | None = None, behind: bool = False
    ) -> UpdateReport:
        """One update in the child (see ``Adapter.observe``); the accepted weights come back."""
        t0 = time.perf_counter()
        self.warm_up()
        if self._error is not None or not self._ready:
            return self._skip(sample.key, t0)
        try:
            send(self._conn, ('observe', sample, bool(behind)))
        except OSError as exc:
            self._fail(f'the training process is gone ({exc})')
            return self._skip(sample.key, t0)
        reply = self._receive(abort)
        if reply is None:
            return self._skip(sample.key, t0)
        if reply[0] == 'failed':
            self.counters = reply[2]
            raise RuntimeError(f'training process: {reply[1]}')
        _, report, self.counters, weights = reply
        if weights is not None:
            self._load(weights)
        self.version = report.version
        return report

    def restart(self, key: int, reason: str) -> UpdateReport:
        """Start the child's training over from the loaded weights (``Adapter.restart``), and
        take them here as the new version (they do not cross the pipe: this side holds them).
        Where the child is gone they are taken all the same: inference must not keep what the
        restart undoes."""
        t0 = time.perf_counter()
        self.warm_up()
        reply = None
        if self._error is None and self._ready:
            try:
                send(self._conn, ('restart', int(key), str(reason)))
                reply = self._receive(None)
            except OSError as exc:
                self._fail(f'the training process is gone ({exc})')
        self._load(self._loaded)
        if reply is not None and reply[0] == 'report':
            _, report, self.counters, _ = reply
            self.version = report.version
            return report
        self.version += 1
        self.counters.restarts += 1
        return UpdateReport(key, 'restarted', reason, version=self.version, seconds=time.perf_counter() - t0)

    def predictor(self) -> DepthPredictor:
        """A predictor around a copy of the last accepted weights (as ``Adapter.predictor``)."""
        return predictor_from_network(self._copies.take(), self.metadata, self.device, name=self.name)

    # --- the process ----------------------------------------------------------------------------

    def cancel(self) -> None:
        """From now on nothing waits for the child: an update in hand is asked to stop, and a
        child still starting is not waited for (a node shutting down; then :meth:`close`)."""
        self._closing = True

    def close(self, timeout: float = 10.0) -> bool:
        """Ask the child to stop (an update in hand stops at its next step) and reap it; True
        when it ended by itself or was still starting (False: killed after ``timeout``).

        A child still starting holds nothing (no keyframe reached it; the weights are this
        process's) and would read the request only once it has imported torch and built its
        adapter: seconds at nice +10 on a busy machine (measured: 6.5 s of a 7.8 s graph stop,
        2 cores under load), which a graph that kills a node after 15 s cannot spare. It is
        ended at once."""
        self._closing = True
        if not self._ready and self._error is None:
            self._proc.kill()
            self._proc.wait()
            self._conn.close()
            return True
        ended = True
        with contextlib.suppress(OSError):
            send(self._conn, ('stop',))
        try:
            self._proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
            ended = False
        self._conn.close()
        return ended

    def _receive(self, abort: Callable[[], bool] | None) -> tuple | None:
        """The child's next reply, asking it once to stop when ``abort`` turns true or the
        adapter is closing; None when the child died (the adapter then failed) or, closing, is
        still starting."""
        asked = False
        try:
            # ``abort`` is looked at before the first wait: an update shorter than POLL_S (a
            # small network) was otherwise done before a stop asked at once reached it.
            while True:
                if not asked and (self._closing or (abort is not None and abort())):
                    if not self._ready:
                        return None
                    send(self._conn, ('abort',))  # after the request: for this update only
                    asked = True
                if self._conn.poll(POLL_S):
                    break
                if self._proc.poll() is not None and not self._conn.poll(0):
                    raise EOFError
            return receive(self._conn)
        except (EOFError, OSError):
            code = self._proc.poll()
            self._fail(f'the training process ended (exit status {code})')
            return None

    def _fail(self, reason: str) -> None:
        if self._error is None:
            self._error = reason
            log.error(
                'adaptation: %s; no more training in this run, inference keeps the last weights', reason
            )

    def _skip(self, key: int, t0: float) -> UpdateReport:
        """A keyframe not trained on because the child is gone (or, closing, never started)."""
        self.counters.observed += 1
        self.counters.skip('trainer_stopped' if self._error is not None else 'stopped')
        reason = f'trainer_stopped: {self._error}' if self._error is not None else 'stopped'
        return UpdateReport(key, 'skipped', reason, version=self.version, seconds=time.perf_counter() - t0)

    @torch.no_grad()
    def _load(self, weights: list[torch.Tensor]) -> None:
        dst = list(self.net.state_dict().values())
        if len(dst) != len(weights):
            raise RuntimeError(f'training process sent {len(weights)} tensors for a network of {len(dst)}')
        torch._foreach_copy_(dst, [w.to(self.device) for w in weights])
