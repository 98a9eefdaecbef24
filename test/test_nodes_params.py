"""Parameters, the YAML file, the launch file and the console scripts of the processing nodes."""

from __future__ import annotations

import faulthandler
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch
import yaml
from rclpy.parameter import Parameter

from depth_fusion_ros.fusion.pipeline import FusionConfig
from depth_fusion_ros.multiview.neighbours import NeighbourConfig
from depth_fusion_ros.multiview.semidense import MultiViewConfig
from depth_fusion_ros.nodes import fusion_node, multi_view_params
from depth_fusion_ros.nodes.config_yaml import (
    PROCESSING_NODES,
    available_nodes,
    find_config_file,
    node_parameters,
    render_yaml,
)
from depth_fusion_ros.nodes.params import missing_descriptions
from depth_fusion_ros.nodes.testing import RosHarness

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / 'config' / 'depth_fusion.yaml'
LAUNCH = ROOT / 'launch' / 'depth_fusion.launch.py'
BIN = Path(sys.executable).parent


class _Net(torch.nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 2.0 + 0.0 * x[:, :1]


@pytest.fixture(scope='module')
def model_path(tmp_path_factory) -> Path:
    """A tiny TorchScript network with its metadata YAML (the shipped model may not exist yet)."""
    from depth_fusion_ros.singleview.metadata import ModelMetadata, write_metadata_yaml

    folder = tmp_path_factory.mktemp('model')
    torch.jit.script(_Net()).save(str(folder / 'net.pt'))
    write_metadata_yaml(ModelMetadata(input_width=64, input_height=48), folder / 'net.yaml')
    return folder / 'net.pt'


def test_yaml_holds_every_parameter_with_its_default():
    doc = yaml.safe_load(CONFIG.read_text())
    assert set(PROCESSING_NODES) <= set(doc), 'a processing node has no section'
    for node in available_nodes():
        section = doc[node]['ros__parameters']
        specs = node_parameters(node)
        assert list(section) == [s.name for s in specs], f'{node}: regenerate config/depth_fusion.yaml'
        for spec in specs:
            assert section[spec.name] == spec.default, f'{node}.{spec.name}'
            assert spec.description and spec.check(section[spec.name]) == spec.default
    regenerate = 'python -m depth_fusion_ros.nodes.config_yaml > config/depth_fusion.yaml'
    assert CONFIG.read_text() == render_yaml(), f'config/depth_fusion.yaml is stale: {regenerate}'
    assert find_config_file() == CONFIG


def test_core_config_fields_are_all_described():
    assert missing_descriptions(MultiViewConfig, multi_view_params.MULTI_VIEW_DESCRIPTIONS) == []
    assert missing_descriptions(NeighbourConfig, multi_view_params.NEIGHBOUR_DESCRIPTIONS) == []
    from depth_fusion_ros.fusion.pipeline import FUSION_PARAMETER_DESCRIPTIONS

    assert missing_descriptions(FusionConfig, FUSION_PARAMETER_DESCRIPTIONS, fusion_node.FUSION_SKIP) == []


def test_params_file_is_accepted_by_every_node_and_descriptors_are_set(model_path):
    from depth_fusion_ros.nodes.fusion_node import FusionNode
    from depth_fusion_ros.nodes.multi_view_node import MultiViewNode
    from depth_fusion_ros.nodes.single_view_node import SingleViewNode

    with RosHarness(args=['--ros-args', '--params-file', str(CONFIG)]) as ros:
        nodes = [
            MultiViewNode(context=ros.context),
            SingleViewNode(
                context=ros.context, parameter_overrides=[Parameter('model', value=str(model_path))]
            ),
            FusionNode(context=ros.context),
        ]
        try:
            fusion = nodes[2]
            # the node's defaults that differ from the core's: real-time mode, compiled kernels,
            # a bounded Ω (the filter's stage 1 sends every estimate)
            assert fusion.config == FusionConfig(mode='fast', compile_kernel=True, max_points=4096)
            descriptor = fusion.describe_parameter('fusion.sigma1')
            assert 'proximity' in descriptor.description and descriptor.read_only
            assert descriptor.floating_point_range[0].from_value > 0
            assert nodes[0].describe_parameter('keyframe_every').integer_range[0].from_value == 1
        finally:
            for node in nodes:
                node.destroy_node()


def test_launch_file_compiles_and_describes_the_graph():
    source = LAUNCH.read_text()
    compile(source, str(LAUNCH), 'exec')
    pytest.importorskip('launch', reason='launch is not installable from pip (see ROS2_PIP.md)')
    pytest.importorskip('launch_ros', reason='launch_ros is not installable from pip')
    import importlib.util

    spec = importlib.util.spec_from_file_location('depth_fusion_launch', LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.generate_launch_description().entities


def _launch_calls(name: str) -> list[dict]:
    """Keyword arguments (as source text) of every ``name(...)`` call in the launch file."""
    import ast

    tree = ast.parse(LAUNCH.read_text())
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, 'id', '') == name]
    return [
        {k.arg: ast.literal_eval(k.value) if isinstance(k.value, ast.Constant) else ast.unparse(k.value)
         for k in c.keywords} | {'_args': [ast.unparse(a) for a in c.args]}
        for c in calls
    ]  # fmt: skip


