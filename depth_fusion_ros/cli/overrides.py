"""``--set OWNER.KEY=VALUE`` options, shared by the subcommands that take them, and their check.

Why the check: ``--set nosuchnode.x=1`` and ``--set multi_view_node.keyframe_evry=3`` (a typo)
used to be ignored silently, and the run used the default. Every name is now checked before
any work against what really exists, with a did-you-mean:

* ``run``: node names and the nodes' ``PARAMETERS`` tables (``nodes/config_yaml``; importing a
  node module declares nothing and starts no rclpy), plus what every ROS node has
  (``use_sim_time``, ``qos_overrides.*``);
* ``evaluate``: the stages the evaluation methods read (:func:`evaluation_stages`) and the
  fields of their config dataclasses.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Mapping
from pathlib import Path

from ..nodes.ignored_params import ROS_NODE_PARAMETERS, ROS_PARAMETER_PREFIXES, node_parameter_names


def parse_overrides(items: list[str], owner: str = 'STAGE') -> dict[str, dict[str, object]]:
    """``['fusion.mode=fast', 'fusion_node.fusion.mode=exact']`` ->
    ``{'fusion': {'mode': 'fast'}, 'fusion_node': {'fusion.mode': 'exact'}}``.

    The owner (a stage or a node) is what comes before the first dot; the value is parsed as
    YAML so numbers, booleans and lists get their types (``96`` is an int, ``true`` a bool).
    """
    import yaml

    out: dict[str, dict[str, object]] = {}
    for item in items:
        key, sep, value = item.partition('=')
        name, dot, param = key.partition('.')
        if not sep or not dot or not name or not param:
            raise ValueError(f'--set expects {owner}.KEY=VALUE, got {item!r}')
        try:
            parsed = yaml.safe_load(value)
        except yaml.YAMLError:
            raise ValueError(f'--set {item}: {value!r} is not a valid value (YAML)') from None
        out.setdefault(name, {})[param] = parsed
    return out


def did_you_mean(name: str, known: Iterable[str]) -> str:
    """``'; did you mean keyframe_every?'`` or ``''``."""
    close = difflib.get_close_matches(name, list(known), n=3, cutoff=0.6)
    return f'; did you mean {" or ".join(close)}?' if close else ''


def check_names(
    overrides: Mapping[str, Mapping[str, object]],
    known: Mapping[str, Iterable[str]],
    owner: str,
    accept: frozenset[str] = frozenset(),
    accept_prefixes: tuple[str, ...] = (),
    source: str | None = None,
) -> None:
    """Raise ``ValueError`` (one line, with a did-you-mean) for the first unknown owner or key.
    ``source``: where the names come from, to start the line with (default ``--set OWNER.KEY``)."""
    for name, values in overrides.items():
        if name not in known:
            first = next(iter(values), 'KEY')
            raise ValueError(
                f'--set {name}.{first}: unknown {owner} {name!r}{did_you_mean(name, known)} '
                f'(known: {", ".join(sorted(known))})'
            )
        params = set(known[name])
        for key in values:
            if key in params or key in accept or key.startswith(accept_prefixes):
                continue
            where = source or f'--set {name}.{key}'
            raise ValueError(
                f'{where}: {name} has no parameter {key!r}{did_you_mean(key, params)}'
                + (
                    ' (all of them: docs/nodes.md)'
                    if owner == 'node'
                    else f' (known: {", ".join(sorted(params))})'
                )
            )


def check_node_overrides(overrides: Mapping[str, Mapping[str, object]]) -> None:
    """``run --set NODE.PARAM=VALUE``: the node exists and declares the parameter."""
    if overrides:
        check_names(overrides, node_parameter_names(), 'node', ROS_NODE_PARAMETERS, ROS_PARAMETER_PREFIXES)


def check_params_file(path: Path | None) -> None:
    """``run`` / ``launch --params FILE``: each section named after one of the package's nodes
    holds only that node's parameters (one line, with a did-you-mean, before any node starts;
    the nodes would only warn). ``/**`` and other nodes' sections are left alone: a file
    shared with the rest of a robot's graph is fine."""
    if path is None:
        return
    from ..nodes.graph.param_merge import read_params_file

    known = node_parameter_names()
    ours = {node: params for node, params in read_params_file(path).items() if node in known}
    check_names(ours, known, 'node', ROS_NODE_PARAMETERS, ROS_PARAMETER_PREFIXES, source=f'--params {path}')


def evaluation_stages() -> dict[str, set[str]]:
    """``{stage: keys}`` that ``evaluate --set STAGE.KEY=VALUE`` reaches (what the methods read
    with ``ctx.stage_params``). A new stage read by a method must be added here."""
    import dataclasses

    from ..adaptation.config import AdaptConfig
    from ..evaluation.focal import STAGE as FOCAL_STAGE
    from ..evaluation.methods.adapted import STAGE as ADAPT_STAGE
    from ..evaluation.methods.fusion import CONSISTENCY_STAGE, GUARD_STAGE, STREAM_SCALE_STAGE
    from ..evaluation.methods.fusion import STAGE as FUSION_STAGE
    from ..evaluation.methods.mapping import STAGE as MAP_STAGE
    from ..evaluation.methods.multi_view import (
        FILTER_STAGE,
        METHOD_PARAM,
        MULTI_VIEW_STAGE,
        NEIGHBOURS_STAGE,
        TV_STAGE,
    )
    from ..evaluation.methods.recorded import TOPICS as RECORDED_TOPICS
    from ..evaluation.methods.single_view import SIMULATED_STAGE
    from ..evaluation.mount import STAGE as MOUNT_STAGE
    from ..evaluation.time_offset import STAGE as TIME_OFFSET_STAGE
    from ..fusion.consistency import ConsistencyConfig
    from ..fusion.guard import GuardConfig
    from ..fusion.pipeline import FusionConfig
    from ..fusion.stream_scale import StreamScaleConfig
    from ..mapping.config import MapConfig
    from ..multiview.filter_config import FilterConfig
    from ..multiview.focal_check import FocalCheckConfig
    from ..multiview.mount_check import MountCheckConfig
    from ..multiview.neighbours import NeighbourConfig
    from ..multiview.semidense import MultiViewConfig
    from ..multiview.time_offset_check import TimeOffsetCheckConfig
    from ..multiview.tv import TVConfig
    from ..singleview.simulated import SimulatedPriorConfig

    def fields(cls: type) -> set[str]:
        return {f.name for f in dataclasses.fields(cls)}

    return {
        MULTI_VIEW_STAGE: fields(MultiViewConfig) | {METHOD_PARAM},
        FILTER_STAGE: fields(FilterConfig),
        FOCAL_STAGE: fields(FocalCheckConfig),
        TIME_OFFSET_STAGE: fields(TimeOffsetCheckConfig),
        MOUNT_STAGE: fields(MountCheckConfig),
        GUARD_STAGE: fields(GuardConfig),
        CONSISTENCY_STAGE: fields(ConsistencyConfig),
        STREAM_SCALE_STAGE: fields(StreamScaleConfig),
        ADAPT_STAGE: fields(AdaptConfig),
        MAP_STAGE: fields(MapConfig),
        NEIGHBOURS_STAGE: fields(NeighbourConfig),
        TV_STAGE: fields(TVConfig),
        FUSION_STAGE: fields(FusionConfig) | {'stage1_fraction', 'stage1', 'oracle_threshold'},
        SIMULATED_STAGE: fields(SimulatedPriorConfig),
        'recorded': {'bag', *RECORDED_TOPICS},
    }


def check_stage_overrides(overrides: Mapping[str, Mapping[str, object]]) -> None:
    """``evaluate --set STAGE.KEY=VALUE``: the stage exists and has the key."""
    if overrides:
        check_names(overrides, evaluation_stages(), 'stage')
