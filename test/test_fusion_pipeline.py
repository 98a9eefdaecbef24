"""Interpolation (exact/fast) and ``fuse_keyframe`` on synthetic planes and boxes with exact depth."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from depth_fusion_ros.fusion import chunk_sums, kernel_compile
from depth_fusion_ros.fusion.chunk_sums import (
    chunk_sums_inplace,
    chunk_sums_one_pass,
    exp_nonpositive,
    no_one_pass,
    one_pass_kernel,
)
from depth_fusion_ros.fusion.interpolation import interpolate
from depth_fusion_ros.fusion.pipeline import FusionConfig, fuse_keyframe
from depth_fusion_ros.fusion.scenes import make_scene
from depth_fusion_ros.fusion.weights import (
    Samples,
    WeightParams,
    depth_gradients,
    normalise_weights,
    proximity_weights,
    samples_at,
    structure_weights,
    unnormalised_weights,
)


def _dense_reference(
    s: np.ndarray, m: np.ndarray, omega: np.ndarray, params: WeightParams, c: np.ndarray | None = None
) -> np.ndarray:
    """Eq. (2) straight from the formulas: the full (pixels x Ω) matrix, normalised, summed;
    with ``c`` (HxW), every weight of point q times c_q before the normalisation."""
    gx, gy = (torch.from_numpy(g.ravel()) for g in depth_gradients(s))
    st = torch.from_numpy(s.ravel())
    width = s.shape[1]
    pixels = samples_at(torch.arange(s.size), width, st, gx, gy).column()
    q_index = torch.from_numpy(np.flatnonzero(omega))
    points = samples_at(q_index, width, st, gx, gy).row()
    w = unnormalised_weights(pixels, points, params).double()
    if c is not None:
        w = w * torch.from_numpy(c[omega].astype(np.float64))[None, :]
    w = normalise_weights(w)
    terms = torch.from_numpy(m.ravel()[q_index.numpy()]).double()[None, :] + (st[:, None] - points.s).double()
    return (w * terms).sum(dim=1).reshape(s.shape).numpy()


@pytest.mark.parametrize('weights', ['w1', 'w1w2', 'all'])
def test_exact_mode_equals_the_formula_and_ignores_chunking(weights: str) -> None:
    sc = make_scene(40, 30, n_points=25)
    params = WeightParams(weights=weights)
    omega = np.isfinite(sc.multi)
    reference = _dense_reference(sc.single, sc.multi, omega, params)
    for chunk in (7, 1 << 20):
        got = sc.single + interpolate(sc.single, sc.multi, omega, params, chunk_elements=chunk).offset
        assert np.allclose(got, reference, atol=2e-5)


@pytest.mark.parametrize('mode', ['exact', 'fast'])
def test_point_weights_multiply_each_points_weights(mode: str) -> None:
    """``point_weight`` (fusion/precision.py) multiplies every weight of its point, in the
    exact and the fast path's exact sums; NaN means weight 1."""
    sc = make_scene(40, 30, n_points=25)
    omega = np.isfinite(sc.multi)
    c = np.random.default_rng(1).uniform(0.02, 1.0, sc.single.shape).astype(np.float32)
    reference = _dense_reference(sc.single, sc.multi, omega, WeightParams(), c)
    for chunk in (7, 1 << 20):
        got = (
            sc.single
            + interpolate(
                sc.single, sc.multi, omega, mode=mode, fast_stride=1, chunk_elements=chunk, point_weight=c
            ).offset
        )
        assert np.allclose(got, reference, atol=2e-5)
    plain = interpolate(sc.single, sc.multi, omega).offset
    ones = interpolate(sc.single, sc.multi, omega, point_weight=np.full_like(c, np.nan)).offset
    assert np.array_equal(plain, ones, equal_nan=True)  # NaN: no evidence, weight 1
    assert not np.allclose(reference, sc.single + plain, atol=1e-3)


