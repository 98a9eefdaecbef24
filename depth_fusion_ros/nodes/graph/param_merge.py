"""Merging a ROS params file, the CLI's flags and ``--set`` into per-node parameters."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from .options import RunOptions
from .topics import GRAPH_NODES, REPLAYER, TOPIC_GT_DEPTH


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


def node_overrides(options: RunOptions, bag_topics: Sequence[str]) -> dict[str, dict[str, Any]]:
    """Per node, the parameters the runner sets on top of the params file."""
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
    for node, values in options.overrides.items():
        out.setdefault(node, {}).update(values)
    return out


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


def bag_topic_names(bag: Path) -> list[str]:
    from ..bag_replayer import open_bag

    reader = open_bag(bag)
    try:
        return sorted({c.topic for c in reader.connections})
    finally:
        reader.close()
