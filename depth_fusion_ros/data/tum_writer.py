"""Write posed RGB-D frames as a TUM RGB-D folder (+ ``camera.yaml``), atomically.

Layout (what ``data/tum.py`` reads and the TUM tools expect)::

    OUT/rgb/<stamp>.png        8-bit colour
    OUT/depth/<stamp>.png      16-bit depth, metres * 5000, 0 = invalid or beyond 13.1 m
    OUT/rgb.txt, depth.txt     '# ...' header, then 'timestamp filename'
    OUT/groundtruth.txt        'timestamp tx ty tz qx qy qz qw' (camera-to-world)
    OUT/camera.yaml            ROS camera-info YAML (plumb_bob, zero distortion)
    OUT/SOURCE.md              how the folder was made
    OUT/.written_by_depth_fusion_ros   the mark that lets ``overwrite`` replace this folder

Frames are written into a temporary sibling folder that is renamed onto ``OUT`` at the
end, so an interrupted run never leaves a half-written sequence that looks complete.
"""

from __future__ import annotations

import itertools
import logging
import os
import shutil
import tempfile
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from ..camera import PinholeCamera
from ..geometry import pose_to_tq, validate_pose
from . import replaceable

log = logging.getLogger(__name__)

#: TUM depth PNG scale: 5000 units per metre.
DEPTH_SCALE = 5000.0
#: Largest depth a uint16 PNG holds at that scale (m); farther depths are written as 0.
MAX_DEPTH = 65535 / DEPTH_SCALE


def depth_to_png16(depth: np.ndarray, scale: float = DEPTH_SCALE) -> np.ndarray:
    """uint16 TUM depth: ``round(depth * scale)``, 0 where NaN, <= 0 or beyond the range."""
    depth = np.asarray(depth, dtype=np.float64)
    valid = np.isfinite(depth) & (depth > 0) & (depth * scale <= 65535.0)
    out = np.zeros(depth.shape, dtype=np.uint16)
    out[valid] = np.rint(depth[valid] * scale).astype(np.uint16)
    return out


def png16_to_depth(raw: np.ndarray, scale: float = DEPTH_SCALE) -> np.ndarray:
    """float32 metres from a TUM uint16 depth image, NaN where 0."""
    depth = raw.astype(np.float32) / np.float32(scale)
    depth[raw == 0] = np.nan
    return depth


def camera_info_yaml(camera: PinholeCamera, camera_name: str) -> str:
    """ROS camera-info YAML (the keys of ``camera_calibration_parsers``), zero distortion."""
    K = [camera.fx, 0.0, camera.cx, 0.0, camera.fy, camera.cy, 0.0, 0.0, 1.0]
    P = [camera.fx, 0.0, camera.cx, 0.0, 0.0, camera.fy, camera.cy, 0.0, 0.0, 0.0, 1.0, 0.0]

    def row(values: list[float]) -> str:
        return '[' + ', '.join(repr(float(v)) for v in values) + ']'

    return (
        f'image_width: {camera.width}\n'
        f'image_height: {camera.height}\n'
        f'camera_name: {camera_name}\n'
        f'camera_matrix:\n  rows: 3\n  cols: 3\n  data: {row(K)}\n'
        'distortion_model: plumb_bob\n'
        'distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0.0, 0.0, 0.0, 0.0, 0.0]\n'
        'rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]\n'
        f'projection_matrix:\n  rows: 3\n  cols: 4\n  data: {row(P)}\n'
    )


def format_stamp(stamp: float) -> str:
    """TUM stamp text: seconds with microseconds (as the TUM files)."""
    return f'{stamp:.6f}'


def _check_stamps(stamps: np.ndarray) -> list[str]:
    texts = [format_stamp(s) for s in stamps]
    if not np.all(np.isfinite(stamps)):
        raise ValueError('write_tum_folder: stamps contain NaN or infinite values')
    if any(float(b) <= float(a) for a, b in itertools.pairwise(texts)):
        raise ValueError('write_tum_folder: stamps must be strictly increasing at microsecond resolution')
    return texts


def _check_frame(i: int, rgb: np.ndarray, depth: np.ndarray, camera: PinholeCamera) -> None:
    shape = (camera.height, camera.width)
    if rgb.dtype != np.uint8 or rgb.shape != (*shape, 3):
        raise ValueError(
            f'write_tum_folder: frame {i}: rgb must be {shape[0]}x{shape[1]}x3 uint8, '
            f'got {rgb.shape} {rgb.dtype}'
        )
    if depth.shape != shape:
        raise ValueError(
            f'write_tum_folder: frame {i}: depth must be {shape[0]}x{shape[1]}, got {depth.shape}'
        )


def _write_index(path: Path, header: str, source: str, stamps: list[str], folder: str) -> None:
    lines = [f'# {header}', f"# file: '{source}'", '# timestamp filename']
    lines += [f'{s} {folder}/{s}.png' for s in stamps]
    path.write_text('\n'.join(lines) + '\n')


def _write_groundtruth(path: Path, source: str, stamps: list[str], poses: np.ndarray) -> None:
    lines = ['# ground truth trajectory', f"# file: '{source}'", '# timestamp tx ty tz qx qy qz qw']
    for s, T in zip(stamps, poses, strict=True):
        t, q = pose_to_tq(T)
        lines.append(s + ' ' + ' '.join(f'{x:.9f}' for x in (*t, *q)))
    path.write_text('\n'.join(lines) + '\n')


