"""``depth-fusion launch``: the graph's nodes for a live camera, started and stopped as one.

Why: pip has no ``ros2 launch`` (no ``launch_ros``), so a live graph was three console
scripts in three terminals, which start at once on 2 cores in ~3.5 s, each importing torch
(docs/performance.md). This starts ``multi_view_node``, ``single_view_node`` and
``fusion_node`` (and ``map_node`` with ``map``) as their own processes, the way
``launch/depth_fusion.launch.py`` does with a ROS install: one params file, the multi-view
node's inputs remapped, each node's output to this terminal or its log file. They are forked
from the fork server that ``depth-fusion run --processes`` uses (``forked.py``), so the
graph is ready sooner.

It supervises them like ``ros2 launch`` with every node required: Ctrl-C or SIGTERM stops
them all (SIGINT, then a kill after the timeout) and exits 0 when every node stopped cleanly.
A node that exits on its own stops the others and exits 1, naming it and how it ended. Either
way it ends with the count ``depth-fusion run`` gives: keyframes chosen, fused and dropped (by
reason), from the nodes' keyframe events (``live_ledger.py``). Unlike
``depth-fusion run`` it plays nothing, records nothing and joins the environment's ROS domain
(``ROS_DOMAIN_ID``): the camera and the SLAM are already there.
"""

from __future__ import annotations

import logging
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .forked import forking_server
from .lifecycle import install_stop_signals
from .live_ledger import start_listening
from .spawn import (
    STOP_TIMEOUT_S,
    describe_exit,
    node_environment,
    node_ros_args,
    remove_segments_of_killed,
    start_node,
    stop_processes,
)
from .summary import live_empty, live_summary
from .topics import graph_nodes

log = logging.getLogger(__name__)

#: The multi-view node's input names (as it declares them) that ``LaunchOptions.inputs`` remaps;
#: the launch file's arguments of the same meaning.
INPUTS = {
    'image': 'camera/rgb/image_color',
    'camera_info': 'camera/rgb/camera_info',
    'pose': 'camera/pose',
    'corrected_path': 'camera/corrected_path',
}


@dataclass
class LaunchOptions:
    """What ``depth-fusion launch`` was asked for."""

    params_file: Path | None = None
    with_map: bool = False
    #: ``INPUTS`` key -> the topic to read it from (``{'pose': '/orb_slam3/camera_pose'}``).
    inputs: dict[str, str] = field(default_factory=dict)
    #: node -> {parameter: value}, as ``run --set`` gives them.
    overrides: dict[str, dict[str, Any]] = field(default_factory=dict)
    log_dir: Path | None = None
    threads_per_node: int | None = None
    #: Seconds a node may take to stop on SIGINT before it is killed.
    stop_timeout: float = STOP_TIMEOUT_S


#: The inputs each node reads that ``LaunchOptions.inputs`` remaps.
NODE_INPUTS = {'multi_view_node': tuple(INPUTS), 'map_node': ('corrected_path',)}


def launch_ros_args(name: str, opts: LaunchOptions) -> list[str]:
    """The ``--ros-args`` of one node: the params file and its ``--set`` values
    (``spawn.node_ros_args``), then the remaps of the inputs it reads."""
    args = node_ros_args(opts.params_file, opts.overrides.get(name, {}))
    for key in NODE_INPUTS.get(name, ()):
        if key in opts.inputs:
            args += ['-r', f'{INPUTS[key]}:={opts.inputs[key]}']
    return args


def launch(opts: LaunchOptions) -> int:
    """Start the nodes, wait until one ends or this process is asked to stop, stop them all;
    the exit code (0: stopped on request, every node cleanly, and a keyframe was fused; 1: a
    node ended on its own or did not stop cleanly, or nothing was fused)."""
    env = node_environment(opts.threads_per_node)
    forking = forking_server(env)
    listener = start_listening()  # before the nodes: their first keyframe events are heard
    previous = install_stop_signals()  # SIGTERM as Ctrl-C: the nodes are never orphaned
    processes: dict[str, Any] = {}
    logs = []
    since = time.time()
    interrupted = False
    ended: tuple[str, int] | None = None
    try:
        for name, (script, module) in graph_nodes(opts.with_map).items():
            log_path = None if opts.log_dir is None else opts.log_dir / f'{name}.log'
            process, out = start_node(script, module, launch_ros_args(name, opts), env, log_path, forking)
            processes[name] = process
            if out is not None:
                logs.append(out)
            where = f', log {log_path}' if log_path else ''
            log.info('%s %s (pid %d%s)', 'forked' if forking else 'started', name, process.pid, where)
        log.info('%d nodes running; Ctrl-C stops them', len(processes))
        ended = _wait_for_an_end(processes)
    except KeyboardInterrupt:
        interrupted = True
        log.info('stopping the nodes')
    finally:
        stopping = time.monotonic()
        codes = stop_processes(processes, interrupted, opts.stop_timeout)
        for f in logs:
            f.close()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        empty = None
        if listener is not None:
            snapshot = listener.snapshot()
            log.info(live_summary(snapshot, time.time() - since))
            empty = live_empty(snapshot)
            listener.close()
        remove_segments_of_killed(codes, since)  # once the listener left the graph too
    if ended is not None:
        name, code = ended
        log.error('%s %s: the other nodes were stopped', name, describe_exit(code))
        return 1
    unclean = {n: c for n, c in codes.items() if c not in (0, None)}
    for name, code in unclean.items():
        log.error('%s did not stop cleanly (exit code %d)', name, code)
    if not unclean:
        log.info('%d nodes stopped cleanly in %.1f s', len(codes), time.monotonic() - stopping)
    if empty is not None:
        log.error(empty)
    return 1 if unclean or empty is not None else 0


def _wait_for_an_end(processes: dict[str, Any]) -> tuple[str, int]:
    """Until a node ends (returned: its name and exit code) or a stop signal interrupts."""
    while True:
        for name, process in processes.items():
            code = process.poll()
            if code is not None:
                return name, code
        time.sleep(0.2)
