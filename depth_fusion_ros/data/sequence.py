"""In-memory posed RGB-D sequences: what every loader returns and every algorithm consumes."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from ..camera import PinholeCamera


def rgb_to_gray(rgb: np.ndarray) -> np.ndarray:
    """Grey image as float32 in [0, 1] (ITU-R 601 luma, as OpenCV)."""
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f'expected an HxWx3 RGB image, got shape {rgb.shape}')
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0


def resize_depth(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize a depth image with nearest-neighbour sampling so that invalid (NaN) pixels and
    depth edges are never blended into depths that exist nowhere in the scene."""
    if depth.shape == (height, width):
        return depth
    return cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)


@dataclass
class Frame:
    """One posed colour image of a sequence, with its ground-truth depth when known.

    ``rgb`` is undistorted and at the working resolution (``Sequence.camera``);
    ``depth`` is ground truth in metres (float32, NaN invalid), undistorted, at the
    ground-truth resolution (``Sequence.gt_camera``, 640x480 for TUM) because the paper
    compares at that resolution. ``pose`` is camera-to-world (4x4 float64).
    """

    index: int
    stamp: float
    rgb: np.ndarray
    pose: np.ndarray
    depth: np.ndarray | None = None
    _gray: np.ndarray | None = field(default=None, repr=False)

    @property
    def gray(self) -> np.ndarray:
        """Grey image (float32, [0, 1]) at the working resolution, computed once."""
        if self._gray is None:
            self._gray = rgb_to_gray(self.rgb)
        return self._gray


@dataclass
class Sequence:
    """A posed sequence: working-resolution camera, ground-truth camera and frames."""

    name: str
    camera: PinholeCamera
    frames: list[Frame]
    gt_camera: PinholeCamera | None = None
    dropped: dict[str, int] = field(default_factory=dict)
    #: The pose source as recorded, ``(stamps (M,) s, poses (M, 4, 4))``, that the frames' poses
    #: were interpolated from (groundtruth.txt, a bag's pose topic); ``None`` when the frames'
    #: own poses are all there is. Read again at other times by the time offset correction.
    pose_stream: tuple[np.ndarray, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def stamps(self) -> np.ndarray:
        return np.array([f.stamp for f in self.frames], dtype=np.float64)

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) camera-to-world poses."""
        return np.stack([f.pose for f in self.frames]) if self.frames else np.zeros((0, 4, 4))

    def with_poses(
        self, poses: np.ndarray, pose_stream: tuple[np.ndarray, np.ndarray] | None = None
    ) -> Sequence:
        """A copy whose frames have ``poses`` (N, 4, 4), as a calibration check's correction reads
        them (images and depth shared, not copied); its pose record ``pose_stream`` when given,
        else the same."""
        frames = [replace(f, pose=p) for f, p in zip(self.frames, poses, strict=True)]
        return replace(
            self, frames=frames, pose_stream=self.pose_stream if pose_stream is None else pose_stream
        )

    def gt_depth_working(self, i: int) -> np.ndarray | None:
        """Ground-truth depth of frame ``i`` at the working resolution (nearest sampling)."""
        depth = self.frames[i].depth
        if depth is None:
            return None
        return resize_depth(depth, self.camera.width, self.camera.height)
