"""A TUM folder (camera.yaml, rgb.txt, depth.txt, groundtruth.txt) -> a rosbag2.

Frames are chosen as ``load_tum_sequence`` chooses them (poses interpolated at the colour
stamps decide which frames have a pose); the pose topic then carries groundtruth.txt's own
rows around those frames (``pose_samples``), as the motion capture published them.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

import numpy as np

from ..progress import progress
from .bag_layout import (
    CAMERA_INFO,
    DEFAULT_FRAME_IDS,
    DEFAULT_TOPICS,
    IMAGE,
    BagTopics,
    ConvertResult,
    FrameIds,
)
from .bag_writer import AtomicBagWriter
from .compressed import RAW_COLOUR, ColourFormat
from .messages import camera_info_msg, depth_image_msg, header_msg
from .pose_samples import SampleFeed, samples_spanning
from .tum import AssociatedFrame, associate, read_depth_file, read_rgb_file, read_tum_index

logger = logging.getLogger(__name__)

T = TypeVar('T')
R = TypeVar('R')

#: ``ConvertResult.pose_source`` of a TUM folder.
POSE_SOURCE = 'groundtruth.txt, its own samples'


def _prefetch(fn: Callable[[T], R], items: Iterable[T], depth: int = 4) -> Iterator[R]:
    """``map(fn, items)`` computed ``depth`` items ahead on threads (bounded memory, in order).

    Image decoding releases the GIL, so reading the next frames overlaps serialising this one.
    """
    with ThreadPoolExecutor(max_workers=2) as pool:
        pending: deque[Future[R]] = deque()
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) > depth:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


def tum_to_rosbag(
    src: str | Path,
    out: str | Path,
    *,
    storage: str = 'mcap',
    max_frames: int | None = None,
    topics: BagTopics = DEFAULT_TOPICS,
    frame_ids: FrameIds = DEFAULT_FRAME_IDS,
    depth_max_gap: float = 0.02,
    include_depth: bool = True,
    overwrite: bool = False,
    show_progress: bool = True,
    colour: ColourFormat = RAW_COLOUR,
) -> ConvertResult:
    """Convert a TUM folder (with camera.yaml and groundtruth.txt) into a rosbag2.

    ``colour`` chooses raw rgb8 images or CompressedImage (PNG/JPEG) on ``<rgb>/compressed``.

    Colour frames outside the ground truth (and, with ``include_depth``, without a depth image
    within ``depth_max_gap`` s) are not written; ``ConvertResult.dropped`` counts them. The
    pose topic holds groundtruth.txt's rows spanning the written frames, at their own stamps.
    """
    start = time.perf_counter()
    index = read_tum_index(src, require_depth=include_depth)
    assoc = associate(
        index, depth_max_gap, require_depth=include_depth, require_pose=True, max_frames=max_frames
    )
    if not assoc.frames:
        raise ValueError(f'{src}: no frame to write (dropped: {assoc.dropped})')
    assert index.groundtruth is not None  # require_pose=True
    samples = samples_spanning(index.groundtruth, assoc.frames[0].stamp_ns, assoc.frames[-1].stamp_ns)
    calib = index.calibration
    camera = calib.camera

    def decode(af: AssociatedFrame) -> tuple[AssociatedFrame, np.ndarray, np.ndarray | None]:
        rgb = read_rgb_file(af.rgb_file, camera)
        depth = read_depth_file(af.depth_file, camera) if include_depth else None
        return af, rgb, depth

    writer = AtomicBagWriter(out, storage, overwrite)
    ts = writer.typestore
    with writer:
        poses = SampleFeed(samples, topics, frame_ids, ts)
        frames = progress(assoc.frames, desc='convert', unit='frame', disable=not show_progress)
        for af, rgb, depth in _prefetch(decode, frames):
            stamp = af.stamp_ns
            for pose in poses.until(stamp):  # a pose at the image's stamp goes before it
                writer.write(*pose)
            hdr = header_msg(stamp, frame_ids.camera, kind=ts)
            rgb_topic, rgb_type, rgb_msg = colour.message(rgb, hdr, topics.rgb, kind=ts)
            writer.write(rgb_topic, rgb_type, stamp, rgb_msg)
            writer.write(topics.camera_info, CAMERA_INFO, stamp, camera_info_msg(calib, hdr, kind=ts))
            if depth is not None:
                writer.write(topics.depth, IMAGE, stamp, depth_image_msg(depth, hdr, kind=ts))
        for pose in poses.until():
            writer.write(*pose)
    result = ConvertResult(
        writer.out,
        len(assoc.frames),
        dict(writer.counts),
        assoc.dropped,
        POSE_SOURCE,
        time.perf_counter() - start,
    )
    logger.debug(
        'wrote %s: %d frames, %d pose samples in %.1f s',
        writer.out,
        result.frames,
        len(samples),
        result.seconds,
    )
    return result
