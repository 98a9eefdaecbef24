"""Parameters given to a node that it does not declare: said, never silently ignored.

rclpy (like rclcpp) ignores a ``-p name:=value`` or a params-file entry the node never
declares. A misspelt ``-p fusion.mod:=exact`` would run the default mode without a word, the
worst kind of wrong for a user who believes the log. So each node, once it has declared its
parameters, warns in one line about every given name it does not know, with the closest
name it does declare. A name another depth_fusion node declares is not a typo: a ``/**:``
section applies to every node, so each gets the others' parameters too (said at debug
level only). ``qos_overrides.*`` belong to rclpy's own QoS overriding and are left alone.
"""

from __future__ import annotations

import difflib
import logging
from typing import Any

log = logging.getLogger(__name__)

#: Parameters every rclpy node declares or accepts besides its own table (the CLI's checks).
ROS_NODE_PARAMETERS = frozenset({'use_sim_time', 'start_type_description_service'})
#: Prefixes of names rclpy declares itself when asked (QoS overriding options).
ROS_PARAMETER_PREFIXES = ('qos_overrides.',)


def node_parameter_names() -> dict[str, set[str]]:
    """``{node: parameter names}`` of every node of the package (their tables; imported only
    when needed: a node module imports torch). ``run --set`` / ``--params`` check against it."""
    from .config_yaml import available_nodes, node_parameters

    return {node: {spec.name for spec in node_parameters(node)} for node in available_nodes()}


def undeclared_overrides(node: Any) -> list[str]:
    """Names given to ``node`` (command line, params file, ``parameter_overrides``) that it has
    not declared, sorted."""
    given = getattr(node, '_parameter_overrides', None) or {}
    return sorted(
        name for name in given if not node.has_parameter(name) and not name.startswith(ROS_PARAMETER_PREFIXES)
    )


def warn_ignored(node: Any, declared: list[str]) -> list[str]:
    """Log one warning per name given to ``node`` that no depth_fusion node declares (with the
    closest of ``declared``); returns those names."""
    names = undeclared_overrides(node)
    if not names:
        return []
    try:
        own = node.get_name()
        elsewhere = {n for other, names in node_parameter_names().items() if other != own for n in names}
    except ImportError as exc:  # a partial install: every unknown name is reported
        log.debug('parameter tables of the other nodes not available: %s', exc)
        elsewhere = set()
    typos = [name for name in names if name not in elsewhere]
    for name in typos:
        close = difflib.get_close_matches(name, declared, n=1, cutoff=0.6)
        hint = f'did you mean {close[0]!r}?' if close else 'config/depth_fusion.yaml lists every parameter'
        node.get_logger().warning(f'{name!r} is not a parameter of {node.get_name()}: ignored ({hint})')
    others = [name for name in names if name in elsewhere]
    if others:
        node.get_logger().debug(f"other nodes' parameters given here too (a '/**' section?): {others}")
    return typos