#: The file :func:`write_tum_folder` leaves in every folder it writes: what it may replace.
WRITTEN_MARK = '.written_by_depth_fusion_ros'
#: What the synthetic sequences' SOURCE.md said before the mark existed.
_OLD_SYNTH_SOURCE = 'Rendered by depth_fusion_ros'


def not_written_here(path: Path) -> str | None:
    """Why ``overwrite`` must keep the folder ``path`` (``None``: this writer made it, by its
    mark or, for folders from before the mark, a synthetic sequence's SOURCE.md)."""
    if (path / WRITTEN_MARK).is_file():
        return None
    source = path / 'SOURCE.md'
    if source.is_file() and _OLD_SYNTH_SOURCE in source.read_text(errors='replace')[:2000]:
        return None
    return f'exists and is not a sequence depth-fusion wrote (no {WRITTEN_MARK})'


def check_replaceable(out_dir: Path, overwrite: bool) -> None:
    """The rule of :mod:`.replaceable` with this writer's mark."""
    replaceable.check_replaceable(out_dir, overwrite, not_written_here)


def _replace_dir(tmp: Path, out_dir: Path, overwrite: bool) -> None:
    """Move the finished ``tmp`` folder onto ``out_dir`` (removing an old one if allowed)."""
    if out_dir.exists():
        check_replaceable(out_dir, overwrite)  # again: it may have changed while we wrote
        trash = out_dir.with_name(f'.{out_dir.name}.old-{os.getpid()}')
        out_dir.rename(trash)
        tmp.rename(out_dir)
        shutil.rmtree(trash)
    else:
        tmp.rename(out_dir)


def write_tum_folder(
    out_dir: str | Path,
    camera: PinholeCamera,
    stamps: np.ndarray,
    rgbs: Iterable[np.ndarray],
    depths: Iterable[np.ndarray],
    poses: np.ndarray,
    *,
    name: str = 'sequence',
    source_md: str | None = None,
    overwrite: bool = False,
    pose_stamps: np.ndarray | None = None,
) -> Path:
    """Write a TUM-layout folder and return its path.

    ``stamps`` (N,) strictly increasing seconds; ``rgbs`` and ``depths`` are iterables of N
    images (consumed lazily, so a generator can render and write frame by frame without
    holding the sequence in memory): rgb HxWx3 uint8 in RGB order, depth HxW float metres
    (NaN = invalid); ``poses`` (N, 4, 4) camera-to-world, stamped as the images unless
    ``pose_stamps`` (M,) gives the pose source's own stamps (then ``poses`` is (M, 4, 4): a pose
    source on another clock or rate). ``name`` is the camera name in
    ``camera.yaml``; ``source_md`` the text of ``SOURCE.md``. An existing ``out_dir`` raises
    ``ValueError`` unless ``overwrite``.
    """
    out_dir = Path(out_dir)
    stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
    poses = np.asarray(poses, dtype=np.float64)
    own = stamps if pose_stamps is None else np.asarray(pose_stamps, dtype=np.float64).reshape(-1)
    if poses.shape != (len(own), 4, 4):
        raise ValueError(f'write_tum_folder: {len(own)} pose stamps but poses have shape {poses.shape}')
    for i, T in enumerate(poses):
        validate_pose(T, f'write_tum_folder: pose {i}')
    texts = _check_stamps(stamps)
    pose_texts = texts if pose_stamps is None else _check_stamps(own)
    check_replaceable(out_dir, overwrite)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f'.{out_dir.name}.tmp-', dir=out_dir.parent))
    try:
        (tmp / 'rgb').mkdir()
        (tmp / 'depth').mkdir()
        count = 0
        for i, (rgb, depth) in enumerate(zip(rgbs, depths, strict=False)):
            if i >= len(texts):
                raise ValueError(f'write_tum_folder: more images than the {len(texts)} stamps')
            _check_frame(i, rgb, depth, camera)
            cv2.imwrite(str(tmp / 'rgb' / f'{texts[i]}.png'), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(tmp / 'depth' / f'{texts[i]}.png'), depth_to_png16(depth))
            count += 1
        if count != len(texts):
            raise ValueError(f'write_tum_folder: {len(texts)} stamps but only {count} rgb/depth images')
        _write_index(tmp / 'rgb.txt', 'color images', out_dir.name, texts, 'rgb')
        _write_index(tmp / 'depth.txt', 'depth maps', out_dir.name, texts, 'depth')
        _write_groundtruth(tmp / 'groundtruth.txt', out_dir.name, pose_texts, poses)
        (tmp / 'camera.yaml').write_text(camera_info_yaml(camera, name))
        (tmp / 'SOURCE.md').write_text(source_md if source_md is not None else f'# {name}\n')
        (tmp / WRITTEN_MARK).write_text(
            'written by depth_fusion_ros (data/tum_writer.py): --overwrite may replace it\n'
        )
        tmp.chmod(0o755)  # mkdtemp makes it private; the result is an ordinary folder
        _replace_dir(tmp, out_dir, overwrite)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    log.info('wrote %d frames to %s', count, out_dir)
    return out_dir
