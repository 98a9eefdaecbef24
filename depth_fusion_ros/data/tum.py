"""TUM RGB-D folders: index files, ground truth, association, and the ``Sequence`` loader.

A TUM folder holds ``rgb.txt`` and ``depth.txt`` ('timestamp filename' lines),
``groundtruth.txt`` ('timestamp tx ty tz qx qy qz qw', camera-to-world) and, for this project,
a ``camera.yaml`` in the ROS camera-info YAML format with the colour camera's calibration.

Reading is split in two so the bag converter never decodes an image twice:

* ``read_tum_index(path)`` parses the text files and ``camera.yaml`` only;
* ``associate(index, ...)`` pairs every colour frame with the nearest depth frame and the
  ground-truth pose interpolated at the colour stamp, dropping (and counting) frames that have
  neither;
* ``load_tum_sequence(path, ...)`` does both, then reads, undistorts and resizes the images.

Stamps are parsed from the text into exact integer nanoseconds (``1305031102.175304`` ->
``1305031102175304000``): float seconds at that magnitude lose ~100 ns, which would make bag
stamps differ from the files they came from.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation
from pathlib import Path

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from ..camera import PinholeCamera
from ..geometry import interpolate_poses
from .depth_registration import register_depth
from .sequence import Frame, Sequence
from .undistort import CameraCalibration, Undistorter, check_distortion

logger = logging.getLogger(__name__)

#: TUM depth PNGs store depth * 5000 as uint16 (0 = no measurement).
TUM_DEPTH_SCALE = 5000.0
NS_PER_SEC = 1_000_000_000

__all__ = [
    'TUM_DEPTH_SCALE',
    'AssociatedFrame',
    'Association',
    'CameraCalibration',
    'TumIndex',
    'TumList',
    'TumTrajectory',
    'associate',
    'load_tum_sequence',
    'nearest_stamps',
    'parse_stamp_ns',
    'read_camera_yaml',
    'read_depth_file',
    'read_groundtruth',
    'read_rgb_file',
    'read_tum_index',
    'read_tum_list',
]


# --------------------------------------------------------------------------- text files


@dataclass(frozen=True)
class TumList:
    """One of ``rgb.txt`` / ``depth.txt``, sorted by stamp."""

    path: Path
    stamps_ns: np.ndarray  # (N,) int64
    files: list[Path]  # absolute paths, same order

    def __len__(self) -> int:
        return len(self.files)


@dataclass(frozen=True)
class TumTrajectory:
    """``groundtruth.txt``: camera-to-world poses, sorted by stamp."""

    path: Path
    stamps_ns: np.ndarray  # (N,) int64
    poses: np.ndarray  # (N, 4, 4) float64

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @classmethod
    def from_samples(
        cls, label: str | Path, stamps_ns: Iterable[int], poses: Iterable[np.ndarray]
    ) -> TumTrajectory:
        """A pose source's samples as a trajectory: sorted by stamp (stably), the first of equal
        stamps kept (a bag may repeat one; the interpolation needs them strictly increasing)."""
        stamps = np.asarray(list(stamps_ns), dtype=np.int64)
        order = np.argsort(stamps, kind='stable')
        stamps, mats = stamps[order], np.asarray(list(poses), dtype=np.float64).reshape(-1, 4, 4)[order]
        keep = np.concatenate(([True], np.diff(stamps) > 0)) if len(stamps) else np.zeros(0, bool)
        return cls(Path(label), stamps[keep], mats[keep])

    def interpolate(self, query_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Poses at ``query_ns`` (linear translation, slerp); ``(T (M,4,4), valid (M,))``.

        Stamps are made relative to the first pose before going to float seconds, so the
        interpolation weight keeps nanosecond precision.
        """
        query_ns = np.asarray(query_ns, dtype=np.int64)
        if len(self) == 0:
            return np.full((len(query_ns), 4, 4), np.nan), np.zeros(len(query_ns), bool)
        t0 = int(self.stamps_ns[0])
        return interpolate_poses((self.stamps_ns - t0) / 1e9, self.poses, (query_ns - t0) / 1e9)


