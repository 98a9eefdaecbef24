"""The filter's native geometry and choice of rows (``multiview/filter_choose.c``) against torch's.

For every candidate pixel of a keyframe the kernel must give what ``frame_geometry`` gives (the
projection at infinity, the epipolar motion, the gradient along the line, the visibility) and
then the rows ``choose_rows`` picks and the first attempts it counts, bit for bit: with and
without the seeding parallax, the pose term, a ``only`` mask, pixels behind the camera and
outside the image, and a keyframe without estimates.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from depth_fusion_ros import native_build
from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.geometry import make_pose
from depth_fusion_ros.multiview import native_choose
from depth_fusion_ros.multiview.filter_config import FilterConfig
from depth_fusion_ros.multiview.filter_frame_update import choose_rows
from depth_fusion_ros.multiview.filter_geometry import frame_geometry
from depth_fusion_ros.multiview.filter_update import BetaGaussian

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _native_or_skip() -> None:
    if native_choose._library() is None:
        pytest.skip(f'the native kernel cannot run here: {native_build.unavailable() or "it did not build"}')


def _keyframe(m: int, gen: torch.Generator, estimates: float) -> SimpleNamespace:
    prior = torch.rand(m, generator=gen) < estimates
    mu = torch.rand(m, generator=gen) * 2 + 0.05
    var = torch.rand(m, generator=gen) ** 4 * 1e-2
    state = BetaGaussian(mu, var, torch.full((m,), 10.0), torch.full((m,), 10.0))
    return SimpleNamespace(
        us=(torch.rand(m, generator=gen) * 319).floor(),
        vs=(torch.rand(m, generator=gen) * 239).floor(),
        state=state,
        prior=prior,
        attempts=torch.randint(0, 3, (m,), generator=gen),
        grad=torch.randn(2, m, generator=gen) * 0.02,
    )


def _filter(config: FilterConfig, scene: float) -> SimpleNamespace:
    cam = PinholeCamera(fx=262.0, fy=262.0, cx=159.5, cy=119.5, width=320, height=240)
    return SimpleNamespace(config=config, camera=cam, margin=4.0, _scene=scene)


def _motion(gen: torch.Generator, turn_deg: float, move: float) -> np.ndarray:
    axis = torch.randn(3, generator=gen).numpy()
    axis /= np.linalg.norm(axis)
    half = math.radians(turn_deg) / 2
    quat = np.array([*(axis * math.sin(half)), math.cos(half)])
    return make_pose(torch.randn(3, generator=gen).numpy() * move, quat)


@pytest.mark.parametrize(
    ('seed', 'turn_deg', 'move', 'estimates', 'pose_sigma', 'scene', 'with_only'),
    [
        (0, 2.0, 0.05, 0.6, 0.0, 1.0, False),
        (1, 8.0, 0.3, 0.9, 0.01, 1.0, False),
        (2, 1.0, 0.01, 0.5, 0.0, 50.0, False),  # no seeding: parallax below seed_parallax
        (3, 3.0, 0.08, 0.0, 0.0, 1.0, False),  # no estimates yet
        (4, 40.0, 2.0, 0.7, 0.0, 1.0, True),  # many pixels behind or outside; a seed mask
    ],
)
def test_the_native_choice_is_the_torch_choice(seed, turn_deg, move, estimates, pose_sigma, scene, with_only):
    _native_or_skip()
    gen = torch.Generator().manual_seed(seed)
    m = 9000
    filt = _filter(FilterConfig(pose_sigma=pose_sigma), scene)
    key = _keyframe(m, gen, estimates)
    T_fk = _motion(gen, turn_deg, move)
    baseline = max(float(np.linalg.norm(T_fk[:3, 3])), 1e-9)
    only = (torch.rand(m, generator=gen) > 0.4) if with_only else None
    attempts_before = key.attempts.clone()
    got = native_choose.native_choose(filt, key, T_fk, baseline, only)
    assert got is not None
    geo, rows, seen = got
    native_attempts = key.attempts.clone()
    key.attempts = attempts_before.clone()
    want_geo = frame_geometry(key, filt.camera, T_fk, filt.margin)
    want_rows, want_seen = choose_rows(filt, key, want_geo, baseline, only)
    for name in ('a', 'j', 'along', 'visible'):
        assert torch.equal(getattr(geo, name), getattr(want_geo, name)), name
    assert geo.b == want_geo.b
    assert torch.equal(rows, want_rows)
    assert seen == want_seen
    assert torch.equal(native_attempts, key.attempts)
    assert 0 < rows.numel() < m
    if turn_deg > 20:
        assert bool((~geo.visible).any())  # the test reached pixels the frame does not see


def test_the_kernel_declines_what_it_was_not_written_for():
    _native_or_skip()
    gen = torch.Generator().manual_seed(9)
    filt = _filter(FilterConfig(), 1.0)
    key = _keyframe(100, gen, 0.5)
    motion = _motion(gen, 2.0, 0.05)
    short_mask = torch.ones(99, dtype=torch.bool)  # one entry short: the kernel would read past it
    assert native_choose.native_choose(filt, key, motion, 0.05, short_mask) is None
    key.state.mu = key.state.mu.double()
    assert native_choose.native_choose(filt, key, motion, 0.05, None) is None
