"""``single_view_node``: image -> single-view CNN depth (32FC1, metres) with the source header.

By default it listens to the keyframes the multi-view node announces
(``depth_fusion/keyframe/image``, already undistorted on the working grid), so the network
runs only on keyframes and in parallel with the multi-view search. Pointed at a raw camera
topic (``input_rectified: false``), it undistorts and resizes each image with its
camera_info first.

The network is loaded once at start-up (``model``: the shipped compact model, a checkpoint,
or an ONNX / torch.export / TorchScript file with its metadata YAML) on ``device``;
inference runs on the worker thread so subscriptions are never stalled. The model's output
kind (``metric_depth``, ``inverse_depth``, ``relative_depth``) is published once on a
latched topic: the fusion node needs it to align non-metric outputs, and the depth image
itself cannot carry it.

With ``adapt`` on (``auto``: on for the project's own networks, off for exported ones), the
node also listens to the multi-view depth and score and the keyframe pose, and trains the
network on each keyframe in a training process of its own (``adaptation.process``; a
background thread when false; ``depth_fusion_ros.adaptation``, docs/adaptation.md).
Inference never waits for it: it uses the last accepted weights, swapped atomically.
``~/save_model`` (std_srvs/Trigger) and shutdown write them to ``adaptation.checkpoint``,
which ``model:`` loads next time.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from sensor_msgs.msg import CameraInfo, Image

from ..data import messages
from .announce import announce
from .base import DepthFusionNode
from .console import run_node
from .graph_events import GraphEvents
from .image_input import CameraInput, InputError, WorkingImage, header_stamp_ns, working_grid_parameters
from .info_wait import AwaitingCalibration
from .lens_topic import LensFollower
from .params import ParamSpec, torch_device
from .single_view_adaptation import ADAPTATION_PARAMETERS, NodeAdaptation, adaptation_wanted

NODE_NAME = 'single_view_node'

TOPIC_IMAGE = 'depth_fusion/keyframe/image'
TOPIC_CAMERA_INFO = 'depth_fusion/keyframe/camera_info'
TOPIC_DEPTH = 'depth_fusion/single_view/depth'
TOPIC_OUTPUT_KIND = 'depth_fusion/single_view/output_kind'

#: Images held for the first camera_info at most (a second of a 30 Hz camera; info_wait.py).
MAX_WAITING_IMAGES = 30

PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec(
        'model',
        'default',
        "single-view network: 'default' (the shipped compact model), a checkpoint file, or an exported "
        'model with its metadata YAML beside it: ONNX .onnx (ONNX Runtime), torch.export .pt2 or '
        'TorchScript .pt (local files only)',
    ),
    ParamSpec('device', 'cpu', 'torch device of the network: cpu, cuda, cuda:1, ...', validate=torch_device),
    ParamSpec(
        'input_rectified',
        True,
        'the input image is already undistorted (the keyframe topic): no camera_info needed, only '
        'resized to width x height; false: undistort and resize with camera_info (a raw camera topic)',
    ),
    *working_grid_parameters('; only for input_rectified: false'),
    ParamSpec(
        'camera_info_wait',
        1.0,
        'images that come before the first camera_info wait for it until the image stream is this many '
        f'seconds (stamp time) ahead of them (at most {MAX_WAITING_IMAGES}); then they are dropped as '
        'no_camera_info (0: drop at once); only for input_rectified: false',
        0.0,
    ),
    ParamSpec(
        'warmup',
        True,
        'run the network once at start-up, on the thread that runs every keyframe, so the first keyframe '
        'is not slow',
    ),
    *ADAPTATION_PARAMETERS,
)


@dataclass(frozen=True)
class _Job:
    image: WorkingImage
    received_at: float


class SingleViewNode(DepthFusionNode):
    """Subscribes to an image stream and publishes the network's depth for each image."""

    def __init__(self, node_name: str = NODE_NAME, **kwargs: Any) -> None:
        super().__init__(node_name, PARAMETERS, **kwargs)
        p = self.params
        self.events = GraphEvents(self)
        self.camera_input = CameraInput.from_parameters(p, rectified=bool(p['input_rectified']))
        self.awaiting_info = AwaitingCalibration(float(p['camera_info_wait']), MAX_WAITING_IMAGES)
        self._subscribe_inputs()
        try:
            self.predictor = self._load_predictor(str(p['model']), str(p['device']))
        except (ValueError, FileNotFoundError) as exc:  # a device or a model this machine lacks
            raise type(exc)(f'{self.get_name()}: {exc}') from None
        self.output_kind = str(getattr(self.predictor, 'output_kind', 'metric_depth'))
        self._stamps = self.stamp_guard('image')
        self._depth_pub = self.create_publisher(Image, TOPIC_DEPTH, self.output_qos)
        self._kind_pub = announce(self, TOPIC_OUTPUT_KIND, self.output_kind)
        warm = self._warm_up if p['warmup'] else None
        self.worker = self.make_worker('single_view', self._process, start=warm)
        self.worker.started.wait()  # ready means warm: the first keyframe is not slow
        self.adaptation: NodeAdaptation | None = None
        if adaptation_wanted(p):
            self.adaptation = NodeAdaptation(self, self.predictor)
        self.get_logger().info(
            f'single-view model {p["model"]!r} ({self.output_kind}) on {p["device"]}; '
            f'{self.resolve_topic_name(TOPIC_IMAGE)} -> {self.resolve_topic_name(TOPIC_DEPTH)}'
        )
        # With adaptation on, warm only once training can take keyframes (NodeAdaptation._on_warm).
        self.events.ready(warm=self.adaptation is None)

    def _subscribe_inputs(self) -> None:
        """Subscribe before the network loads (~1 s), so keyframes that come meanwhile wait.

        The multi-view node publishes its first keyframes as soon as a stream begins; a live
        stream that begins while this node still loads its network would otherwise lose them
        (the fusion node then drops them as ``unpaired``). DDS keeps what arrives in the
        subscription's history (``qos_depth``) until the node spins, which it does only after
        this constructor has loaded and warmed the network: the callbacks never see a node
        without its predictor, and the queued keyframes are processed first.
        """
        self.subscribe(CameraInfo, TOPIC_CAMERA_INFO, self._on_camera_info, self.input_qos)
        self.subscribe(Image, TOPIC_IMAGE, self._on_image, self.input_qos)
        #: A raw camera: the lens the multi-view node takes is taken here too (lens_topic.py).
        self.lens = None if self.camera_input.rectified else LensFollower(self, self.camera_input)

    def _warm_up(self) -> None:
        """The network once on a blank working image, on the worker's thread: the thread that
        runs every keyframe. Run on the constructor's thread (until 2026-11-30), it left the
        thread's own first-call costs to the first live keyframe: on a GPU, the cuDNN and
        cuBLAS handles torch keeps per thread. Whether those are why a real-time stream on an
        H200 lost its first second is not measured yet (docs/performance.md "GPU")."""
        height, width = int(self.params['height']), int(self.params['width'])
        self.predictor.predict(np.zeros((height, width, 3), dtype=np.uint8))

    def _load_predictor(self, spec: str, device: str) -> Any:
        from ..singleview.predictor import load_predictor

        return load_predictor(spec, device=device)

    def _on_camera_info(self, msg: CameraInfo) -> None:
        self.stats.received('camera_info')
        try:
            self.camera_input.update(msg)
        except InputError as exc:
            self.stats.dropped(exc.reason, str(exc))
            return
        for _, image_msg in self.awaiting_info.release():
            self._on_image(image_msg, counted=True)

    def _on_image(self, msg: Image, counted: bool = False) -> None:
        received_at = time.monotonic()
        if not counted:
            self.stats.received('image')
        if self.lens is not None:
            self.lens.before_image(header_stamp_ns(msg))
        try:
            image = self.camera_input.working_image(msg)
            if self._stamps.check(image.stamp_ns):
                self.note_stream_restart('image', image.stamp_ns, 'its keyframes are processed as they come')
        except InputError as exc:
            if exc.reason == 'no_camera_info':  # a raw camera whose camera_info comes a moment later
                for _ in self.awaiting_info.hold(header_stamp_ns(msg), msg):
                    self.stats.dropped(exc.reason, str(exc))
                return
            self.stats.dropped(exc.reason, str(exc))
            return
        self.worker.submit(_Job(image, received_at))
        if self.adaptation is not None:
            self.adaptation.on_keyframe_image(image, calibrated=self.camera_input.calibration is not None)

    def current_predictor(self) -> Any:
        """The predictor to run now: the latest accepted adapted weights, or the loaded model."""
        return self.adaptation.slot.get()[0] if self.adaptation is not None else self.predictor

    def _process(self, job: _Job) -> None:
        depth = np.asarray(self.current_predictor().predict(job.image.rgb), dtype=np.float32)
        if depth.shape != job.image.rgb.shape[:2]:
            raise ValueError(f'the network returned {depth.shape}, expected {job.image.rgb.shape[:2]}')
        self._depth_pub.publish(messages.depth_image_msg(depth, job.image.header, kind=messages.RCLPY))
        self.stats.published('depth')
        self.stats.processed(time.monotonic() - job.received_at)

    def diagnostic_extra(self) -> dict[str, Any]:
        return {'model': self.params['model'], 'output kind': self.output_kind}

    def destroy_node(self) -> None:
        """Stop adapting and write the adapted weights (``adaptation.checkpoint``), then stop."""
        if self.adaptation is not None and not self._destroyed:
            self.adaptation.shutdown()
        super().destroy_node()


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point: ``single_view_node --ros-args --params-file config/depth_fusion.yaml``."""
    return run_node(SingleViewNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