def parse_stamp_ns(text: str) -> int:
    """Exact integer nanoseconds of a decimal stamp string (``ValueError`` if not a number)."""
    try:
        value = Decimal(text)
    except InvalidOperation:
        raise ValueError(f'not a timestamp: {text!r}') from None
    if not value.is_finite():
        raise ValueError(f'not a finite timestamp: {text!r}')
    return int(value.scaleb(9).to_integral_value())


def _data_lines(path: Path) -> Iterable[tuple[int, list[str]]]:
    """``(line number, fields)`` of every non-blank, non-comment line of ``path``."""
    if not path.is_file():
        raise FileNotFoundError(f'{path} not found')
    with path.open('r', encoding='utf-8', errors='replace') as fh:
        for lineno, line in enumerate(fh, start=1):
            text = line.strip()
            if text and not text.startswith('#'):
                yield lineno, text.split()


def _sorted_unique(path: Path, stamps: list[int], lines: list[int]) -> np.ndarray:
    """Sort order of ``stamps``; raise naming the file and lines when two stamps are equal."""
    stamps_arr = np.asarray(stamps, dtype=np.int64)
    order = np.argsort(stamps_arr, kind='stable')
    dup = np.flatnonzero(np.diff(stamps_arr[order]) == 0)
    if dup.size:
        a, b = order[dup[0]], order[dup[0] + 1]
        raise ValueError(
            f'{path}:{lines[b]}: duplicate timestamp {stamps_arr[b] / 1e9:.9f} (also on line {lines[a]})'
        )
    return order


def read_tum_list(path: str | Path) -> TumList:
    """Parse a 'timestamp filename' list; lines may be in any order (sorted here)."""
    path = Path(path)
    stamps: list[int] = []
    files: list[Path] = []
    lines: list[int] = []
    for lineno, fields in _data_lines(path):
        if len(fields) != 2:
            raise ValueError(f'{path}:{lineno}: expected "timestamp filename", got {" ".join(fields)!r}')
        try:
            stamps.append(parse_stamp_ns(fields[0]))
        except ValueError as exc:
            raise ValueError(f'{path}:{lineno}: {exc}') from None
        files.append(path.parent / fields[1])
        lines.append(lineno)
    order = _sorted_unique(path, stamps, lines)
    return TumList(path, np.asarray(stamps, dtype=np.int64)[order], [files[i] for i in order])


def read_groundtruth(path: str | Path) -> TumTrajectory:
    """Parse 'timestamp tx ty tz qx qy qz qw' lines (camera-to-world), any order."""
    path = Path(path)
    stamps: list[int] = []
    values: list[list[float]] = []
    lines: list[int] = []
    for lineno, fields in _data_lines(path):
        if len(fields) != 8:
            raise ValueError(
                f'{path}:{lineno}: expected "timestamp tx ty tz qx qy qz qw", got {len(fields)} fields'
            )
        try:
            stamps.append(parse_stamp_ns(fields[0]))
            row = [float(v) for v in fields[1:]]
        except ValueError as exc:
            raise ValueError(f'{path}:{lineno}: {exc}') from None
        q = np.asarray(row[3:])
        if not np.all(np.isfinite(row)) or np.linalg.norm(q) < 1e-6:
            raise ValueError(f'{path}:{lineno}: pose has non-finite values or a zero quaternion')
        values.append(row)
        lines.append(lineno)
    order = _sorted_unique(path, stamps, lines)
    arr = np.asarray(values, dtype=np.float64).reshape(-1, 7)[order]
    poses = np.tile(np.eye(4), (len(arr), 1, 1))
    if len(arr):
        q = arr[:, 3:] / np.linalg.norm(arr[:, 3:], axis=1, keepdims=True)
        poses[:, :3, :3] = Rotation.from_quat(q).as_matrix()
        poses[:, :3, 3] = arr[:, :3]
    return TumTrajectory(path, np.asarray(stamps, dtype=np.int64)[order], poses)


