"""The life of one graph run: start, feed, wait for the outputs, stop.

Two ways to run the same graph on a bag:

* **composed** (default): ``single_view_node``, ``multi_view_node``, ``fusion_node``, the
  ``bag_replayer`` and a recorder in this process, on one multi-threaded executor. One
  start-up (torch, rclpy) instead of four, nothing copied between processes.
* **processes**: the console scripts started with ``subprocess`` (:mod:`.spawn`), each with the
  same params file, the recorder staying here. What a robot with a live camera runs, one node
  per core.

The replayer starts once every node said it is ready (``depth_fusion/ready``) and, unless
``realtime``, paces the replay by the graph's progress so no keyframe is lost (:mod:`.pacing`).
Either way the run ends by itself: when the replayer reaches the end of the bag, the runner
waits until every keyframe the keyframe policy chose (``depth_fusion/keyframe/events``) is
fused or given up, or until ``flush_timeout`` (a warning then names the keyframes that got no
fused output and how far each one got). Then it
closes the bag (written under a staging name and renamed only now), stops the nodes
(SIGINT to the processes; they exit 0) and returns. Ctrl-C stops everything the same way,
leaving the partial recording under ``OUT.partial/``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from ...cpu_budget import CpuSampler, budget_line
from ..gil import set_switch_interval
from ..graph_events import KeyframeLedger, ReadyWatcher, subscribe_events
from ..node_executor import executor_choice, make_node_executor, spin_until
from .dds import apply_fastdds_profile
from .forked import ForkedNode, forking_server
from .inputs import check_inputs
from .isolation import Isolation, isolate
from .map_output import check_saved_map
from .options import GraphError, RunOptions, RunResult
from .pacing import paced_overrides
from .param_merge import bag_topic_types, node_overrides, recorder_qos
from .spawn import (
    describe_exit,
    node_class,
    node_environment,
    node_ros_args,
    remove_segments_of_killed,
    start_node,
    stop_processes,
)
from .summary import fused_chosen
from .topics import (
    FUSED_OUTPUTS,
    GRAPH_NODES,
    IMAGE,
    POSING_TOPICS,
    RECORDED_TOPICS,
    RECORDER_NODE,
    REPLAYER,
    STAGES,
    TOPIC_FUSED_DEPTH,
    TOPIC_IMAGE,
    TOPIC_KEYFRAME_IMAGE,
    graph_nodes,
)

log = logging.getLogger(__name__)


class GraphRun:
    """One run of the graph; :meth:`run` does it all. Exposed for the benchmark's sampling."""

    def __init__(self, options: RunOptions) -> None:
        self.options = options
        #: The nodes this run starts: the fusion graph, plus ``map_node`` with ``--map``.
        self.graph_nodes = graph_nodes(options.with_map)
        self.started = time.monotonic()
        self.recorder: Any = None
        self.nodes: dict[str, Any] = {}
        self.processes: dict[str, subprocess.Popen | ForkedNode] = {}
        self._context: Any = None
        self._executor: Any = None
        self._spin_thread: threading.Thread | None = None
        #: Composed: each graph node's own executor (``DEPTH_FUSION_EXECUTOR``) and spin thread,
        #: which spins while ``_node_spin_stop`` is clear.
        self._node_executors: dict[str, tuple[Any, threading.Thread]] = {}
        self._node_spin_stop = threading.Event()
        self._runner_spin_stop = threading.Event()  # the runner's own executor (recorder, events)
        self._logs: list[Any] = []
        self._torch_threads_before: int | None = None
        self._switch_interval_before: float | None = None
        self._wall_start = time.time()
        self.exit_codes: dict[str, int | None] = {}
        self.executor_error: BaseException | None = None
        self._next_progress = 0.0
        #: CPU seconds of the graph's processes at every progress tick: the summary's budget line
        #: (``RunResult.cpu_budget``) and the bench's window (cpu_budget.py).
        self.cpu = CpuSampler(self.options.processes)
        self.ledger = KeyframeLedger()
        self.ready = ReadyWatcher()
        self._spawned_at: dict[str, float] = {}
        #: When the fork server started (monotonic s); 0.0 when nodes start as console scripts.
        self._fork_server_started = 0.0
        self.ready_seconds: dict[str, float] = {}
        self.isolation: Isolation | None = None

    @property
    def forked(self) -> bool:
        """Whether this run's node processes are forked from the fork server (graph/forked.py)."""
        return bool(self._fork_server_started)

    # -- public --

    def run(self) -> RunResult:
        import rclpy
        from rclpy.signals import SignalHandlerOptions

        opts = self.options
        types = bag_topic_types(opts.bag)  # a bad bag fails here, before anything starts
        topics = sorted(types)
        overrides = paced_overrides(opts, node_overrides(opts, types))
        check_inputs(opts, topics)  # a bag without image/camera_info/pose fails here, see .inputs
        if opts.processes:
            self._start_fork_server()  # its torch import overlaps with the set-up below
        profile = apply_fastdds_profile()
        log.info('Fast DDS profile: %s', profile)
        self._wall_start = time.time()
        self._context = rclpy.context.Context()
        args = ['--ros-args', '--params-file', str(opts.params_file)] if opts.params_file else None
        self.isolation = isolate(opts.domain_id, opts.localhost_only)  # before any context: see .isolation
        rclpy.init(args=args, context=self._context, signal_handler_options=SignalHandlerOptions.NO)
        previous_handlers = install_stop_signals()
        interrupted = False
        try:
            try:
                self._start_recorder(opts)
                if opts.processes:
                    self._start_processes(overrides)
                else:
                    self._start_composed(overrides)
                self._wait_for_end_of_bag()
                self._wait_for_flush()
            except KeyboardInterrupt:
                interrupted = True
                log.warning('interrupted: stopping the graph')
                if self.recorder is None:
                    raise
            except GraphError as exc:  # a node died: say how far the run got, keep what was recorded
                if self.recorder is not None:
                    exc.result = self._result(interrupted=True)
                    exc.result.recorded = self._close_recorder(success=False)
                raise
            result = self._result(interrupted)
            result.recorded = self._close_recorder(success=not interrupted)
            return result
        finally:
            self._shutdown(interrupted)
            self.isolation.close()
            for sig, handler in previous_handlers.items():
                signal.signal(sig, handler)

    # -- start-up --

    def _start_recorder(self, opts: RunOptions) -> None:
        from rclpy.parameter import Parameter

        from ..recorder import Recorder

        topics = dict(RECORDED_TOPICS)
        topics.update({t: '' for t in opts.record_extra if t not in topics})
        watch = {TOPIC_IMAGE: IMAGE} if opts.track_input else {}
        self.recorder = Recorder(
            output=opts.record,
            topics=topics,
            watch=watch,
            latched=POSING_TOPICS,
            track_only=opts.record is None,
            node_name=RECORDER_NODE,
            context=self._context,
            parameter_overrides=[
                Parameter('storage', value=opts.record_storage),
                Parameter('qos', value=recorder_qos(opts)),
            ],
        )
        # Keyframe events and ready lines: readiness, the flush and the honest summary.
        self._event_subs = subscribe_events(self.recorder, self.ledger, self.ready)
        self._executor = self._make_executor()
        self._executor.add_node(self.recorder)
        args = (self._executor, self._runner_spin_stop)
        self._spin_thread = threading.Thread(target=self._spin, args=args, name='graph-executor', daemon=True)
        self._spin_thread.start()

    def _make_executor(self) -> Any:
        """The runner's executor (its recorder and keyframe events): the nodes' choice, one
        thread; rclpy's multi-threaded one only for ``DEPTH_FUSION_SHARED_EXECUTOR`` (every
        composed node on it, a diagnostic)."""
        from rclpy.executors import MultiThreadedExecutor

        if not os.environ.get('DEPTH_FUSION_SHARED_EXECUTOR'):
            return make_node_executor(executor_choice(), self._context)[0]
        threads = self.options.executor_threads if not self.options.processes else 2
        return MultiThreadedExecutor(num_threads=threads, context=self._context)

    def _spin(self, executor: Any, stop: threading.Event) -> None:
        """One executor's spin thread (the runner's, or a composed node's): until ``stop`` is
        set or the context ends."""
        try:
            spin_until(executor, lambda: self._context.ok() and not stop.is_set())
        except Exception as exc:
            # The context is shut down under the executor at the end: nothing to report then.
            if self._context.ok() and not stop.is_set():
                log.error('executor stopped: %r', exc, exc_info=True)
                self.executor_error = exc

    def _start_composed(self, overrides: dict[str, dict[str, Any]]) -> None:
        import importlib

        from rclpy.parameter import Parameter

        from ..bag_replayer import BagReplayer

        def params(node: str) -> list[Parameter]:
            return [Parameter(k, value=v) for k, v in overrides.get(node, {}).items()]

        self._set_composed_threads()
        self._switch_interval_before = set_switch_interval()  # the graph's threads share one GIL

        for name, (_, module) in self.graph_nodes.items():
            cls = node_class(importlib.import_module(module))
            log.info('starting %s', name)
            started = time.monotonic()
            node = cls(context=self._context, parameter_overrides=params(name))
            self.ready_seconds[name] = time.monotonic() - started
            self.nodes[name] = node
            self._spin_composed(name, node)
        replayer = BagReplayer(
            context=self._context, parameter_overrides=params(REPLAYER[0]), autostart=False
        )
        self.nodes[REPLAYER[0]] = replayer
        self._spin_composed(REPLAYER[0], replayer)
        replayer.start()

    def _spin_composed(self, name: str, node: Any) -> None:
        """Each composed node on its own executor and thread, as each runs in its own process:
        rclpy's executors rebuild their wait set in Python at every wake-up, over every entity
        they hold, so one executor for the whole graph did the bookkeeping of all nodes for
        each message of any one. The executor is the console nodes' choice (the events
        executor unless ``DEPTH_FUSION_EXECUTOR=single``), spun one callback at a time
        (``node_executor.spin_until``: its ``spin()`` would hold the GIL)."""
        if os.environ.get('DEPTH_FUSION_SHARED_EXECUTOR'):
            self._executor.add_node(node)
            return
        executor, line = make_node_executor(executor_choice(), self._context)
        if not self._node_executors:
            log.info('composed graph: %s', line)
        executor.add_node(node)
        thread = threading.Thread(
            target=self._spin, args=(executor, self._node_spin_stop), name=f'executor-{name}', daemon=True
        )
        self._node_executors[name] = (executor, thread)
        thread.start()

    def _set_composed_threads(self) -> None:
        """One torch thread per op unless told otherwise: three workers each running ops on a
        2-thread pool fight over the same cores and all fall behind."""
        threads = self.options.threads_per_node
        if threads is None and 'OMP_NUM_THREADS' in os.environ:
            return
        import torch

        self._torch_threads_before = torch.get_num_threads()
        torch.set_num_threads(threads or 1)
        log.info('composed graph: %d torch thread(s) per op', torch.get_num_threads())

    def _node_env(self) -> dict[str, str]:
        return node_environment(self.options.threads_per_node)

    def _start_processes(self, overrides: dict[str, dict[str, Any]]) -> None:
        env = self._node_env()
        for name, (script, module) in self.graph_nodes.items():
            self._spawn(name, script, module, overrides, env)
        self._wait_for_nodes_ready()
        self._spawn(REPLAYER[0], *REPLAYER, overrides, env)

    def _start_fork_server(self) -> None:
        """Start the server the node processes are forked from (graph/forked.py), unless
        ``DEPTH_FUSION_FORK_NODES=0`` asks for console scripts."""
        started = time.monotonic()
        try:
            forking = forking_server(self._node_env())
        except ValueError as exc:
            raise GraphError(str(exc)) from None
        if forking:
            self._fork_server_started = started

    def _spawn(
        self, name: str, script: str, module: str, overrides: dict[str, dict[str, Any]], env: dict[str, str]
    ) -> None:
        ros_args = node_ros_args(self.options.params_file, overrides.get(name, {}))
        # A forked node's start began with the server's imports: its time to ready counts them.
        # The replayer imports no torch: it starts as its console script, as before.
        fork = bool(self._fork_server_started) and name in self.graph_nodes
        self._spawned_at[name] = self._fork_server_started if fork else time.monotonic()
        self.processes[name] = self._start_node(name, script, module, ros_args, env, fork)
        how = 'forked' if fork else 'started'
        log.info('%s %s (pid %d)', how, name, self.processes[name].pid)

    def _wait_for_nodes_ready(self) -> None:
        """Wait until every node process said it is ready (``depth_fusion/ready``: warm-up done,
        subscriptions made) and this runner hears each node's keyframe events, so no keyframe
        is missed by the summary. The replayer waits for the same lines before it plays."""
        deadline = time.monotonic() + self.options.startup_timeout
        publishers = self._event_subs[0]
        while True:
            self._check_processes()
            for name in self.graph_nodes:
                arrived = self.ready.arrival.get('/' + name)
                if arrived is not None and name not in self.ready_seconds:
                    self.ready_seconds[name] = arrived - self._spawned_at[name]
            waiting = self.ready.missing(list(self.graph_nodes))
            if not waiting and publishers.get_publisher_count() >= len(GRAPH_NODES):
                log.info(
                    'nodes ready after %.1f s (%s)',
                    time.monotonic() - self.started,
                    ', '.join(f'{n} {t:.1f} s' for n, t in self.ready_seconds.items()),
                )
                return
            if time.monotonic() > deadline:
                waiting = waiting or ['the keyframe events of every node']
                raise GraphError(
                    f'{", ".join(waiting)} not ready after {self.options.startup_timeout:g} s'
                    + ''.join(self._log_hint(n) for n in waiting[:1] if n in self.graph_nodes)
                )
            time.sleep(0.05)

    def _start_node(
        self, name: str, script: str, module: str, ros_args: list[str], env: dict[str, str], fork: bool
    ) -> subprocess.Popen | ForkedNode:
        """The node started by ``spawn.start_node``, logging to its file in ``log_dir`` or to
        this terminal."""
        log_path = self.options.log_dir / f'{name}.log' if self.options.log_dir is not None else None
        process, out = start_node(script, module, ros_args, env, log_path, fork)
        if out is not None:
            self._logs.append(out)  # closed in _shutdown
        return process

    # -- waiting --

    def _wait_for_end_of_bag(self) -> None:
        while True:
            self._check_processes()
            if self.options.processes:
                code = self.processes[REPLAYER[0]].poll()
                if code is not None:
                    if code != 0:
                        raise GraphError(f'bag_replayer {describe_exit(code)}{self._log_hint(REPLAYER[0])}')
                    return
            else:
                replayer = self.nodes[REPLAYER[0]]
                if replayer.finished.wait(0.1):
                    if replayer.error is not None:
                        raise GraphError(f'bag_replayer failed: {replayer.error!r}')
                    return
            if self.options.processes:
                time.sleep(0.1)
            self._tick_progress()

    def _tick_progress(self) -> None:
        """Every ``progress_period`` s while the graph runs: read its processes' CPU time
        (:attr:`cpu`), then call ``on_progress`` (benchmark sampling)."""
        now = time.monotonic()
        if now < self._next_progress:
            return
        self._next_progress = now + self.options.progress_period
        self.cpu(self)
        if self.options.on_progress is not None:
            self.options.on_progress(self)

    def _check_processes(self) -> None:
        """Raise ``GraphError`` when a node process or this process's executor died."""
        if self.executor_error is not None:
            raise GraphError(f'the executor stopped: {self.executor_error!r}')
        if not self.options.processes:
            return
        for name in self.graph_nodes:
            code = self.processes[name].poll()
            if code is not None:
                raise GraphError(f'{name} {describe_exit(code)}{self._log_hint(name)}')

    def _log_hint(self, name: str) -> str:
        if self.options.log_dir is None:
            return ''
        return f' (see {self.options.log_dir / f"{name}.log"})'

    def chosen_keyframes(self) -> list[int]:
        """Every keyframe the policy chose: the chosen events, plus any announced or fused one
        whose event was missed (so nothing fused is ever left out of the count)."""
        logs = self.recorder.stamp_logs
        seen = set(self.ledger.snapshot().chosen)
        for topic in (TOPIC_KEYFRAME_IMAGE, TOPIC_FUSED_DEPTH):
            if topic in logs:
                seen.update(logs[topic].stamps())
        return sorted(seen)

    def pending_keyframes(self) -> dict[int, str]:
        """Chosen keyframes without their complete fused output -> what became of each."""
        logs = self.recorder.stamp_logs
        drops = self.ledger.snapshot().dropped
        missing = {}
        for stamp in self.chosen_keyframes():
            if all(topic in logs and stamp in logs[topic] for topic in FUSED_OUTPUTS):
                continue
            if stamp in drops:
                missing[stamp] = f'dropped: {drops[stamp]}'
                continue
            announced = TOPIC_KEYFRAME_IMAGE in logs and stamp in logs[TOPIC_KEYFRAME_IMAGE]
            lacking = [what for topic, what in STAGES if topic not in logs or stamp not in logs[topic]]
            if not announced:
                missing[stamp] = 'chosen, never announced'
            else:
                missing[stamp] = 'no ' + ' and no '.join(lacking) if lacking else 'not fused'
        return missing

    def _wait_for_flush(self) -> None:
        """Wait until every chosen keyframe is fused or given up; warn naming what never came.

        The nodes report each keyframe's end (``fused`` or ``dropped:<reason>``), so the run is
        done when none is in flight and nothing arrived for ``settle`` s (composed: the workers
        must be idle too). A keyframe still in flight after ``idle_timeout`` s without any
        output is given up; ``flush_timeout`` bounds it all.
        """
        opts = self.options
        start = time.monotonic()
        why = ''
        while True:
            self._check_processes()
            now = time.monotonic()
            silent = now - max(self.recorder.last_arrival, self.ledger.last_event)
            if silent >= opts.settle and self._nodes_idle():
                if not self.in_flight_keyframes():
                    break
                if silent >= opts.idle_timeout:
                    why = f'nothing arrived for {silent:.0f} s'
                    break
            if now - start >= opts.flush_timeout:
                why = f'gave up after {opts.flush_timeout:g} s'
                break
            self._tick_progress()
            time.sleep(0.05)
        missing = self.pending_keyframes()
        if missing:
            listed = ', '.join(f'{s / 1e9:.3f} ({what})' for s, what in list(missing.items())[:10])
            more = f' and {len(missing) - 10} more' if len(missing) > 10 else ''
            log.warning(
                '%d chosen keyframe(s) have no fused output%s: %s%s%s',
                len(missing),
                f' ({why})' if why else '',
                listed,
                more,
                self._drop_summary(),
            )

    def in_flight_keyframes(self) -> list[int]:
        """Chosen keyframes neither fused nor given up yet (they may still come)."""
        logs = self.recorder.stamp_logs
        fused = set(logs[TOPIC_FUSED_DEPTH].stamps()) if TOPIC_FUSED_DEPTH in logs else set()
        snap = self.ledger.snapshot()
        done = fused | set(snap.dropped)
        return [s for s in self.chosen_keyframes() if s not in done]

    def _drop_summary(self) -> str:
        """``'; dropped by fusion_node: worker_queue_full=2'`` (composed mode: the nodes' counters)."""
        parts = []
        for name, node in self.nodes.items():
            if name in GRAPH_NODES:
                dropped = node.stats.snapshot().dropped
                if dropped:
                    parts.append(f'{name}: ' + ', '.join(f'{k}={v}' for k, v in sorted(dropped.items())))
        return '; dropped by ' + '; '.join(parts) if parts else ''

    def _nodes_idle(self) -> bool:
        """Composed: every worker has finished, the map's integration included (processes are
        judged by their outputs only)."""
        return all(node.wait_idle(0.0) for name, node in self.nodes.items() if name in self.graph_nodes)

    # -- results and shutdown --

    def _images_played(self) -> int | None:
        """Camera images the replayer published: its counter composed; as processes the bag's
        count when the whole bag played once (else unknown)."""
        replayer = self.nodes.get(REPLAYER[0])
        if replayer is not None:
            return int(replayer.stats.published.get(TOPIC_IMAGE, 0))
        settings = self.options.overrides.get(REPLAYER[0], {})
        if self.options.start_offset or settings.get('loop') or settings.get('start_offset'):
            return None
        from ...data.bag_open import open_bag

        reader = open_bag(self.options.bag)
        try:
            return sum(c.msgcount for c in reader.connections if c.topic == TOPIC_IMAGE)
        finally:
            reader.close()

    def _result(self, interrupted: bool) -> RunResult:
        logs = self.recorder.stamp_logs
        announced = logs[TOPIC_KEYFRAME_IMAGE].stamps() if TOPIC_KEYFRAME_IMAGE in logs else []
        fused = logs[TOPIC_FUSED_DEPTH].stamps() if TOPIC_FUSED_DEPTH in logs else []
        latencies = {}
        if TOPIC_IMAGE in logs and TOPIC_FUSED_DEPTH in logs:
            for stamp in fused:
                t_in = logs[TOPIC_IMAGE].arrival(stamp)
                t_out = logs[TOPIC_FUSED_DEPTH].arrival(stamp)
                if t_in is not None and t_out is not None:
                    latencies[stamp] = t_out - t_in
        stats = {}
        for name, node in self.nodes.items():
            if name in self.graph_nodes:
                stats[name] = node.stats.snapshot()
        result = RunResult(
            announced=announced,
            fused=fused,
            chosen=self.chosen_keyframes(),
            drops=self.ledger.snapshot().dropped,
            paced=not self.options.realtime,
            ready_seconds=dict(self.ready_seconds),
            images_played=self._images_played(),
            images_handled=self.ledger.snapshot().images,
            constructor_seconds={
                n: st.seconds
                for n in self.graph_nodes
                if (st := self.ready.statuses.get('/' + n)) is not None
            },
            warm_seconds={
                n: warm.seconds
                for n in self.graph_nodes
                if (st := self.ready.statuses.get('/' + n)) is not None
                and not st.warm
                and (warm := self.ready.warm_statuses.get('/' + n)) is not None
            },
            missing=self.pending_keyframes(),
            recorded=None,
            counts=dict(self.recorder.counts),
            unannounced=self.recorder.waiting_topics,
            seconds=time.monotonic() - self.started,
            interrupted=interrupted,
            node_stats=stats,
            latencies=latencies,
        )
        result.cpu_budget = budget_line(self.cpu, fused_chosen(result))
        return result

    def _close_recorder(self, success: bool) -> Path | None:
        path = self.recorder.close(success=success)
        if path is not None:
            log.info('%s %s', 'recorded' if success else 'partial recording left in', path)
        return path

    def _shutdown(self, interrupted: bool) -> None:
        if self.processes:
            self.exit_codes = stop_processes(self.processes, interrupted)
        replayer = self.nodes.get(REPLAYER[0])
        if replayer is not None:
            replayer.stop()
        # The composed nodes' spin loops end first (each within its 0.2 s wait and the
        # callback in hand), so no node is removed or destroyed under a spinning executor.
        self._node_spin_stop.set()
        for _, thread in self._node_executors.values():
            thread.join(5.0)
        for name in reversed(list(self.nodes)):
            executor = self._node_executors.get(name, (self._executor, None))[0]
            with contextlib.suppress(Exception):
                executor.remove_node(self.nodes[name])
            try:
                self.nodes[name].destroy_node()
            except Exception as exc:  # one node's failure must not leave the others running
                log.error('%s: destroy_node failed: %r', name, exc)
        # The runner's loop ends before its recorder is destroyed (as the nodes' loops above).
        self._runner_spin_stop.set()
        if self._spin_thread is not None:
            self._spin_thread.join(5.0)
        if self.recorder is not None:
            if not self.recorder.closed:
                with contextlib.suppress(Exception):
                    self.recorder.close(success=False)
            self.recorder.destroy_node()
        for executor, _ in self._node_executors.values():
            with contextlib.suppress(Exception):
                executor.shutdown(timeout_sec=5.0)
        if self._executor is not None:
            self._executor.shutdown(timeout_sec=5.0)
        if self._context is not None:
            self._context.try_shutdown()
        # After this process's own participants (the recorder, the listener) left the graph.
        remove_segments_of_killed(self.exit_codes, self._wall_start)
        for f in self._logs:
            f.close()
        if self._torch_threads_before is not None:  # the caller's process gets its pool back
            import torch

            torch.set_num_threads(self._torch_threads_before)
        if self._switch_interval_before is not None:
            sys.setswitchinterval(self._switch_interval_before)


def _raise_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


def install_stop_signals() -> dict[int, Any]:
    """SIGINT and SIGTERM stop the run cleanly (as ``KeyboardInterrupt``); returns the old handlers.

    Also when the shell started us with SIGINT ignored (a background job) or a supervisor
    stops us with SIGTERM: the node processes must never be orphaned.
    """
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {sig: signal.signal(sig, _raise_interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}


def run_graph(options: RunOptions) -> RunResult:
    """Run the graph on ``options.bag`` until the bag ends and the outputs are flushed."""
    run = GraphRun(options)
    result = run.run()
    result.exit_codes = dict(run.exit_codes)
    result.domain_id = run.isolation.domain if run.isolation else None
    if options.save_map is not None:  # written by map_node as it stopped
        result.map_file, result.map_size, result.map_error = check_saved_map(
            options.save_map, run._wall_start
        )
    return result
