"""Per-keyframe evaluation context: the data a method needs and a memo shared by methods.

Several methods share expensive intermediates (``fused`` needs the multi-view result that
``multi_view`` also scores, and the single-view depth that ``single_view`` scores), so a
context memoises them per keyframe (``cached``) and per sequence (``shared``: models,
neighbour tables).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from ..camera import PinholeCamera
from ..data.sequence import Frame, Sequence

T = TypeVar('T')


@dataclass
class EvalOptions:
    """Options of one evaluation run (the CLI flags of ``depth-fusion evaluate``)."""

    frames: int | None = 100
    #: Every ``stride``-th frame of the first ``frames`` is a keyframe.
    stride: int = 1
    #: Explicit keyframe indices (overrides ``stride``), e.g. the frames the node graph chose.
    keyframes: list[int] | None = None
    #: The keyframes are the frames the recorded bag (``params['recorded']['bag']``) holds fused
    #: depth for, per sequence: the graph's methods and the offline ones scored on the same set.
    recorded_keyframes: bool = False
    seed: int = 0
    device: str = 'cpu'
    #: ``default`` (the shipped compact model), ``simulated`` (the simulated CNN prior),
    #: ``simulated_relative`` (it as inverse depth up to scale and shift), or a path to a
    #: checkpoint or an exported model (``.onnx``, ``.pt2``, TorchScript ``.pt``) with its YAML.
    single_view: str = 'default'
    #: ``offline``: neighbours from a window around the keyframe; ``online``: past frames only.
    neighbour_mode: str = 'offline'
    num_neighbours: int = 4
    width: int = 320
    height: int = 240
    #: Colour-camera calibration YAML per sequence name ('*': every sequence), for folders whose
    #: camera.yaml is the depth camera's (7-Scenes): see ``load_tum_sequence(rgb_calibration=)``.
    rgb_cameras: dict[str, str] = field(default_factory=dict)
    #: A rosbag2 sequence's topics (``data.recording.TOPIC_KEYWORDS`` names: ``image_topic``,
    #: ``camera_info_topic``, ``pose_topic``, ``depth_topic``); those not given are the layout
    #: ``depth-fusion convert`` writes. For a robot's own recording.
    topics: dict[str, str] = field(default_factory=dict)
    #: The camera optical frame in the poses' frame ``[x, y, z, qx, qy, qz, qw]`` (a body's
    #: odometry, as multi_view_node's ``camera_from_pose_frame``), for every sequence.
    camera_from_pose_frame: list[float] | None = None
    #: Per-stage overrides, e.g. ``{'multi_view': {'num_samples': 96}, 'fusion': {'mode': 'fast'}}``.
    params: dict[str, dict[str, Any]] = field(default_factory=dict)


def keyframe_indices(num_frames: int, options: EvalOptions) -> list[int]:
    """The keyframes of a run: ``options.keyframes`` within the sequence, else every ``stride``-th."""
    if options.keyframes is not None:
        return [i for i in options.keyframes if 0 <= i < num_frames]
    return list(range(0, num_frames, max(1, options.stride)))


class KeyframeContext:
    """One keyframe of a sequence under evaluation."""

    def __init__(self, sequence: Sequence, index: int, options: EvalOptions, shared: dict[str, Any]):
        self.sequence = sequence
        self.index = index
        self.options = options
        self.shared = shared
        self._memo: dict[str, Any] = {}

    @property
    def frame(self) -> Frame:
        return self.sequence.frames[self.index]

    @property
    def camera(self) -> PinholeCamera:
        """Working-resolution camera."""
        return self.sequence.camera

    @property
    def gt_depth(self) -> np.ndarray | None:
        """Ground truth at its own resolution (what metrics compare against)."""
        return self.frame.depth

    @property
    def gt_depth_working(self) -> np.ndarray | None:
        """Ground truth at the working resolution (oracle selection, simulated prior)."""
        return self.cached('gt_depth_working', lambda: self.sequence.gt_depth_working(self.index))

    def cached(self, key: str, factory: Callable[[], T]) -> T:
        """Compute ``factory()`` once per keyframe and key."""
        if key not in self._memo:
            self._memo[key] = factory()
        return self._memo[key]

    def shared_cached(self, key: str, factory: Callable[[], T]) -> T:
        """Compute ``factory()`` once per evaluation run and key (models, tables)."""
        if key not in self.shared:
            self.shared[key] = factory()
        return self.shared[key]

    def stage_params(self, stage: str) -> dict[str, Any]:
        return dict(self.options.params.get(stage, {}))


@dataclass
class SequenceContext:
    """A whole sequence after its keyframes ran: what a sequence-level method's ``finish`` sees."""

    sequence: Sequence
    keyframes: list[int]
    options: EvalOptions
    #: The same per-sequence memo as ``KeyframeContext.shared``.
    shared: dict[str, Any]