def test_wrong_scale_and_offset_pulled_onto_the_true_surface() -> None:
    sc = make_scene(80, 60, n_points=80, scale=0.8, offset=0.3)
    err_single = np.abs(sc.single - sc.depth).mean()
    # Metric source: s kept, the paper's interpolation alone bends it onto the points.
    res = fuse_keyframe(sc.single, sc.multi, None, FusionConfig(guard=False), 'metric_depth')
    assert res.fallback is None and res.n_omega == 80
    assert np.abs(res.depth - sc.depth).mean() < 0.15 * err_single
    # The guard (default) fades corrections out far from the 80 points (1.7 % of the pixels):
    # towards the globally scaled single-view depth there, still far better than s.
    guarded = fuse_keyframe(sc.single, sc.multi, None, FusionConfig(), 'metric_depth')
    assert np.abs(guarded.depth - sc.depth).mean() < 0.6 * err_single
    # Relative source: the stage-2 line maps s exactly, then the interpolation adds nothing.
    res = fuse_keyframe(sc.single, sc.multi, None, FusionConfig(), 'relative_depth')
    assert res.a == pytest.approx(1.25, rel=1e-4) and res.b == pytest.approx(-0.375, abs=1e-4)
    assert np.abs(res.depth - sc.depth).max() < 1e-4


def test_planted_outliers_are_rejected_before_fusing() -> None:
    sc = make_scene(80, 60, n_points=100, n_outliers=20, scale=1.0, offset=0.0)
    res = fuse_keyframe(sc.single, sc.multi, None, FusionConfig(ransac_threshold=0.1), 'metric_depth')
    assert res.n_stage1 == 100 and res.n_omega == 80
    assert np.array_equal(res.omega_mask, sc.good)
    assert np.abs(res.depth - sc.depth).max() < 1e-4


@pytest.mark.parametrize('mode', ['exact', 'fast'])
def test_empty_single_and_pair_of_points(mode: str) -> None:
    sc = make_scene(40, 30, n_points=2, scale=1.0, offset=0.0)
    # eq. (9) as the paper has it
    cfg = FusionConfig(mode=mode, fast_stride=3, certainty_floor=0.0, certainty_gain=0.0)
    s = sc.single
    none = interpolate(s, sc.multi, np.zeros(s.shape, bool), mode=mode)
    assert np.all(np.isnan(none.offset)) and np.all(np.isnan(none.support_distance))

    # |Ω| = 1: plain normalisation, every pixel moves by that point's offset.
    one = np.zeros(s.shape, bool)
    one[10, 12] = True
    m = np.full(s.shape, np.nan, np.float32)
    m[10, 12] = s[10, 12] + 0.4
    res = fuse_keyframe(s, m, None, cfg, omega_mask=one)
    assert res.fallback is None and res.n_omega == 1
    assert np.allclose(res.depth, s + 0.4, atol=1e-5)

    # |Ω| = 2: min subtraction gives each pixel the offset of its heavier point.
    two = one.copy()
    two[25, 30] = True
    m[25, 30] = s[25, 30] - 0.2
    res = fuse_keyframe(s, m, None, cfg, omega_mask=two)
    offset = res.depth - s
    either = np.isclose(offset, 0.4, atol=1e-4) | np.isclose(offset, -0.2, atol=1e-4)
    # The fast mode blends the two offsets along the border between the regions.
    assert either.all() if mode == 'exact' else either.mean() > 0.8
    assert np.all((offset > -0.2 - 1e-4) & (offset < 0.4 + 1e-4))
    assert offset[10, 12] == pytest.approx(0.4, abs=1e-4) and offset[25, 30] == pytest.approx(-0.2, abs=1e-4)


def test_fast_and_exact_agree_on_small_inputs() -> None:
    sc = make_scene(96, 72, n_points=150, scale=0.85, offset=0.2, seed=2)
    omega = np.isfinite(sc.multi)
    exact = interpolate(sc.single, sc.multi, omega, mode='exact')
    fast = interpolate(sc.single, sc.multi, omega, mode='fast', fast_stride=4)
    diff = np.abs(exact.offset - fast.offset)
    assert np.median(diff) < 2e-3 and diff.mean() < 1e-2
    mae_exact = np.abs(sc.single + exact.offset - sc.depth).mean()
    mae_fast = np.abs(sc.single + fast.offset - sc.depth).mean()
    assert abs(mae_fast - mae_exact) <= 0.02 * mae_exact + 1e-4


