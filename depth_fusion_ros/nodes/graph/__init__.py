"""The node graph runner behind ``depth-fusion run``: replayer + three nodes + recorder.

One idea per module:

* :mod:`.topics`       topic names, the node table, what is recorded;
* :mod:`.dds`          the Fast DDS profile and its shared-memory segments;
* :mod:`.options`      :class:`RunOptions` in, :class:`RunResult` out;
* :mod:`.param_merge`  params file + CLI flags + ``--set`` -> per-node parameters;
* :mod:`.spawn`        node processes: command lines, start, stop;
* :mod:`.lifecycle`    :class:`GraphRun`: start, feed, wait for the outputs, stop.
"""

from .dds import (
    PROFILE_ENV,
    apply_fastdds_profile,
    fastdds_profile_path,
    mapped_shm_files,
    orphan_segments,
    remove_segments,
    shm_segments,
)
from .lifecycle import GraphRun, install_stop_signals, run_graph
from .options import GraphError, RunOptions, RunResult
from .param_merge import (
    bag_topic_names,
    node_overrides,
    param_from_file,
    read_params_file,
    recorder_qos,
    ros_arg_value,
)
from .spawn import node_class, node_command, popen_node, stop_processes
from .topics import *  # noqa: F403 - the topic constants are part of the runner's interface

__all__ = [
    'PROFILE_ENV',
    'GraphError',
    'GraphRun',
    'RunOptions',
    'RunResult',
    'apply_fastdds_profile',
    'bag_topic_names',
    'fastdds_profile_path',
    'install_stop_signals',
    'mapped_shm_files',
    'node_class',
    'node_command',
    'node_overrides',
    'orphan_segments',
    'param_from_file',
    'popen_node',
    'read_params_file',
    'recorder_qos',
    'remove_segments',
    'ros_arg_value',
    'run_graph',
    'shm_segments',
    'stop_processes',
]