def _yaml_matrix(doc: dict, key: str, path: Path, size: int | None = None) -> np.ndarray:
    try:
        data = np.asarray(doc[key]['data'], dtype=np.float64).ravel()
    except (KeyError, TypeError, ValueError):
        raise ValueError(f'{path}: missing or malformed "{key}: {{data: [...]}}"') from None
    if size is not None and data.size != size:
        raise ValueError(f'{path}: {key} has {data.size} values, expected {size}')
    return data


def read_camera_yaml(path: str | Path) -> CameraCalibration:
    """The calibration in a ROS camera-info YAML file (``camera_calibration_parsers`` format)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f'camera calibration {path} not found (a TUM folder needs a camera.yaml)')
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ValueError(f'{path}: not valid YAML: {exc}') from None
    if not isinstance(doc, dict):
        raise ValueError(f'{path}: expected a camera-info mapping')
    try:
        width, height = int(doc['image_width']), int(doc['image_height'])
    except (KeyError, TypeError, ValueError):
        raise ValueError(f'{path}: missing or malformed image_width / image_height') from None
    K = _yaml_matrix(doc, 'camera_matrix', path, 9)
    model = str(doc.get('distortion_model', 'plumb_bob'))
    D = (
        _yaml_matrix(doc, 'distortion_coefficients', path)
        if 'distortion_coefficients' in doc
        else np.zeros(0)
    )
    centre = doc.get('centre_in_depth_camera', (0.0, 0.0, 0.0))
    try:
        camera = PinholeCamera.from_K(K, width, height)
        check_distortion(model, D)
        return CameraCalibration(camera, model, tuple(D.tolist()), centre)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{path}: {exc}') from None


@dataclass(frozen=True)
class TumIndex:
    """Everything in a TUM folder except the pixels."""

    root: Path
    rgb: TumList
    depth: TumList | None
    groundtruth: TumTrajectory | None
    calibration: CameraCalibration

    @property
    def name(self) -> str:
        return self.root.resolve().name


def read_tum_index(
    path: str | Path, require_depth: bool = True, require_groundtruth: bool = True
) -> TumIndex:
    """Parse ``rgb.txt``, ``depth.txt``, ``groundtruth.txt`` and ``camera.yaml`` of a folder."""
    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(f'TUM folder {root} not found')
    calibration = read_camera_yaml(root / 'camera.yaml')
    rgb = read_tum_list(root / 'rgb.txt')
    depth_path = root / 'depth.txt'
    depth = read_tum_list(depth_path) if (require_depth or depth_path.is_file()) else None
    gt_path = root / 'groundtruth.txt'
    gt = read_groundtruth(gt_path) if (require_groundtruth or gt_path.is_file()) else None
    return TumIndex(root, rgb, depth, gt, calibration)


# --------------------------------------------------------------------------- association


@dataclass(frozen=True)
class AssociatedFrame:
    """A colour frame with its nearest depth frame and its interpolated pose."""

    stamp_ns: int
    rgb_file: Path
    depth_file: Path | None
    depth_stamp_ns: int | None
    pose: np.ndarray | None  # (4, 4) camera-to-world at stamp_ns

    @property
    def stamp(self) -> float:
        return self.stamp_ns / NS_PER_SEC


@dataclass
class Association:
    frames: list[AssociatedFrame]
    dropped: dict[str, int] = field(default_factory=dict)


def nearest_stamps(sorted_ns: np.ndarray, query_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of the nearest stamp in ``sorted_ns`` (sorted) for each query, and its gap (ns).

    With no stamps at all the gap is the int64 maximum, so every query fails any gap test.
    """
    sorted_ns = np.asarray(sorted_ns, dtype=np.int64)
    query_ns = np.asarray(query_ns, dtype=np.int64)
    if len(sorted_ns) == 0:
        return np.zeros(len(query_ns), np.int64), np.full(len(query_ns), np.iinfo(np.int64).max)
    if len(sorted_ns) == 1:
        return np.zeros(len(query_ns), np.int64), np.abs(query_ns - sorted_ns[0])
    right = np.clip(np.searchsorted(sorted_ns, query_ns), 1, len(sorted_ns) - 1)
    left = right - 1
    gap_left = np.abs(query_ns - sorted_ns[left])
    gap_right = np.abs(sorted_ns[right] - query_ns)
    return np.where(gap_right < gap_left, right, left), np.minimum(gap_left, gap_right)


