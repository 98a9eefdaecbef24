"""Topic names given on the command line, checked before any node starts.

``depth-fusion launch --pose bad//topic`` passed the name to ``multi_view_node`` as a remap;
rcl refused it inside the forked node (a Python traceback from ``rclpy.init``) after the
three nodes had started, and the launch ended with "multi_view_node exited early". The name
is checked here with rclpy's own rules, as the node would expand it, and refused in one line.
"""

from __future__ import annotations

import re


def check_topic_name(option: str, name: str, node: str = 'multi_view_node') -> str:
    """``name`` when it is a valid ROS topic name once expanded for ``node`` (relative names
    and ``~`` are allowed, as in a remap); a ``ValueError`` naming ``option`` otherwise."""
    from rclpy.exceptions import InvalidTopicNameException
    from rclpy.expand_topic_name import expand_topic_name
    from rclpy.validate_full_topic_name import validate_full_topic_name

    from ..nodes.rcl_errors import rcl_message

    try:
        validate_full_topic_name(expand_topic_name(name, node, '/'))
    except (InvalidTopicNameException, ValueError) as exc:
        line = rcl_message(exc)
        rule = re.search(r'topic name (?:token )?must [^:]*', line)  # the rule alone, once
        reason = rule.group(0) if rule else line
        raise ValueError(f'{option} {name!r} is not a valid ROS topic name ({reason})') from None
    return name
