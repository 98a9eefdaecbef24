"""Poses given inverted: the world's pose in the camera (T_cw) where the camera's in the world
(T_wc) is meant.

Why: ``geometry_msgs/PoseStamped`` on ``camera/pose`` in the world frame is the camera's pose
in the world, as TF and REP 105 hold it. A SLAM system keeps the other one internally (ORB-SLAM's
``Tcw``), and a relay that publishes it as it is gives every pose inverted. Nothing else about
the stream looks wrong. 7-Scenes 0-499 with its poses inverted was triangulated with that motion:
the mount check read the 180 deg it makes of a motion in the image plane as a frame turn
(171.9 deg, taken), the focal length check found no focal length that fits, and the adaptation,
trained on the points, made the single view 0.975 m against the shipped network's 0.511
(docs/multi_view.md, "Poses given inverted").

The check needs no fit of the directions. Each image pair's own motion (``cv2.recoverPose``: the translation's
direction and the rotation's axis, ``frame_fit.pair_directions``) is compared with the told
relative pose and with the relative pose of the inverted poses. Inverted poses fit the images
as right poses fit them, with the directions' own noise (7-Scenes: 12-18 deg median). The
told ones miss them by far more: when the world frame is the first camera's, as a SLAM
system's is, by about 180 deg, the told motion running backwards. The mount check looks for
this before a frame turn (a frame turn is fitted, 3 degrees of freedom; this has none), and, as
for a frame turn, keeps it only when the pairs' matches fit the inverted poses far better than
the told ones (``mount_check.FRAME_COST_GAIN``): on a repetitive wall ``recoverPose`` can be
fooled, and the `repetitive` stress stream of seed 151, posed right, read as inverted from its
directions alone. The directions can be fooled the other way too: a sideways sweep of a
textured room and a low-texture room (seed 161) given inverted poses read as a frame turn of
135-143 deg from them, and a hand-held stream (seed 221) as one of 80 deg. So a frame turn
found is kept only when the matches fit it ``FRAME_COST_GAIN`` times better than the inverted
poses (a turn fits three parameters to the pairs, the inversion none; a body frame's turn fits
25 to 3000 times better); else, where they fit the inverted poses that much better than the
told ones (0.16 against 84 as told over 7 pairs of the sweep), the poses are inverted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .frame_fit import MIN_DIRECTIONS, MIN_FIT_GAIN, Directions, median_angle_deg

#: The told directions must miss the images' by at least this (degrees, median). Lower than the
#: frame check's 45 (``frame_fit.MIN_TOLD_RESIDUAL_DEG``): a turn is fitted to the directions,
#: the inversion is not, and the matches' cost confirms it. TUM fr1_xyz given inverted poses
#: misses by 44 deg (its motion mostly a translation seen from a near-level camera), the
#: inverted poses by 6, and its matches fit them 19 times better; a right frame misses by the
#: directions' own noise (7-Scenes 0-499: 12-18 deg).
MIN_TOLD_RESIDUAL_DEG = 30.0


@dataclass(frozen=True)
class InvertedPoses:
    """How the told poses and the same inverted fit the images' directions: the median angles
    (degrees) between the images' directions and the told ones, as told and inverted, over
    ``directions`` of them."""

    told_residual_deg: float
    inverted_residual_deg: float
    directions: int

    @property
    def says_inverted(self) -> bool:
        """The told ones miss the images' by at least ``MIN_TOLD_RESIDUAL_DEG`` and the inverted
        ones fit ``MIN_FIT_GAIN`` times better (the frame check's own rules)."""
        told, inverted = self.told_residual_deg, self.inverted_residual_deg
        return told >= MIN_TOLD_RESIDUAL_DEG and inverted * MIN_FIT_GAIN <= told


def direction_fit(known: list[Directions], min_directions: int = MIN_DIRECTIONS) -> InvertedPoses | None:
    """How the told and the inverted poses fit the pairs' directions (``frame_fit.pair_directions``,
    one tuple per pair); None under ``min_directions`` directions."""
    told, image, inverted = [], [], []
    for a, b, c in known:
        told += a
        image += b
        inverted += c
    if len(told) < min_directions:
        return None
    A, B, C = np.array(told), np.array(image), np.array(inverted)
    return InvertedPoses(median_angle_deg(A, B), median_angle_deg(C, B), len(told))