def associate(
    index: TumIndex,
    depth_max_gap: float = 0.02,
    require_depth: bool = True,
    require_pose: bool = True,
    max_frames: int | None = None,
) -> Association:
    """Pair colour frames with depth (nearest within ``depth_max_gap`` s) and poses.

    Frames outside the ground-truth time span (``outside_groundtruth``) or without depth
    within the gap (``no_depth``, only with ``require_depth``) are dropped and counted, each
    under the first reason that applies. ``max_frames`` keeps the first N kept frames.
    """
    if depth_max_gap < 0:
        raise ValueError(f'depth_max_gap must be >= 0, got {depth_max_gap}')
    if max_frames is not None and max_frames < 0:
        raise ValueError(f'max_frames must be >= 0, got {max_frames}')
    if require_depth and index.depth is None:
        raise FileNotFoundError(f'{index.root / "depth.txt"} not found (needed for ground-truth depth)')
    if require_pose and index.groundtruth is None:
        raise FileNotFoundError(f'{index.root / "groundtruth.txt"} not found (needed for poses)')
    query = index.rgb.stamps_ns
    if index.groundtruth is not None:
        poses, has_pose = index.groundtruth.interpolate(query)
    else:
        poses, has_pose = np.full((len(query), 4, 4), np.nan), np.zeros(len(query), bool)
    if index.depth is not None:
        didx, gap = nearest_stamps(index.depth.stamps_ns, query)
        has_depth = gap <= round(depth_max_gap * NS_PER_SEC)
    else:
        didx, has_depth = np.zeros(len(query), np.int64), np.zeros(len(query), bool)
    dropped = {'outside_groundtruth': 0, 'no_depth': 0}
    frames: list[AssociatedFrame] = []
    for i, stamp in enumerate(query.tolist()):
        if max_frames is not None and len(frames) >= max_frames:
            break
        if require_pose and not has_pose[i]:
            dropped['outside_groundtruth'] += 1
            continue
        if require_depth and not has_depth[i]:
            dropped['no_depth'] += 1
            continue
        depth_file = index.depth.files[didx[i]] if has_depth[i] else None
        depth_stamp = int(index.depth.stamps_ns[didx[i]]) if has_depth[i] else None
        frames.append(
            AssociatedFrame(
                stamp, index.rgb.files[i], depth_file, depth_stamp, poses[i] if has_pose[i] else None
            )
        )
    return Association(frames, {k: v for k, v in dropped.items() if v})


# --------------------------------------------------------------------------- images


def _imread(path: Path, flags: int) -> np.ndarray:
    if not path.is_file():
        raise FileNotFoundError(f'image file {path} not found')
    img = cv2.imread(str(path), flags)
    if img is None:
        raise ValueError(f'cannot decode image file {path}')
    return img


def _check_size(img: np.ndarray, camera: PinholeCamera, path: Path) -> None:
    h, w = img.shape[:2]
    if (w, h) != camera.size:
        raise ValueError(f'{path}: image is {w}x{h}, camera.yaml says {camera.width}x{camera.height}')


def read_rgb_file(path: str | Path, camera: PinholeCamera | None = None) -> np.ndarray:
    """An ``HxWx3 uint8`` RGB image from a PNG/JPEG (size checked against ``camera``)."""
    path = Path(path)
    img = _imread(path, cv2.IMREAD_COLOR)
    if camera is not None:
        _check_size(img, camera, path)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth_file(
    path: str | Path, camera: PinholeCamera | None = None, scale: float = TUM_DEPTH_SCALE
) -> np.ndarray:
    """Depth in metres (float32, NaN = invalid) from a TUM uint16 PNG (``value / scale``)."""
    path = Path(path)
    raw = _imread(path, cv2.IMREAD_UNCHANGED)
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise ValueError(f'{path}: a depth image must be single-channel 16-bit, got {raw.dtype} {raw.shape}')
    if camera is not None:
        _check_size(raw, camera, path)
    depth = raw.astype(np.float32) / np.float32(scale)
    depth[raw == 0] = np.nan
    return depth


