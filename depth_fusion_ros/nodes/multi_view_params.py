"""``multi_view_node``'s topics and parameters: what a user wires and sets, apart from what
the node does with them (``multi_view_node.py``).

Why a module of its own: the declarations are a third of the node's file, and the
configuration tools (``config_yaml``, the bench, the docs' tables) read them without the node.
"""

from __future__ import annotations

from typing import Any

from ..multiview.descriptors import PATCH_OFFSETS
from ..multiview.neighbours import NeighbourConfig
from ..multiview.semidense import MultiViewConfig
from . import robot_inputs
from .check_process import CHECK_PROCESS_PARAMETERS
from .corrected_path import correction_parameters
from .focal_check_runner import FOCAL_CHECK_PARAMETERS
from .image_input import working_grid_parameters
from .mount_check_runner import MOUNT_CHECK_PARAMETERS
from .multi_view_filter import FILTER_PARAMETERS
from .params import ParamSpec, dataclass_specs, torch_device
from .pose_jump_params import pose_jump_parameters
from .time_offset_check_runner import TIME_OFFSET_CHECK_PARAMETERS

TOPIC_IMAGE = 'camera/rgb/image_color'
TOPIC_CAMERA_INFO = 'camera/rgb/camera_info'
TOPIC_POSE = 'camera/pose'
TOPIC_KEYFRAME_IMAGE = 'depth_fusion/keyframe/image'
TOPIC_KEYFRAME_CAMERA_INFO = 'depth_fusion/keyframe/camera_info'
TOPIC_DEPTH = 'depth_fusion/multi_view/depth'
TOPIC_SCORE = 'depth_fusion/multi_view/score'
#: Per-estimate depth standard deviation (m, 32FC1): the fusion guard's parallax evidence.
TOPIC_DEPTH_STD = 'depth_fusion/multi_view/depth_std'
#: The part of that std (m, 32FC1) every estimate of the keyframe shares: the bias of an
#: unverified focal length under its motion (the filter's, NaN where no estimate; the sweep
#: publishes none).
TOPIC_BIAS_STD = 'depth_fusion/multi_view/bias_std'
#: The keyframe's interpolated camera-to-world pose, with its stamp (map_node pairs it by stamp).
TOPIC_KEYFRAME_POSE = 'depth_fusion/keyframe/pose'
#: Latched: the multi-view method (``sweep`` or ``filter``); fusion_node's stage 1 follows it.
TOPIC_METHOD = 'depth_fusion/multi_view/method'

KEYFRAME_POLICIES = ('every_k', 'motion')

#: Descriptions of the ``MultiViewConfig`` fields exposed as ``multi_view.*`` parameters.
MULTI_VIEW_DESCRIPTIONS = {
    'min_depth': 'nearest depth hypothesis (m); the sweep is uniform in inverse depth',
    'max_depth': 'farthest depth hypothesis (m)',
    'num_samples': 'coarse inverse-depth samples per pixel',
    'refine_samples': 'fine samples on each side of the coarse minimum',
    'patch': "patch layout of the ZNCC cost: 'cross' (5 pixels) or 'box' (3x3)",
    'patch_stride': 'spacing (px) of the patch samples',
    'blur_sigma': 'Gaussian blur (px) before matching (noise, aliasing)',
    'noise_floor': 'grey-level noise floor of the ZNCC normalisation',
    'min_gradient': 'candidate pixels: grey gradient magnitude (grey in [0, 1] per px) at least this',
    'all_pixels': 'search every pixel instead of the high-gradient ones (dense, slower)',
    'min_view_fraction': 'a depth sample counts only if at least this fraction of the neighbours sees it',
    'max_cost': 'estimates whose best cost (1 - ZNCC) is above this are dropped',
    'second_min_exclusion': 'samples around the best ignored when looking for the second-best minimum',
    'chunk_elements': 'largest intermediate tensor in float elements (bounds memory)',
    'cuda_graph': 'on a GPU (device: cuda), replay the sweep from a CUDA graph captured once per image '
    'size and neighbour count: the same estimates without the launch overhead (method sweep only)',
}
MULTI_VIEW_LIMITS: dict[str, Any] = {
    'min_depth': (1e-3, None),
    'max_depth': (1e-3, None),
    'num_samples': (3, 4096),
    'refine_samples': (1, 64),
    'patch': tuple(sorted(PATCH_OFFSETS)),
    'patch_stride': (1, 16),
    'blur_sigma': (0.0, 20.0),
    'noise_floor': (0.0, 1.0),
    'min_gradient': (0.0, 10.0),
    'max_candidate_fraction': (0.0, 1.0),
    'min_view_fraction': (0.0, 1.0),
    'max_cost': (0.0, 2.0),
    'second_min_exclusion': (0, 1000),
    'chunk_elements': (1024, None),
}
#: Descriptions of the ``NeighbourConfig`` fields exposed as ``neighbours.*`` parameters.
NEIGHBOUR_DESCRIPTIONS = {
    'window': 'neighbour candidates: the last window posed frames received (kept undistorted in memory)',
    'scene_depth': 'typical scene depth (m) that turns a baseline into parallax and places the overlap test',
    'target_parallax': 'preferred baseline / scene depth of a neighbour',
    'min_parallax': 'below this baseline / depth a frame counts as zero baseline (pure rotation)',
    'max_parallax': 'above this baseline / depth a frame is not used (appearance changes too much)',
    'max_rotation_deg': 'largest rotation between keyframe and neighbour (degrees)',
    'min_overlap': 'smallest fraction of the keyframe that must be visible in a neighbour',
    'min_separation': 'chosen neighbours are at least this fraction of the target baseline apart',
}
NEIGHBOUR_LIMITS: dict[str, Any] = {
    'window': (1, 1000),
    'scene_depth': (1e-3, None),
    'target_parallax': (1e-6, None),
    'min_parallax': (0.0, None),
    'max_parallax': (0.0, None),
    'max_rotation_deg': (0.0, 180.0),
    'min_overlap': (0.0, 1.0),
    'min_separation': (0.0, None),
}
#: Stage 1 runs in the fusion node (``fusion.stage1_fraction``), on the score image published here.
MULTI_VIEW_SKIP = ('select_fraction',)

PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec(
        'device',
        'cpu',
        'torch device of the multi-view estimate (filter or sweep): cpu, cuda, ...',
        validate=torch_device,
    ),
    *working_grid_parameters(),
    *robot_inputs.PARAMETERS,
    ParamSpec(
        'keyframe_policy',
        'every_k',
        'every_k: every keyframe_every-th posed frame; motion: when the camera moved '
        'keyframe_min_translation or turned keyframe_min_rotation_deg since the last keyframe',
        choices=KEYFRAME_POLICIES,
    ),
    ParamSpec('keyframe_every', 5, 'every_k policy: posed frames 0, k, 2k, ... are keyframes', 1, 100000),
    ParamSpec(
        'keyframe_min_translation', 0.05, 'motion policy: translation (m) since the last keyframe', 0.0
    ),
    ParamSpec(
        'keyframe_min_rotation_deg',
        5.0,
        'motion policy: rotation (degrees) since the last keyframe',
        0.0,
        180.0,
    ),
    ParamSpec('num_neighbours', 4, 'overlapping past frames used per keyframe', 1, 32),
    ParamSpec(
        'min_neighbours',
        1,
        'a frame becomes a keyframe only when at least this many usable neighbours exist',
        1,
        32,
    ),
    ParamSpec(
        'image_qos_depth',
        30,
        'history depth of the image and camera_info subscriptions, or qos_depth if larger (30: one second '
        'at 30 Hz): a camera '
        "outpaces a busy node's callbacks for a moment (its first frames, a loaded machine), and images "
        'beyond the depth are lost before the node sees them (10: 6 of 37 in a live 2-core run)',
        1,
        1000,
    ),
    ParamSpec(
        'pose_qos_depth',
        100,
        'history depth of the pose subscription: poses are small and come in bursts from a SLAM, and a '
        'lost pose means interpolating over a longer interval',
        1,
        100000,
    ),
    ParamSpec('pose_buffer_size', 1000, 'poses kept for interpolation (oldest dropped first)', 2, 1000000),
    ParamSpec(
        'max_pose_gap',
        0.5,
        'seconds between two poses above which an image between them is not interpolated (tracking lost)',
        0.0,
    ),
    *pose_jump_parameters(
        'poses',
        'the images between them are dropped (pose_jump) and the frame history and filter start over '
        'after it',
    ),
    *correction_parameters('moves the buffered poses and starts the frame history and filter over'),
    ParamSpec(
        'pose_time_offset',
        0.0,
        "seconds: the pose source's clock minus the camera's (an image stamped t takes the pose "
        'interpolated at t + this); at 0.35 m/s, 10 ms out of sync moves a pose by a third of a '
        '30 Hz frame-to-frame baseline (docs/nodes.md "Clocks out of sync")',
        -1.0,
        1.0,
    ),
    ParamSpec(
        'pose_wait',
        1.0,
        'an image newer than the latest pose waits until the image stream is this many seconds (stamp '
        'time) ahead of it, or until no image nor pose arrived for this many seconds (end of the stream); '
        'then it is dropped as not posed (no_pose)',
        0.0,
    ),
    ParamSpec(
        'max_pending_images', 30, 'images waiting for their pose at most (oldest dropped first)', 1, 10000
    ),
    ParamSpec(
        'camera_info_wait',
        1.0,
        'images that come before the first camera_info wait for it until the image stream is this many '
        'seconds (stamp time) ahead of them (at most max_pending_images); then they are dropped as '
        'no_camera_info (0: drop at once)',
        0.0,
    ),
    *dataclass_specs(NeighbourConfig, 'neighbours', NEIGHBOUR_DESCRIPTIONS, NEIGHBOUR_LIMITS),
    *dataclass_specs(
        MultiViewConfig, 'multi_view', MULTI_VIEW_DESCRIPTIONS, MULTI_VIEW_LIMITS, skip=MULTI_VIEW_SKIP
    ),
    *FILTER_PARAMETERS,
    *FOCAL_CHECK_PARAMETERS,
    *TIME_OFFSET_CHECK_PARAMETERS,
    *MOUNT_CHECK_PARAMETERS,
    *CHECK_PROCESS_PARAMETERS,
)
