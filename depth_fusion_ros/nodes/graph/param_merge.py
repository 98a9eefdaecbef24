"""Merging a ROS params file, the CLI's flags and ``--set`` into per-node parameters."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from .map_output import check_map_path
from .options import RunOptions
from .topics import GRAPH_NODES, MAP_NODE, REPLAYER, TOPIC_GT_DEPTH


def read_params_file(path: Path | None) -> dict[str, dict[str, Any]]:
    """``{node or '/**': {param: value}}`` of a ROS params file (validated enough to fail early)."""
    if path is None:
        return {}
    import yaml

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f'params file {path} does not exist')
    try:
        doc = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ValueError(f'params file {path}: not valid YAML: {exc}') from None
    if not isinstance(doc, dict):
        raise ValueError(f'params file {path}: expected node sections at the top level')
    out: dict[str, dict[str, Any]] = {}
    for node, section in doc.items():
        params = section.get('ros__parameters') if isinstance(section, dict) else None
        if not isinstance(params, dict):
            raise ValueError(f'params file {path}: section {node!r} has no ros__parameters mapping')
        out[str(node).lstrip('/') if node != '/**' else '/**'] = _flatten(params)
    return out


def _flatten(params: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    """Nested YAML mappings -> dotted parameter names, as ROS reads them."""
    flat: dict[str, Any] = {}
    for key, value in params.items():
        name = f'{prefix}{key}'
        if isinstance(value, dict):
            flat.update(_flatten(value, f'{name}.'))
        else:
            flat[name] = value
    return flat


def param_from_file(params: Mapping[str, Mapping[str, Any]], node: str, name: str) -> Any:
    """The value a node gets from the params file: its own section first, then ``/**``."""
    for section in (node, '/**'):
        if name in params.get(section, {}):
            return params[section][name]
    return None


def ros_arg_value(value: Any) -> str:
    """A parameter value as ``-p name:=VALUE`` wants it (YAML)."""
    import yaml

    if isinstance(value, str):
        return value if yaml.safe_load(value) == value and value else f"'{value}'"
    return yaml.safe_dump(value, default_flow_style=True).strip().removesuffix('...').strip()


def node_overrides(
    options: RunOptions, bag_topics: Mapping[str, str] | Sequence[str]
) -> dict[str, dict[str, Any]]:
    """Per node, the parameters the runner sets on top of the params file.

    ``bag_topics``: the bag's topic names, or ``{name: message type}`` (``bag_topic_types``),
    which also sets ``multi_view_node.pose_type`` from the pose topic's type.
    """
    params = read_params_file(options.params_file)
    out: dict[str, dict[str, Any]] = {name: {} for name in (*GRAPH_NODES, REPLAYER[0])}
    if options.device is not None:
        for name in GRAPH_NODES:
            out[name]['device'] = options.device
    if options.single_view_model is not None:
        out['single_view_node']['model'] = options.single_view_model
    replayer = out[REPLAYER[0]]
    replayer['bag'] = str(options.bag)
    if options.rate is not None:
        replayer['rate'] = float(options.rate)
    if options.start_offset is not None:
        replayer['start_offset'] = float(options.start_offset)
    if param_from_file(params, REPLAYER[0], 'topics') in (None, [], ['']):
        # Ground-truth depth is for evaluation only: no node listens, don't pay to publish it.
        played = [t for t in bag_topics if t != TOPIC_GT_DEPTH]
        replayer['topics'] = played or list(bag_topics)
    replayer.setdefault('wait_for_nodes', list(GRAPH_NODES))
    _inputs_from_bag(params, bag_topics, out['multi_view_node'])
    if options.with_map:
        out[MAP_NODE[0]] = map_overrides(options)
    for node, values in options.overrides.items():
        out.setdefault(node, {}).update(values)
    return out


def _inputs_from_bag(
    params: dict, bag_topics: Mapping[str, str] | Sequence[str], multi_view: dict[str, Any]
) -> None:
    """The image transport and pose type the bag holds, unless the params file says.

    A bag with only ``<image>/compressed`` then runs with ``image_transport: compressed``,
    one with Odometry or PoseWithCovarianceStamped poses subscribes with that type from the
    start (``auto`` would discover it, a moment later: the first poses could be lost).
    """
    from ...data.compressed import image_transport_for_topics
    from ..robot_inputs import pose_type_for_topics

    if param_from_file(params, 'multi_view_node', 'image_transport') is None:
        multi_view['image_transport'] = image_transport_for_topics(bag_topics)
    if isinstance(bag_topics, Mapping) and param_from_file(params, 'multi_view_node', 'pose_type') is None:
        multi_view['pose_type'] = pose_type_for_topics(bag_topics)


def map_overrides(options: RunOptions) -> dict[str, Any]:
    """``map_node``'s settings in a run: the mesh written when it stops with ``--save-map``
    (``save_on_shutdown``, after its queue drained), every keyframe integrated in a paced
    replay (its callback waits instead of dropping, as the other nodes' do), the device."""
    values: dict[str, Any] = {}
    if options.save_map is not None:
        values.update(save_path=str(check_map_path(options.save_map)), save_on_shutdown=True)
    if not options.realtime:
        values.update(queue_policy='block', queue_size=16, qos_depth=100)
    if options.device is not None:
        values['device'] = options.device
    return values


def recorder_qos(options: RunOptions) -> str:
    """The QoS the recorder must use to match the nodes' publishers."""
    params = read_params_file(options.params_file)
    kinds = {
        options.overrides.get(n, {}).get('output_qos')
        or param_from_file(params, n, 'output_qos')
        or 'reliable'
        for n in GRAPH_NODES
    }
    return 'sensor_data' if 'sensor_data' in kinds else 'reliable'


def bag_topic_types(bag: Path) -> dict[str, str]:
    """``{topic: message type}`` of the bag, read once for the names and the types."""
    from ...data.bag_open import open_bag

    reader = open_bag(bag)
    try:
        return {c.topic: c.msgtype for c in reader.connections}
    finally:
        reader.close()


def bag_topic_names(bag: Path) -> list[str]:
    return sorted(bag_topic_types(bag))