def _load_frame(
    i: int,
    af: AssociatedFrame,
    undistorter: Undistorter,
    depth_undistorter: Undistorter,
    depth_scale: float,
    colour_centre: tuple[float, float, float],
) -> Frame:
    """One frame: colour on the working grid; depth undistorted (and registered into the colour
    camera, from ``colour_centre``, when the two calibrations differ) at the native resolution."""
    rgb = undistorter.rgb(read_rgb_file(af.rgb_file, undistorter.native_camera))
    depth = None
    if af.depth_file is not None:
        native = depth_undistorter.native_camera
        depth = depth_undistorter.depth(read_depth_file(af.depth_file, native, depth_scale))
        if depth_undistorter is not undistorter:
            depth = register_depth(depth, native, undistorter.native_camera, colour_centre)
    return Frame(index=i, stamp=af.stamp, rgb=rgb, pose=af.pose, depth=depth)


def load_tum_sequence(
    path: str | Path,
    width: int = 320,
    height: int = 240,
    max_frames: int | None = None,
    depth_max_gap: float = 0.02,
    require_depth: bool = True,
    undistort: bool = True,
    depth_scale: float = TUM_DEPTH_SCALE,
    rgb_calibration: CameraCalibration | None = None,
) -> Sequence:
    """Load a TUM folder as a ``Sequence``.

    ``Frame.rgb`` is undistorted and resized to ``width x height`` (``Sequence.camera``);
    ``Frame.depth`` is the associated ground truth in metres, undistorted, at the original
    resolution (``Sequence.gt_camera``). Frames outside the ground truth or without depth are
    dropped and counted in ``Sequence.dropped``. With ``undistort=False`` the distortion in
    camera.yaml is ignored (for already-rectified data).

    ``rgb_calibration``: the colour camera's calibration when the folder's camera.yaml
    describes the *depth* camera (7-Scenes ships the depth intrinsics). Colour is then
    undistorted with it, and the ground-truth depth is registered into the colour camera
    with :func:`.depth_registration.register_depth`, from the colour camera's
    ``centre_in_depth_camera`` (the same optical centre where the YAML does not give one). The
    poses stay the folder's.
    """
    index = read_tum_index(path, require_depth=require_depth)
    assoc = associate(index, depth_max_gap, require_depth=require_depth, max_frames=max_frames)
    depth_calib = index.calibration
    colour_calib = rgb_calibration or depth_calib
    if colour_calib.camera.size != depth_calib.camera.size:
        raise ValueError(
            f'{index.root}: colour calibration is {colour_calib.camera.width}x{colour_calib.camera.height}, '
            f'camera.yaml (depth) is {depth_calib.camera.width}x{depth_calib.camera.height}'
        )

    def undistorter_of(calib: CameraCalibration) -> Undistorter:
        D = calib.D if undistort else ()
        return Undistorter.for_calibration(
            CameraCalibration(calib.camera, calib.distortion_model, D), width, height
        )

    undistorter = undistorter_of(colour_calib)
    depth_undistorter = undistorter_of(depth_calib) if rgb_calibration is not None else undistorter

    centre = colour_calib.centre_in_depth_camera
    # cv2 decodes with the GIL released: a few threads overlap PNG/JPEG decoding.
    workers = max(1, min(4, os.cpu_count() or 1))
    with ThreadPoolExecutor(workers) as pool:
        frames = list(
            pool.map(
                lambda item: _load_frame(*item, undistorter, depth_undistorter, depth_scale, centre),
                enumerate(assoc.frames),
            )
        )
    if rgb_calibration is not None:
        logger.info('%s: colour calibration overridden; depth registered into the colour camera', index.name)
    if assoc.dropped:
        logger.info('%s: dropped frames %s', index.name, assoc.dropped)
    gt = index.groundtruth
    return Sequence(
        name=index.name,
        camera=undistorter.camera,
        frames=frames,
        gt_camera=undistorter.native_camera,
        dropped=assoc.dropped,
        pose_stream=None if gt is None or not len(gt) else (gt.stamps_ns / NS_PER_SEC, gt.poses),
    )
