"""Image pairs from a posed stream, for the calibration checks (focal length, time offset).

Both checks ask the same of a stream: frames far enough apart that a pair carries a signal
at any speed and frame rate (moved ``min_baseline`` or turned ``min_rotation_deg`` since the
last sample, by the told poses), and the matches of consecutive samples that fit one rigid
motion (ORB, cross-checked Hamming matches, the images' own essential matrix:
:func:`rigid_matches`), with the second position of each tracked from the first to sub-pixel
where a check asks (``tracking``: by a shift for the focal check, :mod:`.match_refinement`; by an
affine warp for the mount check, :mod:`.affine_tracking`). :class:`ImagePairs` does that once for each; the
checks differ in what they fit to the pairs. Also the two checks' shared config rules.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..geometry import invert_pose, relative_pose, rotation_angle
from .affine_tracking import track_affine
from .match_refinement import as_uint8, refine_matches
from .match_screening import screen_matches

#: Standard errors a fit must clear a check's threshold by: at its last look, and at an early
#: look (``early_pairs``: the mount and time offset checks), whose error over fewer pairs is noisier.
STANDARD_ERRORS = 2.0
EARLY_STANDARD_ERRORS = 3.0
#: OpenCV's random state (per thread) is set to this before each RANSAC: a deterministic check.
RANSAC_SEED = 12345


def _as_detected(
    first: np.ndarray, second: np.ndarray, p1: np.ndarray, p2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The matches as detected (``tracking`` 'none')."""
    return p1, p2


#: How a pair's second positions are tracked from the first (``ImagePairs.tracking``): not at
#: all (as detected), by a shifted window (:func:`.match_refinement.refine_matches`) or by an
#: affine one (:func:`.affine_tracking.track_affine`).
_TRACKERS = {'none': _as_detected, 'shift': refine_matches, 'affine': track_affine}
TRACKINGS = tuple(_TRACKERS)


def check_sampling(section: str, config: object) -> None:
    """The sampling fields a check's config shares (``pairs``, ``min_matches``, ``features``,
    ``min_baseline``, ``min_rotation_deg``, and ``early_pairs`` where it has an early look):
    one-line errors naming the section."""
    c = config
    if c.pairs < 5 or c.min_matches < 8 or c.features < 50:  # type: ignore[attr-defined]
        raise ValueError(f'{section}: need pairs >= 5, min_matches >= 8 and features >= 50')
    if not (c.min_baseline > 0 and c.min_rotation_deg > 0):  # type: ignore[attr-defined]
        raise ValueError(f'{section}: need min_baseline > 0 and min_rotation_deg > 0')
    early = getattr(c, 'early_pairs', 0)
    if early != 0 and early < 5:
        raise ValueError(f'{section}: need early_pairs 0 (no early look) or >= 5')


def graded_verdict(size: float, sure: float, threshold: float) -> str:
    """The verdict of an observable fit, the same for every calibration check: ``disagrees``
    when even ``sure`` (the fitted offset less :data:`STANDARD_ERRORS` of its standard error;
    :data:`EARLY_STANDARD_ERRORS` at an early look) is at least
    ``threshold``, ``suspect`` when only ``size`` (the fitted offset itself) is (said, never
    applied: before 2026-11-30 such a fit read as agreement), else ``consistent``."""
    if sure >= threshold:
        return 'disagrees'
    return 'suspect' if size >= threshold else 'consistent'