@pytest.mark.parametrize('kind', ['relative_depth', 'inverse_depth'])
def test_a_source_that_needs_the_fit_is_withheld_when_it_fails(kind: str) -> None:
    """A relative map passed on as metres (or mapped by a fit the guard rejected) would be
    numbers that look like depth: such a keyframe gets NaN, confidence 0 and the reason."""
    sc = make_scene(40, 30, n_points=5)
    s = sc.single if kind == 'relative_depth' else 1.0 / sc.single
    res = fuse_keyframe(s, sc.multi, None, FusionConfig(ransac_min_inliers=10), kind)
    assert res.fallback == 'too_few_points' and res.decision == 'single_view' and res.withheld
    assert np.isnan(res.depth).all() and np.all(res.confidence == 0)
    assert 'withheld' in res.decision_reason and kind in res.decision_reason
    # align_scale on a metric source (monocular SLAM units): the same
    scaled = fuse_keyframe(sc.single, sc.multi, None, FusionConfig(ransac_min_inliers=10, align_scale=True))
    assert scaled.withheld and np.isnan(scaled.depth).all()


@pytest.mark.parametrize('mode', ['exact', 'fast'])
def test_fused_output_is_finite_wherever_s_is(mode: str) -> None:
    sc = make_scene(64, 48, n_points=60, seed=4)
    s = sc.single.copy()
    s[5:9, 20:40] = np.nan  # a hole, including coarse-grid pixels of the fast mode
    s[0, :] = np.nan
    res = fuse_keyframe(s, sc.multi, None, FusionConfig(mode=mode), 'relative_depth')
    assert res.fallback is None
    assert np.array_equal(np.isfinite(res.depth), np.isfinite(s))
    assert np.all((res.confidence >= 0) & (res.confidence <= 1))
    assert np.all(res.confidence[np.isnan(s)] == 0)


def test_confidence_is_high_near_points_and_low_far_away() -> None:
    s = np.full((60, 80), 2.0, np.float32)
    m = np.full(s.shape, np.nan, np.float32)
    m[28:33, 5:10] = 2.1
    res = fuse_keyframe(s, m, None, FusionConfig(), 'metric_depth', omega_mask=np.isfinite(m))
    assert res.confidence[30, 7] > 0.8 and res.confidence[30, 75] < 0.05


def test_fallbacks_publish_the_single_view_depth_flagged() -> None:
    sc = make_scene(40, 30, n_points=5)
    res = fuse_keyframe(sc.single, sc.multi, None, FusionConfig(ransac_min_inliers=10), 'metric_depth')
    assert res.fallback == 'too_few_points' and res.n_stage1 == 5 and res.n_omega == 0
    assert np.array_equal(res.depth, sc.single) and np.all(res.confidence == 0)
    assert not res.withheld
    rng = np.random.default_rng(0)
    junk = np.where(np.isfinite(make_scene(40, 30, n_points=200).multi), rng.uniform(1, 9, (30, 40)), np.nan)
    cfg = FusionConfig(ransac_threshold=0.005, ransac_min_inliers=50)
    assert fuse_keyframe(sc.single, junk.astype(np.float32), None, cfg).fallback == 'no_consensus'
    empty = fuse_keyframe(sc.single, sc.multi, None, omega_mask=np.zeros((30, 40), bool))
    assert empty.fallback == 'empty_omega'
    nan = np.full((30, 40), np.nan, np.float32)
    assert fuse_keyframe(nan, sc.multi, None).fallback == 'no_single_view'
    stage1_empty = fuse_keyframe(sc.single, sc.multi, np.zeros((30, 40), bool))
    assert stage1_empty.fallback == 'too_few_points' and stage1_empty.n_stage1 == 0


