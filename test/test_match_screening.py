"""Matches at occlusion outlines are screened out of the mount check's pairs (match_screening.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from depth_fusion_ros.data.synthetic import render_sequence, stress_config
from depth_fusion_ros.multiview.match_screening import patch_residuals, screen_matches
from depth_fusion_ros.multiview.mount_check import MountCheckConfig, check_frames

H, W = 120, 160


def _texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    return cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 1.2)


def _pair() -> tuple[np.ndarray, np.ndarray]:
    """A textured wall that moves 2 px right between the images and a textured box before it
    (rows 40-79) that moves 6 px, each image with its own sensor noise (2 grey levels)."""
    rng = np.random.default_rng(3)
    wall, box = _texture(rng, H, W + 40), _texture(rng, 40, 40)

    def image(wall_shift: int, box_x: int) -> np.ndarray:
        out = wall[:, 20 - wall_shift : 20 - wall_shift + W].copy()
        out[40:80, box_x : box_x + 40] = box
        out += rng.normal(0.0, 2.0, out.shape).astype(np.float32)
        return np.clip(out, 0, 255).astype(np.uint8)

    return image(0, 60), image(2, 66)


def _matches() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Matches of the wall (moved 2 px), of the box (6 px) and on the box's left and right
    outlines, where a corner of both slides 4 px; the last array says which are outlines."""
    ys = np.arange(14, 110, 8, dtype=np.float64)
    wall = np.array([(x, y) for x in (12.0, 24.0, 36.0) for y in ys])
    box = np.array([(x, y) for x in (72.0, 80.0, 88.0) for y in (48.0, 56.0, 64.0, 72.0)])
    outline = np.array([(x, y) for x in (60.0, 99.0) for y in (46.0, 52.0, 58.0, 64.0, 70.0)])
    p1 = np.concatenate([wall, box, outline])
    shift = np.concatenate([np.full(len(wall), 2.0), np.full(len(box), 6.0), np.full(len(outline), 4.0)])
    p2 = p1 + np.stack([shift, np.zeros_like(shift)], axis=1)
    is_outline = np.arange(len(p1)) >= len(wall) + len(box)
    return p1, p2, is_outline


def test_a_window_on_an_outline_is_left_with_a_larger_residual_and_dropped():
    first, second = _pair()
    p1, p2, is_outline = _matches()
    residual = patch_residuals(first, second, p1, p2)
    assert np.isfinite(residual).all()
    # Each surface's window is carried by one shift (the sensor noise is left); the outline's is not.
    assert np.max(residual[~is_outline]) < 4.0 < np.min(residual[is_outline]), residual
    k1, k2 = screen_matches(first, second, p1, p2, 1.5)
    kept = {tuple(p) for p in k1}
    assert all(tuple(p) in kept for p in p1[~is_outline])
    assert not any(tuple(p) in kept for p in p1[is_outline])
    # The positions stay as matched: the screen only drops.
    assert np.array_equal(k2, p2[~is_outline])


def test_the_screen_off_or_empty_keeps_every_match():
    first, second = _pair()
    p1, p2, _ = _matches()
    k1, k2 = screen_matches(first, second, p1, p2, 0.0)
    assert k1 is p1 and k2 is p2
    e1, e2 = screen_matches(first, second, p1[:0], p2[:0], 1.5)
    assert e1.shape == (0, 2) and e2.shape == (0, 2)
    assert patch_residuals(first, second, p1[:0], p2[:0]).shape == (0,)


def test_the_screen_is_validated():
    with pytest.raises(ValueError, match='max_patch_residual'):
        MountCheckConfig(max_patch_residual=0.5)
    with pytest.raises(ValueError, match='max_patch_residual'):
        MountCheckConfig(max_patch_residual=-1.0)
    assert MountCheckConfig(max_patch_residual=0.0).max_patch_residual == 0.0


def test_a_level_robot_is_not_turned_by_the_matches_at_its_outlines():
    """The failure: the level robot of seed 45 (300 frames, 20 pairs 10 cm apart) was turned
    0.95 deg about x, sure at two standard errors of 0.10 deg: 17 % of its matches sit on
    occlusion outlines and slide along the flow. Screened, the same stream's fit falls to
    0.60 deg, short of sure: not turned. Since its matches are tracked with an affine window
    (and a turn's sureness counts the spread over the image), the unscreened stream is not
    turned either, but its fit is still the furthest off: 0.63 deg about x against 0.43
    screened (0.28 at 1.5)."""
    cfg = stress_config('mount_tilt', width=320, height=240, frames=300, seed=45, mount_tilt_deg=0.0)
    seq = render_sequence(cfg)
    fitted = {}
    for ratio in (2.0, 1.5, 0.0):
        screened = check_frames(seq.camera, seq.frames, MountCheckConfig(max_patch_residual=ratio)).result
        assert screened is not None and screened.pairs == 20, screened
        assert screened.verdict != 'disagrees', screened.message()
        assert np.array_equal(screened.rotation(), np.eye(4))
        fitted[ratio] = screened.fitted_deg[0]
    assert MountCheckConfig().max_patch_residual == 2.0
    assert fitted[1.5] < fitted[2.0] < 0.5 < fitted[0.0] - 0.1, fitted