def test_launch_file_starts_map_node_only_with_map_true():
    """Without ``launch`` installed: the launch file's map argument and map_node, read from its AST."""
    arguments = {c['_args'][0].strip("'"): c for c in _launch_calls('DeclareLaunchArgument')}
    assert arguments['map']['default_value'] == 'false'
    nodes = {c['executable']: c for c in _launch_calls('Node')}
    assert set(nodes) >= {'multi_view_node', 'single_view_node', 'fusion_node', 'map_node'}
    assert nodes['map_node']['condition'] == "IfCondition(LaunchConfiguration('map'))"
    assert nodes['map_node']['parameters'] == 'common'  # the same params file as the other nodes
    assert 'condition' not in nodes['fusion_node']


class _Process:
    """A console script with its merged output collected by a thread."""

    def __init__(self, *args: str, env: dict[str, str] | None = None) -> None:
        self.proc = subprocess.Popen(
            [str(BIN / args[0]), *args[1:]],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=None if env is None else {**os.environ, **env},
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.append(line)

    @property
    def output(self) -> str:
        return ''.join(self.lines)

    def wait_for_output(self, text: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self.proc.poll() is None:
            if text in self.output:
                return True
            time.sleep(0.1)
        return text in self.output

    def finish(self, timeout: float = 30.0) -> int:
        try:
            code = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            code = self.proc.wait()
        self._reader.join(5.0)
        return code


def test_console_scripts_start_with_the_params_file_and_stop_on_signals(model_path):
    args = ['--ros-args', '--params-file', str(CONFIG)]
    procs = {
        'multi_view_node': _Process('multi_view_node', *args, '-p', 'keyframe_every:=3'),
        'single_view_node': _Process('single_view_node', *args, '-p', f'model:={model_path}'),
        'fusion_node': _Process('fusion_node', *args, '-p', 'fusion.mode:=exact'),
        'bad': _Process('fusion_node', '--ros-args', '-p', 'fusion.weights:=w5'),
    }
    ready = {
        'multi_view_node': 'keyframes every_k every 3',  # the -p on top of the file took effect
        'single_view_node': "single-view model '",
        'fusion_node': 'fusion (exact mode)',
    }
    try:
        for name, marker in ready.items():
            assert procs[name].wait_for_output(marker, 90.0), f'{name} did not start:\n{procs[name].output}'
        for name in ready:  # Ctrl-C, and a service manager's SIGTERM for one of them
            procs[name].proc.send_signal(signal.SIGTERM if name == 'fusion_node' else signal.SIGINT)
        for name in ready:
            code = procs[name].finish()
            assert code == 0, f'{name} exited with {code}:\n{procs[name].output}'
            assert 'final counters' in procs[name].output, procs[name].output
            assert 'Fast DDS profile: ' in procs[name].output, procs[name].output  # said at start
            assert 'executor: events' in procs[name].output, procs[name].output  # node_executor.py
            assert 'Traceback' not in procs[name].output, procs[name].output
            assert 'context is invalid' not in procs[name].output, procs[
                name
            ].output  # logged before shutdown
        assert procs['bad'].finish() == 2
        assert 'fusion.weights' in procs['bad'].output and 'Traceback' not in procs['bad'].output
    finally:
        for proc in procs.values():
            if proc.proc.poll() is None:
                proc.proc.kill()
                proc.finish()


def test_a_namespace_moves_every_topic_of_a_node():
    from depth_fusion_ros.nodes.fusion_node import FusionNode

    with RosHarness() as ros:
        node = FusionNode(context=ros.context, namespace='robot1')
        try:
            published = sorted(p.topic_name for p in node.publishers if 'depth_fusion' in p.topic_name)
            subscribed = sorted(s.topic_name for s in node.subscriptions)
        finally:
            node.destroy_node()
    assert published == [
        '/robot1/depth_fusion/fused/camera_info',
        '/robot1/depth_fusion/fused/confidence',
        '/robot1/depth_fusion/fused/decision',
        '/robot1/depth_fusion/fused/depth',
        '/robot1/depth_fusion/fused/points',
        '/robot1/depth_fusion/keyframe/events',
        '/robot1/depth_fusion/ready',
    ]
    assert all(topic.startswith('/robot1/depth_fusion/') for topic in subscribed), subscribed


def test_a_misspelt_parameter_is_said_with_the_name_meant_and_other_nodes_parameters_are_not_typos(capfd):
    """rclpy ignores a parameter the node does not declare; the node says so in one line per
    name, with the closest declared name. A parameter of another node (a ``/**:`` section
    gives every node all of them) and rclpy's own ``qos_overrides.*`` are no typo."""
    from depth_fusion_ros.nodes.fusion_node import FusionNode
    from depth_fusion_ros.nodes.ignored_params import warn_ignored

    given = [
        Parameter('fusion.mod', value='exact'),
        Parameter('zzz_unheard_of', value=1),
        Parameter('multi_view.method', value='sweep'),  # multi_view_node's
        Parameter('qos_overrides./x.publisher.depth', value=3),
        Parameter('fusion.mode', value='exact'),  # declared: taken
    ]
    with RosHarness() as ros:
        node = FusionNode(context=ros.context, parameter_overrides=given)
        try:
            mode = node.params['fusion.mode']
            typos = warn_ignored(node, ['fusion.mode'])
        finally:
            node.destroy_node()
    err = capfd.readouterr().err
    assert mode == 'exact'
    assert typos == ['fusion.mod', 'zzz_unheard_of']
    assert "'fusion.mod' is not a parameter of fusion_node: ignored (did you mean 'fusion.mode'?)" in err
    assert "'zzz_unheard_of' is not a parameter of fusion_node: ignored" in err
    assert 'multi_view.method' not in err and 'qos_overrides' not in err


def test_a_ctrl_c_as_the_node_finishes_building_still_destroys_it_with_its_final_counters():
    """The signal lands just after the node's "ready" line, before ``run_node`` holds the node
    (a KeyboardInterrupt there left nothing to destroy: exit 0 without final counters)."""
    import os

    from depth_fusion_ros.nodes.console import run_node
    from depth_fusion_ros.nodes.map_node import MapNode

    destroyed = []

    class _Node(MapNode):
        def destroy_node(self) -> None:
            destroyed.append(self.stats.snapshot().summary())
            super().destroy_node()

    def build() -> MapNode:
        node = _Node()
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C while the constructor returns
        return node

    # The handler run_node found is put back: Python's default, or SIG_IGN when the test run
    # itself was started in the background by a shell without job control.
    before = signal.getsignal(signal.SIGINT)
    assert run_node(build, []) == 0
    faulthandler.cancel_dump_traceback_later()  # this process goes on: no stop stacks later
    assert len(destroyed) == 1
    assert signal.getsignal(signal.SIGINT) is before  # restored


def test_a_node_that_hangs_as_it_stops_writes_its_threads_stacks_to_its_log(monkeypatch, capfd):
    """A node process the graph kills for not stopping (graph/spawn.py) has first written where
    each of its threads was, to its stderr (its log): here with the delay cut to 0.3 s and a
    destroy that takes 1 s."""
    from depth_fusion_ros.nodes import console
    from depth_fusion_ros.nodes.map_node import MapNode

    monkeypatch.setattr(console, 'STOP_STACKS_AFTER_S', 0.3)

    class _SlowToStop(MapNode):
        def destroy_node(self) -> None:
            time.sleep(1.0)  # stands for a stop that hangs
            super().destroy_node()

    def build() -> MapNode:
        node = _SlowToStop()
        os.kill(os.getpid(), signal.SIGINT)
        return node

    try:
        assert console.run_node(build, []) == 0
    finally:
        faulthandler.cancel_dump_traceback_later()
    err = capfd.readouterr().err
    assert 'Thread' in err and 'in destroy_node' in err, err[-2000:]


def test_a_remap_rcl_cannot_parse_is_a_one_line_error_not_a_traceback():
    """``depth-fusion launch --pose bad//topic`` once ended in a Python traceback from
    ``rclpy.init`` inside the node; a node started by hand with such a remap says so in one
    line and exits 2, as for a bad parameter."""
    bad = _Process('multi_view_node', '--ros-args', '-r', 'camera/pose:=bad//topic')
    assert bad.finish(60.0) == 2, bad.output
    assert (
        "multi_view_node: cannot start: failed to initialize rcl: Couldn't parse remap rule: " in bad.output
    )
    assert "'-r camera/pose:=bad//topic'" in bad.output and 'Traceback' not in bad.output, bad.output


def test_a_bad_executor_choice_is_a_one_line_error_and_single_still_runs():
    """``DEPTH_FUSION_EXECUTOR`` picks the console node's executor; a typo stops the node at
    once with exit code 2 and a line naming the variable, and ``single`` (the rclpy default
    before the events executor) still runs the node and stops it cleanly."""
    args = ['--ros-args', '--params-file', str(CONFIG)]
    bad = _Process('fusion_node', *args, env={'DEPTH_FUSION_EXECUTOR': 'evnets'})
    single = _Process('fusion_node', *args, env={'DEPTH_FUSION_EXECUTOR': 'single'})
    try:
        assert bad.finish(60.0) == 2, bad.output
        assert "DEPTH_FUSION_EXECUTOR='evnets': must be one of events, single" in bad.output, bad.output
        assert 'Traceback' not in bad.output, bad.output
        assert single.wait_for_output('fusion (fast mode)', 90.0), single.output
        # The executor's line follows the node's construction (console.run_node): waited for,
        # not read at once (a full suite on two cores read the output between the two lines).
        assert single.wait_for_output('executor: single-threaded', 30.0), single.output
        single.proc.send_signal(signal.SIGINT)
        assert single.finish() == 0, single.output
        assert 'final counters' in single.output, single.output
    finally:
        for p in (bad, single):
            if p.proc.poll() is None:
                p.proc.kill()