def test_bad_inputs_raise_clear_errors() -> None:
    s = np.ones((30, 40), np.float32)
    with pytest.raises(ValueError, match='differ in size'):
        fuse_keyframe(s, np.ones((30, 41), np.float32), None)
    with pytest.raises(ValueError, match='stage1_mask'):
        fuse_keyframe(s, s, np.ones((3, 3), bool))
    with pytest.raises(ValueError, match='output_kind'):
        fuse_keyframe(s, s, None, output_kind='disparity')
    with pytest.raises(ValueError, match='floating point'):
        fuse_keyframe(s.astype(np.uint16), s, None)
    with pytest.raises(ValueError, match='mode'):
        FusionConfig(mode='approximate')
    with pytest.raises(ValueError, match='max_points'):
        FusionConfig(max_points=0)


def test_max_points_caps_omega_deterministically() -> None:
    sc = make_scene(40, 30, n_points=100, scale=1.0, offset=0.0)
    cfg = FusionConfig(max_points=30, seed=5)
    a = fuse_keyframe(sc.single, sc.multi, None, cfg)
    b = fuse_keyframe(sc.single, sc.multi, None, cfg)
    assert a.n_omega == 30 and np.array_equal(a.omega_mask, b.omega_mask)


def _reference_sums(
    p: Samples, q: Samples, v: torch.Tensor, params: WeightParams, lw: torch.Tensor | None = None
) -> tuple:
    """``(ΣW'v, ΣW', ΣW'd, min W̃)`` straight from the formulas of ``fusion.weights``."""
    dx = q.x - p.x
    dy = q.y - p.y
    distance = torch.sqrt(dx * dx + dy * dy)
    w = proximity_weights(distance, params, lw)
    if params.weights != 'w1':
        w = w * structure_weights(p, q, params, dx, dy)
    low = w.amin(dim=1, keepdim=True)
    shifted = w - low
    return shifted @ v, shifted.sum(dim=1), (shifted * distance).sum(dim=1), low.squeeze(1)


@pytest.mark.parametrize('point_weights', [False, True])
@pytest.mark.parametrize('weights', ['w1', 'w1w2', 'all'])
def test_compiled_and_eager_kernels_compute_the_same_sums(weights: str, point_weights: bool) -> None:
    """The weights' formulas (functional) and the in-place eager kernel agree, with and
    without each point's own weight (a factor exp(lw))."""
    g = torch.Generator().manual_seed(0)

    def samples(n: int) -> Samples:
        x, y = torch.rand(n, generator=g) * 80, torch.rand(n, generator=g) * 60
        s = 1 + 3 * torch.rand(n, generator=g)
        return Samples(x, y, s, torch.randn(n, generator=g) * 0.05, torch.randn(n, generator=g) * 0.05)

    p, q, v = samples(64).column(), samples(300).row(), torch.randn(300, generator=g)
    lw = torch.log(0.05 + torch.rand(1, 300, generator=g)).clamp_max(0) if point_weights else None
    params = WeightParams(weights=weights)
    reference = _reference_sums(p, q, v, params, lw)
    for a, b in zip(reference, chunk_sums_inplace(p, q, v, lw, params), strict=True):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-5 * float(a.abs().max()))


def test_polynomial_exp_is_within_the_sums_own_float32_error() -> None:
    """The compiled kernel's exp: < 3e-6 relative over the clamped range (the rounding error of
    a float32 sum over 2000 points is of that order), and exactly 1 at 0."""
    x = -torch.linspace(0, 60, 200_001)
    ref = torch.exp(x.double())
    assert float(((exp_nonpositive(x).double() - ref) / ref).abs().max()) < chunk_sums.EXP_RTOL
    assert float(exp_nonpositive(torch.zeros(8))[0]) == 1.0


