"""Does the bag feed the graph? The topics ``multi_view_node`` needs, checked before anything starts.

Why: a bag without the pose topic used to "succeed" (exit 0, an empty recording, no warning):
the images were never posed, so no keyframe was ever announced and the runner had nothing to
wait for. The graph needs, after the replayer's ``topics`` selection and ``remap``:

* the image (``/camera/rgb/image_color``, or its ``/compressed`` image_transport topic; an
  explicit ``multi_view_node.image_transport`` decides which one);
* the camera_info, unless ``multi_view_node.camera_intrinsics`` is set (not all zero);
* the pose (any message type: the node's ``pose_type`` decides what it accepts).

:func:`check_inputs` raises :class:`MissingInputError` naming what is missing (one line), or
with ``allow_missing`` returns the list so the run can say what it runs without.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any

from .options import RunOptions
from .param_merge import param_from_file, read_params_file
from .topics import REPLAYER, TOPIC_CAMERA_INFO, TOPIC_IMAGE, TOPIC_POSE

log = logging.getLogger(__name__)

MULTI_VIEW = 'multi_view_node'
COMPRESSED_SUFFIX = '/compressed'


class MissingInputError(ValueError):
    """The bag lacks a topic the graph needs (a ``ValueError``: the CLI prints it in one line)."""


def _param(options: RunOptions, params: Mapping[str, Mapping[str, Any]], node: str, name: str) -> Any:
    """The value ``node`` runs with: ``--set`` first, then the params file (None: the default)."""
    if name in options.overrides.get(node, {}):
        return options.overrides[node][name]
    return param_from_file(params, node, name)


def _non_empty(values: Any) -> list[str]:
    if isinstance(values, str):
        values = [values]
    return [str(v) for v in values or [] if str(v)]


def published_topics(options: RunOptions, bag_topics: Sequence[str]) -> set[str]:
    """Topics the replayer will publish: its ``topics`` selection, renamed by its ``remap``."""
    params = read_params_file(options.params_file)
    selected = _non_empty(_param(options, params, REPLAYER[0], 'topics')) or list(bag_topics)
    remaps = {}
    for item in _non_empty(_param(options, params, REPLAYER[0], 'remap')):
        src, sep, dst = item.partition(':=')
        if sep:
            remaps[src] = dst
    return {remaps.get(t, t) for t in selected if t in bag_topics}


def missing_inputs(options: RunOptions, bag_topics: Sequence[str]) -> list[str]:
    """What the graph needs and the bag (as played) does not give, as readable phrases."""
    params = read_params_file(options.params_file)
    played = published_topics(options, bag_topics)
    missing = []
    transport = _param(options, params, MULTI_VIEW, 'image_transport')
    raw, compressed = TOPIC_IMAGE, TOPIC_IMAGE + COMPRESSED_SUFFIX
    if transport == 'compressed':
        if compressed not in played:
            missing.append(f'the image topic {compressed} (multi_view_node.image_transport is compressed)')
    elif transport == 'raw':
        if raw not in played:
            missing.append(f'the image topic {raw} (multi_view_node.image_transport is raw)')
    elif raw not in played and compressed not in played:
        missing.append(f'the image topic {raw} (or {compressed})')
    intrinsics = _param(options, params, MULTI_VIEW, 'camera_intrinsics')
    has_intrinsics = bool(intrinsics) and any(float(v) != 0.0 for v in intrinsics)
    if TOPIC_CAMERA_INFO not in played and not has_intrinsics:
        missing.append(
            f'the camera_info topic {TOPIC_CAMERA_INFO} (or set multi_view_node.camera_intrinsics)'
        )
    if TOPIC_POSE not in played:
        missing.append(f'the pose topic {TOPIC_POSE}' + (_TF_HINT if '/tf' in bag_topics else ''))
    return missing


#: A bag posed only on ``/tf``: the nodes cannot subscribe to it (``tf2_msgs`` is not on pip),
#: and ``depth-fusion convert`` writes the chain as a pose topic.
_TF_HINT = (
    ' (its poses are on /tf, which the nodes cannot read: tf2_msgs is not on pip; '
    'depth-fusion convert BAG OUT --tf-world-frame FRAME writes them as a pose topic)'
)


def check_inputs(options: RunOptions, bag_topics: Sequence[str]) -> list[str]:
    """Raise :class:`MissingInputError` when the bag lacks a needed topic, unless
    ``options.allow_missing`` (then warn once and return what is missing)."""
    missing = missing_inputs(options, bag_topics)
    if not missing:
        return []
    has = ', '.join(sorted(bag_topics)) or 'no topics'
    if not options.allow_missing:
        raise MissingInputError(
            f'{options.bag} lacks {"; ".join(missing)} (it has: {has}); '
            'remap it with --set bag_replayer.remap=[FROM:=TO], or run anyway with --allow-missing'
        )
    log.warning('running without %s (--allow-missing): expect no fused output', '; '.join(missing))
    return missing