def image_features(orb: cv2.ORB, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """ORB keypoint positions (N, 2) float64 and descriptors (``None`` when none) of a grey image
    (float in [0, 1] or uint8)."""
    keypoints, descriptors = orb.detectAndCompute(as_uint8(gray), None)
    return np.float64([k.pt for k in keypoints]).reshape(-1, 2), descriptors


def rigid_matches(
    matcher: cv2.DescriptorMatcher,
    K: np.ndarray,
    a: tuple[np.ndarray, np.ndarray | None],
    b: tuple[np.ndarray, np.ndarray | None],
    min_matches: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The matches of two images' features (``image_features``) that fit one rigid motion:
    positions ``p1``, ``p2`` (M, 2) accepted by the images' own essential matrix (RANSAC, 1 px,
    OpenCV's random state seeded first: the same pair gives the same matches whatever ran
    before) and that matrix; ``None`` under ``min_matches``."""
    if a[1] is None or b[1] is None:
        return None
    matches = matcher.match(a[1], b[1])
    if len(matches) < min_matches:
        return None
    p1 = a[0][[m.queryIdx for m in matches]]
    p2 = b[0][[m.trainIdx for m in matches]]
    cv2.setRNGSeed(RANSAC_SEED)
    E, mask = cv2.findEssentialMat(p1, p2, K, cv2.RANSAC, 0.999, 1.0)
    if E is None or mask is None or E.shape != (3, 3):
        return None
    inliers = mask.ravel() > 0
    if int(inliers.sum()) < min_matches:
        return None
    return p1[inliers], p2[inliers], E


@dataclass
class Sample:
    """A frame taken as a sample: its stamp, told pose and ORB features."""

    stamp: float
    pose: np.ndarray
    points: np.ndarray  # (N, 2) float64 keypoint positions
    descriptors: np.ndarray | None


@dataclass
class MatchedPair:
    """Two consecutive samples and their matches that fit one rigid motion."""

    a: Sample
    b: Sample
    p1: np.ndarray  # (M, 2) matched positions in the first image
    p2: np.ndarray

    @property
    def T_ba(self) -> np.ndarray:
        """The told relative pose: first-camera coordinates to second-camera coordinates."""
        return relative_pose(self.a.pose, self.b.pose)

    @property
    def T_ba_inverted(self) -> np.ndarray:
        """The same were the told poses inverted (the world's pose in the camera given as the
        camera's in the world: ``pose_inversion.py``)."""
        return relative_pose(invert_pose(self.a.pose), invert_pose(self.b.pose))


class ImagePairs:
    """Takes the samples of a posed stream and matches each with the one before."""

    def __init__(
        self,
        K: np.ndarray,
        min_baseline: float,
        min_rotation_deg: float,
        min_matches: int,
        features: int,
        tracking: str = 'none',
        screen: float = 0.0,
    ) -> None:
        if tracking not in TRACKINGS:
            raise ValueError(f'tracking must be one of {", ".join(TRACKINGS)}, got {tracking!r}')
        self.K = K
        #: How each match's second position is tracked from the first (:data:`TRACKINGS`; which
        #: checks do what and why: ``PairedCheck.TRACKING``).
        self.tracking = tracking
        #: Drop matches whose patch no single shift carries into the second image, above this
        #: multiple of the pair's median residual (:mod:`.match_screening`; 0: none dropped).
        self.screen = float(screen)
        self.min_baseline = min_baseline
        self.min_rotation_deg = min_rotation_deg
        self.min_matches = min_matches
        self._orb = cv2.ORB_create(features)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        self.last: Sample | None = None
        self._last_image: np.ndarray | None = None  # the last sample's uint8 image, kept to track from

    @classmethod
    def for_config(
        cls, K: np.ndarray, config: object, tracking: str = 'none', screen: float = 0.0
    ) -> ImagePairs:
        c = config
        return cls(K, c.min_baseline, c.min_rotation_deg, c.min_matches, c.features, tracking, screen)  # type: ignore[attr-defined]

    @property
    def _tracks(self) -> bool:
        """Whether pairs are tracked from the last sample's image (refined or screened), which
        is then kept."""
        return self.tracking != 'none' or self.screen > 0

    def far_enough(self, pose: np.ndarray, since: np.ndarray | None = None) -> bool:
        """Whether a frame at ``pose`` is the next sample: moved or turned enough since the last
        (or since ``since``: a sample chosen but not yet added, as a check's thread lags its
        stream)."""
        if since is None and self.last is None:
            return True
        T = relative_pose(self.last.pose if since is None else since, np.asarray(pose, dtype=np.float64))
        moved = float(np.linalg.norm(T[:3, 3])) >= self.min_baseline
        return moved or math.degrees(rotation_angle(T[:3, :3])) >= self.min_rotation_deg

    def add(self, gray: np.ndarray, pose: np.ndarray, stamp: float = 0.0) -> MatchedPair | None:
        """Take a frame as the next sample; its pair with the last one when they match (at least
        ``min_matches`` after RANSAC) and moved apart, else ``None``."""
        image = as_uint8(gray)
        current = Sample(float(stamp), np.asarray(pose, dtype=np.float64), *image_features(self._orb, image))
        last, last_image = self.last, self._last_image
        self.last, self._last_image = current, (image if self._tracks else None)
        if last is None:
            return None
        matched = rigid_matches(
            self._matcher,
            self.K,
            (last.points, last.descriptors),
            (current.points, current.descriptors),
            self.min_matches,
        )
        if matched is None:
            return None
        p1, p2 = matched[:2]
        if self._tracks:
            if last_image is None or last_image.shape != image.shape:  # another grid: nothing to track
                return None
            p1, p2 = screen_matches(last_image, image, p1, p2, self.screen)
            p1, p2 = _TRACKERS[self.tracking](last_image, image, p1, p2)
            if len(p1) < self.min_matches:
                return None
        pair = MatchedPair(last, current, p1, p2)
        if np.linalg.norm(pair.T_ba[:3, 3]) < 1e-4:
            return None
        return pair

    def reset(self) -> None:
        self.last = None
        self._last_image = None
