"""The native halo test (``fusion/halo_test.c``) against the numpy one (``occlusion.halo_points``).

On rendered keyframes with fattened silhouettes (halos, ramps and regions off at once), with
holes in the single view, points at the image border, a flat image (no gradient) and scaled
depths, the kernel must mark exactly the numpy code's points; and where it cannot be built the
numpy code runs.
"""

from __future__ import annotations

import numpy as np
import pytest
from native_calls import count_native_calls

from depth_fusion_ros import native_build
from depth_fusion_ros.fusion import native_halo, occlusion
from depth_fusion_ros.fusion.scenes import rendered_halo_keyframe
from depth_fusion_ros.point_lookup import bilinear_at


def _native_or_skip() -> None:
    if native_halo._library() is None:
        pytest.skip(f'the native kernel cannot run here: {native_build.unavailable() or "it did not build"}')


def _both(monkeypatch, *args, **kwargs) -> tuple[np.ndarray, np.ndarray]:
    calls = count_native_calls(monkeypatch, occlusion, 'native_halo')
    mine = occlusion.halo_points(*args, **kwargs)
    with monkeypatch.context() as off:
        off.setattr(occlusion, 'native_halo', lambda *a: None)
        theirs = occlusion.halo_points(*args, **kwargs)
    assert calls in ([], [True])  # too few points: neither ran the test
    return mine, theirs


@pytest.fixture(scope='module')
def keyframe():
    return rendered_halo_keyframe(width=160, height=120, point_share=0.6)


@pytest.mark.parametrize('min_step', [0.1, 0.03, 0.3])
def test_the_native_halos_are_numpys(monkeypatch, keyframe, min_step):
    _native_or_skip()
    rgb, single, multi, points = keyframe
    mine, theirs = _both(monkeypatch, rgb, single, multi, points, min_step)
    assert int(theirs.sum()) > 50  # the scene has halos to find
    assert np.array_equal(mine, theirs)


def test_holes_borders_and_scales_give_numpys_halos(monkeypatch, keyframe):
    """A single view with holes (filled with its median), points on the border rows and
    columns (samples read past the image), the points in another unit (the median scale)."""
    _native_or_skip()
    rgb, single, multi, points = keyframe
    single = single.copy()
    single[40:60, 70:90] = np.nan
    single[:3, :] = 0.0  # not a depth: a hole too
    points = points.copy()
    points[[0, -1], :] = True
    points[:, [0, -1]] = True
    mine, theirs = _both(monkeypatch, rgb, single, multi * 3.7, points, 0.1)
    assert int(theirs.sum()) > 50
    assert np.array_equal(mine, theirs)


def test_a_flat_image_and_too_few_points(monkeypatch, keyframe):
    _native_or_skip()
    _, single, multi, points = keyframe
    flat = np.full(single.shape, 0.5, dtype=np.float32)  # no gradient: the unit direction of 0 / 1e-6
    mine, theirs = _both(monkeypatch, flat, single, multi, points, 0.1)
    assert np.array_equal(mine, theirs)
    few = np.zeros_like(points)
    few[60, 10:20] = True  # below MIN_POINTS: nothing tested, by either
    mine, theirs = _both(monkeypatch, flat, single, multi, few, 0.1)
    assert not mine.any() and not theirs.any()


def test_random_fields_give_numpys_halos(monkeypatch):
    """Fields with no structure at all: every branch of the five steps taken somewhere."""
    _native_or_skip()
    rng = np.random.default_rng(5)
    h, w = 90, 130
    image = (rng.random((h, w)) * 255).astype(np.uint8)
    single = np.exp(rng.normal(0.5, 0.4, (h, w))).astype(np.float32)
    multi = np.exp(rng.normal(0.3, 0.5, (h, w))).astype(np.float32)
    points = rng.random((h, w)) < 0.5
    mine, theirs = _both(monkeypatch, image, single, multi, points, 0.05)
    assert int(theirs.sum()) > 20
    assert np.array_equal(mine, theirs)


GEOMETRIES = [(2, 4.0, 0.4, (2, 6)), (5, 9.5, 0.6, (4, 12)), (1, 6.0, 0.5, (0, 0))]


@pytest.mark.parametrize(('search', 'side', 'share', 'beyond'), GEOMETRIES)
def test_other_geometries_give_numpys_halos(monkeypatch, keyframe, search, side, share, beyond):
    """``occlusion.py``'s constants reach the kernel at each call: changed there, the kernel
    follows (no copy of them in C to fall out of step)."""
    _native_or_skip()
    constants = {'SEARCH_PX': search, 'SIDE_PX': side, 'NEAR_SHARE': share, 'BEYOND_PX': beyond}
    for name, value in constants.items():
        monkeypatch.setattr(occlusion, name, value)
    rgb, single, multi, points = keyframe
    mine, theirs = _both(monkeypatch, rgb, single, multi, points, 0.1)
    assert int(theirs.sum()) > 20
    assert np.array_equal(mine, theirs)


def test_a_geometry_the_kernel_does_not_hold_goes_to_numpy(monkeypatch, keyframe):
    _native_or_skip()
    monkeypatch.setattr(occlusion, 'SEARCH_PX', native_halo.MAX_SEARCH_PX + 1)
    calls = count_native_calls(monkeypatch, occlusion, 'native_halo')
    rgb, single, multi, points = keyframe
    occlusion.halo_points(rgb, single, multi, points, 0.1)
    assert calls == [False]


def test_the_bilinear_read_is_opencvs():
    """The kernel reads as ``point_lookup.bilinear_at`` (cv2.remap) does, to the bit: checked
    through the halo test above; here the form it relies on, numpy's float32 FMAs emulated in
    float64, against remap on coordinates inside, on and past the border."""
    rng = np.random.default_rng(2)
    image = (rng.random((40, 60)) * 5).astype(np.float32)
    x = (rng.random(20000) * 80 - 10).astype(np.float32)
    y = (rng.random(20000) * 60 - 10).astype(np.float32)

    def fma(a, b, c):
        return (a.astype(np.float64) * b + c.astype(np.float64)).astype(np.float32)

    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0).astype(np.float32), (y - y0).astype(np.float32)
    c0, c1 = np.clip(x0.astype(int), 0, 59), np.clip(x0.astype(int) + 1, 0, 59)
    r0, r1 = np.clip(y0.astype(int), 0, 39), np.clip(y0.astype(int) + 1, 0, 39)
    top = fma(image[r0, c1] - image[r0, c0], fx, image[r0, c0])
    bottom = fma(image[r1, c1] - image[r1, c0], fx, image[r1, c0])
    assert np.array_equal(fma(bottom - top, fy, top), bilinear_at(image, x, y))