def test_polynomial_exp_keeps_its_accuracy_when_compiled() -> None:
    """Compiled with the kernels' inductor options (fused multiply-adds, which round
    differently), the exp's range reduction and exponent-bit scale keep the polynomial's accuracy."""
    x = -torch.linspace(0, 60, 20_001)
    ref = torch.exp(x.double())
    options = kernel_compile.inductor_options(torch.device('cpu'))  # outside the try: a bad call fails
    try:
        compiled = torch.compile(exp_nonpositive, dynamic=False, options=options)(x)
    except Exception as exc:  # no C++ toolchain: the eager fallback is what runs, tested above
        pytest.skip(f'torch.compile unavailable here: {exc}')
    assert float(((compiled.double() - ref) / ref).abs().max()) < chunk_sums.EXP_RTOL


@pytest.mark.parametrize('point_weights', [False, True])
@pytest.mark.parametrize('weights', ['w1', 'w1w2', 'all'])
@pytest.mark.parametrize('n_points', [1, 3, 300])
def test_one_pass_sums_equal_the_two_pass_kernel(weights: str, n_points: int, point_weights: bool) -> None:
    """Σ(W̃ - min)·x = ΣW̃·x - min·Σx: the one-pass kernel (what the compiled path runs) gives the
    two-pass sums, including rows where the minimum is not negligible (tiny Ω: redone two-pass)."""
    g = torch.Generator().manual_seed(n_points)

    def samples(n: int) -> Samples:
        x = torch.randint(0, 80, (n,), generator=g).float()
        y = torch.randint(0, 60, (n,), generator=g).float()
        s = 1 + 3 * torch.rand(n, generator=g)
        return Samples(x, y, s, torch.randn(n, generator=g) * 0.05, torch.randn(n, generator=g) * 0.05)

    p, q, v = samples(64).column(), samples(n_points).row(), torch.randn(n_points, generator=g)
    lw = torch.log(0.05 + torch.rand(1, n_points, generator=g)).clamp_max(0) if point_weights else None
    params = WeightParams(weights=weights)
    one_pass = one_pass_kernel(lambda *a: chunk_sums_one_pass(*a, params), params, chunk_elements=50)
    no_compiler = one_pass_kernel(no_one_pass, params, chunk_elements=50)  # two-pass in blocks
    reference = chunk_sums_inplace(p, q, v, lw, params)
    # The one-pass kernel's exp is EXP_RTOL-accurate: a sum whose terms cancel (v of both signs)
    # carries that error relative to its terms, Σ W̃|v| (min-subtracted, plus the min's share).
    terms = chunk_sums_inplace(p, q, v.abs(), lw, params)[0] + reference[3] * v.abs().sum()
    magnitudes = (terms, *reference[1:])
    for kernel in (one_pass, no_compiler):
        for a, b, m in zip(kernel(p, q, v, lw), reference, magnitudes, strict=True):
            exp_error = 2 * chunk_sums.EXP_RTOL * m.abs()
            assert bool(((a - b).abs() <= 1e-5 * b.abs() + 1e-6 * float(b.abs().max()) + exp_error).all())


def test_a_failing_compiler_falls_back_to_the_eager_kernel(monkeypatch: pytest.MonkeyPatch) -> None:
    def broken_compile(fn: object, **kwargs: object) -> object:
        def call(*args: object) -> None:
            raise RuntimeError('no C++ compiler')

        return call

    monkeypatch.setattr(torch, 'compile', broken_compile)
    monkeypatch.setattr(kernel_compile, 'COMPILED', {})
    monkeypatch.setattr(kernel_compile, 'COMPILE_FAILED', set())
    sc = make_scene(40, 30, n_points=25)
    omega = np.isfinite(sc.multi)
    eager = interpolate(sc.single, sc.multi, omega, chunk_elements=100)
    fallen = interpolate(sc.single, sc.multi, omega, chunk_elements=100, compile_kernel=True)
    assert 'cpu' in kernel_compile.COMPILE_FAILED
    assert np.allclose(eager.offset, fallen.offset, atol=1e-6, equal_nan=True)
