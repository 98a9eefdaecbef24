"""Topic names and node table of the graph ``depth-fusion run`` starts.

They restate the node modules' relative names (a test checks they agree) so that the process
mode never imports torch in the runner.
"""

from __future__ import annotations

TOPIC_IMAGE = '/camera/rgb/image_color'
TOPIC_CAMERA_INFO = '/camera/rgb/camera_info'
TOPIC_POSE = '/camera/pose'
TOPIC_GT_DEPTH = '/camera/depth/image'
TOPIC_KEYFRAME_IMAGE = '/depth_fusion/keyframe/image'
TOPIC_SINGLE_DEPTH = '/depth_fusion/single_view/depth'
TOPIC_MV_DEPTH = '/depth_fusion/multi_view/depth'
TOPIC_FUSED_DEPTH = '/depth_fusion/fused/depth'
TOPIC_FUSED_CONFIDENCE = '/depth_fusion/fused/confidence'
TOPIC_FUSED_CAMERA_INFO = '/depth_fusion/fused/camera_info'
TOPIC_KEYFRAME_POSE = '/depth_fusion/keyframe/pose'
TOPIC_POSING_TRANSFORM = '/depth_fusion/posing/camera_from_pose_frame'
TOPIC_POSING_TIME = '/depth_fusion/posing/pose_time'
TOPIC_REPOSED_KEYFRAMES = '/depth_fusion/posing/reposed_keyframes'

IMAGE = 'sensor_msgs/msg/Image'
CAMERA_INFO = 'sensor_msgs/msg/CameraInfo'
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
TRANSFORM_STAMPED = 'geometry_msgs/msg/TransformStamped'
TIME_REFERENCE = 'sensor_msgs/msg/TimeReference'
PATH = 'nav_msgs/msg/Path'

#: The posing multi_view_node says (nodes/posing.py): latched, so a late map_node hears it.
POSING_TOPICS: dict[str, str] = {
    TOPIC_POSING_TRANSFORM: TRANSFORM_STAMPED,
    TOPIC_POSING_TIME: TIME_REFERENCE,
    TOPIC_REPOSED_KEYFRAMES: PATH,
}
#: What ``--record`` writes: enough to evaluate the fused depth against the bag's ground truth,
#: and, with the keyframe poses and the posing they were posed with, to map it again later
#: (the posing topics recorded transient local, so a replay of the recording latches them too).
RECORDED_TOPICS: dict[str, str] = {
    TOPIC_FUSED_DEPTH: IMAGE,
    TOPIC_FUSED_CONFIDENCE: IMAGE,
    TOPIC_FUSED_CAMERA_INFO: CAMERA_INFO,
    TOPIC_MV_DEPTH: IMAGE,
    TOPIC_SINGLE_DEPTH: IMAGE,
    TOPIC_KEYFRAME_IMAGE: IMAGE,
    TOPIC_KEYFRAME_POSE: POSE_STAMPED,
    **POSING_TOPICS,
}
#: A keyframe is complete when all of these carry its stamp.
FUSED_OUTPUTS = (TOPIC_FUSED_DEPTH, TOPIC_FUSED_CONFIDENCE, TOPIC_FUSED_CAMERA_INFO)
#: Where a keyframe can get stuck, in pipeline order (named in the flush warning).
STAGES = ((TOPIC_MV_DEPTH, 'multi-view depth'), (TOPIC_SINGLE_DEPTH, 'single-view depth'))

#: node name -> (console script, module); the order nodes are started in.
GRAPH_NODES: dict[str, tuple[str, str]] = {
    'single_view_node': ('single_view_node', 'depth_fusion_ros.nodes.single_view_node'),
    'multi_view_node': ('multi_view_node', 'depth_fusion_ros.nodes.multi_view_node'),
    'fusion_node': ('fusion_node', 'depth_fusion_ros.nodes.fusion_node'),
}
#: Started with ``--map`` / ``--save-map``: integrates the fused keyframes into a TSDF map.
MAP_NODE = ('map_node', 'depth_fusion_ros.nodes.map_node')
REPLAYER = ('bag_replayer', 'depth_fusion_ros.nodes.bag_replayer')
RECORDER_NODE = 'depth_fusion_recorder'

#: Topics every rclpy node has, which say nothing about a node being set up.
STANDARD_TOPICS = frozenset({'/rosout', '/parameter_events'})


def graph_nodes(with_map: bool) -> dict[str, tuple[str, str]]:
    """The nodes a run starts, in start order: the fusion graph, and ``map_node`` with a map."""
    nodes = dict(GRAPH_NODES)
    if with_map:
        nodes[MAP_NODE[0]] = MAP_NODE
    return nodes
