"""What makes the depth filter's frame cheap: the search kernel, its buckets and the seed bracket.

Each is checked against what it replaces: the kernel against the sweep's own cost
(``cost_volume.sample_cost``) and a plain second-best loop, the buckets against the intervals
they are planned for, the bracket against whole-range seeding on the synthetic room.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch
from bucket_index import plan_buckets

import depth_fusion_ros.multiview.filter as filter_module
from depth_fusion_ros.multiview.cost_volume import EpipolarRays, sample_cost
from depth_fusion_ros.multiview.filter import DepthFilter
from depth_fusion_ros.multiview.filter_buckets import search_buckets
from depth_fusion_ros.multiview.filter_config import FilterConfig
from depth_fusion_ros.multiview.filter_search import (
    _distinctiveness,
    _lookup,
    frame_cost,
    search_interval,
)

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _random_rays(rows: int, width: int = 80, height: int = 60) -> tuple[torch.Tensor, EpipolarRays]:
    gen = torch.Generator().manual_seed(0)
    u = torch.rand(rows, generator=gen) * (width - 10) + 5
    v = torch.rand(rows, generator=gen) * (height - 10) + 5
    a = torch.stack((u, v, torch.ones(rows)), dim=1)[None]
    key = torch.randn(6, rows, generator=gen)
    return key / key.norm(dim=0), EpipolarRays(a, torch.tensor([[30.0, 3.0, 0.5]]), width, height)


def _descriptors(width: int = 80, height: int = 60) -> torch.Tensor:
    desc = torch.randn(1, 7, height, width, generator=torch.Generator().manual_seed(1))
    desc[0, 6] = 0.0
    desc[0, 6, 3:-3, 3:-3] = 1.0  # the visibility band, as patch_descriptors makes it
    return desc


def test_frame_cost_is_the_sweeps_cost_for_one_frame():
    key, rays = _random_rays(500)
    desc = _descriptors()
    rho = torch.linspace(0.1, 3.0, 12)[None, :].expand(500, 12).contiguous()
    ours = frame_cost(key, desc, rays, rho)
    reference, count = sample_cost(key, desc, rays, rho)
    reference = torch.where(count >= 0.5, reference, torch.full_like(reference, math.inf))
    seen = torch.isfinite(reference)
    assert torch.equal(torch.isfinite(ours), seen) and seen.float().mean() > 0.3
    assert torch.allclose(ours[seen], reference[seen], atol=1e-5)


@pytest.mark.parametrize('samples', [6, 7, 12])
def test_lookups_split_over_threads_are_bit_identical(samples):
    """The frame's lookups split into one batch per thread (ATen's CPU grid_sample spreads
    over batches only) give the very numbers of one batch, in the same order; an odd sample
    count that two threads cannot split falls back to one batch."""
    desc = _descriptors()
    grid = torch.rand(1, samples, 300, 2, generator=torch.Generator().manual_seed(2)) * 2.2 - 1.1
    single = torch.nn.functional.grid_sample(desc, grid, mode='bilinear', align_corners=True)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        split = _lookup(desc, grid)
    finally:
        torch.set_num_threads(before)
    assert split.shape[0] == (1 if samples % 2 else 2)
    assert torch.equal(split.transpose(0, 1).reshape(single.shape[1:])[None], single)


def test_distinctiveness_is_the_second_best_local_minimum_ratio():
    gen = torch.Generator().manual_seed(2)
    cost = torch.rand(300, 9, generator=gen) + 0.1
    cost[:5] = torch.linspace(0.2, 1.0, 9)[None, :]  # a single basin: falls back to the largest
    cost[5, 4] = math.inf  # an invisible sample
    c1, best = cost.min(dim=1)
    ours = _distinctiveness(cost.T.contiguous(), best, c1)  # the search works samples-first
    for r in range(cost.shape[0]):
        col = cost[r].tolist()
        padded = [math.inf, *col, math.inf]
        minima = [
            col[s]
            for s in range(len(col))
            if col[s] <= padded[s] and col[s] <= padded[s + 2] and abs(s - int(best[r])) > 1
        ]
        c2 = min(minima, default=math.inf)
        if not math.isfinite(c2):
            c2 = max(c for c in col if math.isfinite(c))
        expected = min(max(1.0 - float(c1[r]) / max(c2, 1e-6), 0.0), 1.0)
        assert float(ours[r]) == pytest.approx(expected, abs=1e-6), r


def test_search_finds_a_planted_minimum_in_every_bucket():
    """A cost with one sharp minimum along each row's line: every bucket's search finds it."""
    rows, width, height = 200, 80, 60
    key, rays = _random_rays(rows, width, height)
    desc = _descriptors(width, height)
    # Plant the key descriptor at each row's true match (rho_true), so the ZNCC peaks there.
    rho_true = torch.full((rows,), 0.8)
    u, v, _ = (t[0, :, 0] for t in rays.project(rho_true[:, None]))
    ui, vi = u.round().long(), v.round().long()
    inside = (ui > 4) & (ui < width - 5) & (vi > 4) & (vi < height - 5)
    desc[0, :6, vi[inside], ui[inside]] = key[:, inside]
    rho_true = rays_rho_at_pixel(rays, ui.float(), rho_true)
    for samples, refine, distinct in search_buckets(FilterConfig()):
        found = search_interval(
            key, desc, rays, rho_true - 0.05, rho_true + 0.05, samples, refine, 1 << 22, distinct
        )
        ok = found.ok & inside
        assert ok.float().mean() > 0.5 * inside.float().mean(), samples
        err = (found.rho - rho_true)[ok].abs() * torch.hypot(*(t[0] for t in rays.motion(rho_true)))[ok]
        assert float(torch.median(err)) < 0.75, (samples, float(torch.median(err)))  # px along the line


def test_a_minimum_outside_the_interval_is_no_measurement(monkeypatch):
    """A cost whose minimum lies below some rows' intervals: their best sample is the interval's
    lower end. With ``reject_edges`` that is not ``ok`` (the filter takes it as an outlier vote);
    without, the parabola clamped to the end passed it as a match (the old behaviour). Rows
    whose minimum lies inside are found either way. Every bucket (refined or not)."""
    import depth_fusion_ros.multiview.filter_search as search_module

    rows = 100
    key, rays = _random_rays(rows)
    truth = torch.full((rows,), 1.0)
    truth[::2] = 0.5  # below [0.8, 1.2] for the even rows
    # A smooth basin around each row's truth (samples-first, as the kernel computes it), through
    # the torch search (the native one computes the real cost).
    monkeypatch.setattr(search_module, 'native_frame_search', lambda *args: None)
    monkeypatch.setattr(
        search_module,
        '_frame_cost',
        lambda kd, fd, a, b, rho: 0.05 + (rho - truth[None, : rho.shape[1]]) ** 2,
    )
    lo, hi = torch.full((rows,), 0.8), torch.full((rows,), 1.2)
    outside = truth < lo
    for samples, refine, distinct in search_buckets(FilterConfig()):
        args = (key, _descriptors(), rays, lo, hi, samples, refine, 1 << 22, distinct)
        old = search_interval(*args)
        new = search_interval(*args, reject_edges=True)
        assert bool(old.ok[outside].all()) and not bool(new.ok[outside].any()), samples
        assert bool(new.ok[~outside].all()), samples
        assert torch.allclose(new.rho[~outside], truth[~outside], atol=1e-4), samples


def rays_rho_at_pixel(rays: EpipolarRays, u: torch.Tensor, rho: torch.Tensor) -> torch.Tensor:
    """Inverse depth at which each row's line reaches column ``u`` (the planted pixel)."""
    a, b = rays.a[0], rays.b[0]
    # u = (a0 + rho b0) / (a2 + rho b2)  =>  rho = (u a2 - a0) / (b0 - u b2)
    return (u * a[:, 2] - a[:, 0]) / (b[0] - u * b[2])


def test_buckets_follow_the_interval_length():
    c = FilterConfig()
    span = torch.tensor([2.5, 2.5, 7.0, 7.0, 14.0, 14.0, 100.0, 100.0])
    fresh = torch.tensor([False, True, False, True, False, True, False, True])
    bucket = plan_buckets(span, fresh, c).tolist()
    # verify (floor of a converged estimate), short, medium, long; a new pixel: never without
    # the distinctiveness test (medium or long).
    assert bucket == [0, 2, 1, 2, 2, 2, 3, 3]
    assert [s for s, _, _ in search_buckets(c)] == [
        c.verify_samples,
        c.short_samples,
        c.medium_samples,
        c.long_samples,
    ]
    off = FilterConfig(verify_samples=0, medium_samples=0)
    assert plan_buckets(span, fresh, off).tolist() == [1, 3, 1, 3, 3, 3, 3, 3]
    with pytest.raises(ValueError, match=r'filter\.medium_samples'):
        FilterConfig(medium_samples=4).validate()
    with pytest.raises(ValueError, match=r'filter\.verify_samples'):
        FilterConfig(verify_samples=9).validate()


def _long_rows_and_accuracy(seq, radius: int, monkeypatch) -> tuple[int, float]:
    """Whole-range (long) search rows over the first frames, and the median AbsRel of the
    published estimates after them (warped into the last frame)."""
    counted = []
    real = filter_module.search_interval
    config = FilterConfig(seed_radius=radius)

    def counting(key_desc, desc, rays, lo, hi, samples, *args, **kwargs):
        if samples == config.long_samples:
            counted.append(key_desc.shape[1])
        return real(key_desc, desc, rays, lo, hi, samples, *args, **kwargs)

    monkeypatch.setattr(filter_module, 'search_interval', counting)
    f = DepthFilter(seq.camera, config)
    frames = seq.frames[:14]  # two keyframe switches
    for fr in frames:
        f.process(fr.gray, fr.pose)
    r = f.result(frames[-1].pose)
    gt = seq.gt_depth_working(len(frames) - 1)
    ok = np.isfinite(r.depth) & np.isfinite(gt) & (gt > 0)
    return sum(counted), float(np.median(np.abs(r.depth[ok] - gt[ok]) / gt[ok]))


def test_bracketed_seeds_save_whole_range_searches(synthetic_sequence, monkeypatch):
    """A new pixel next to measured ones is first searched over their range: fewer
    whole-range searches for estimates as accurate."""
    long_off, err_off = _long_rows_and_accuracy(synthetic_sequence, 0, monkeypatch)
    long_on, err_on = _long_rows_and_accuracy(synthetic_sequence, FilterConfig().seed_radius, monkeypatch)
    assert long_on < 0.95 * long_off, (long_on, long_off)
    assert err_on < 1.1 * err_off + 1e-3, (err_on, err_off)


def test_stage_clock_splits_the_frame_and_changes_nothing(synthetic_sequence):
    """The bench's per-stage breakdown: the stages of every frame add up to the frame, a
    keyframe switch charges its propagation and seeding separately, and switching the clock
    on leaves every estimate bit for bit as it was."""
    frames = synthetic_sequence.frames[:8]
    plain = DepthFilter(synthetic_sequence.camera)
    timed = DepthFilter(synthetic_sequence.camera)
    timed.clock.enabled = True
    spent = 0.0
    for frame in frames:
        plain.process(frame.gray, frame.pose)
        before = sum(timed.clock.seconds.values())
        t0 = time.process_time()
        timed.process(frame.gray, frame.pose)
        spent += time.process_time() - t0
        assert sum(timed.clock.seconds.values()) >= before
    seconds = timed.clock.seconds
    assert {'descriptors', 'selection', 'search', 'update', 'other'} <= set(seconds)
    if timed.stats.keyframes > 1:
        assert {'propagation', 'seed search'} <= set(seconds)
    assert sum(seconds.values()) == pytest.approx(spent, rel=0.05, abs=5e-3)
    assert torch.equal(plain.key.state.mu, timed.key.state.mu)
    assert torch.equal(plain.key.updates, timed.key.updates)


def test_first_minimum_matches_torch_min():
    """``_min0`` (amin, compare, amax) gives ``min(dim=0)``'s values and first indices: ties,
    all-inf columns and NaN included."""
    from depth_fusion_ros.multiview.filter_search import _min0

    torch.manual_seed(0)
    cost = torch.rand(6, 500).mul_(4).round_()  # many ties
    cost[:, :20] = math.inf
    cost[2, 20:40] = math.inf
    for c in (cost, torch.cat((cost, torch.full((6, 1), math.nan)), dim=1)):
        ref = c.min(dim=0)
        values, first = _min0(c)
        assert torch.equal(values.nan_to_num(-1.0), ref.values.nan_to_num(-1.0))
        assert torch.equal(first, ref.indices)


@pytest.mark.parametrize('patch', ['box', 'cross'])
def test_channels_last_descriptors_are_the_same_numbers(patch: str) -> None:
    """The filter's frame descriptors are written channels-last by the projection itself (no
    copy of the finished ones): the same values, visibility band included, in that layout."""
    from depth_fusion_ros.multiview.descriptors import patch_descriptors

    images = torch.rand(2, 30, 40, generator=torch.Generator().manual_seed(3))
    planar = patch_descriptors(images, patch, visibility_margin=3, channels=4)
    last = patch_descriptors(images, patch, visibility_margin=3, channels=4, channels_last=True)
    assert last.is_contiguous(memory_format=torch.channels_last)
    assert not planar.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(last, planar, rtol=0, atol=0)


def test_the_bench_ratio_pairs_each_filter_pass_with_the_sweep_timed_after_it(monkeypatch):
    """On a machine whose speed drifts, the filter / sweep ratio compares each pass of the
    filter with a sweep timed right after it (median of those ratios), not the median pass
    with a median sweep timed at another moment: here the machine slows down pass after pass,
    which leaves every paired ratio at 0.2, while the median pass against sweeps timed after
    the last pass (as the bench did) would say 0.1."""
    from depth_fusion_ros.bench import BenchOptions
    from depth_fusion_ros.bench import multi_view_filter as bench_filter

    speed = iter([1.0, 1.0, 0.5, 0.25])  # the warm-up pass, then three passes
    now = {'factor': 1.0}

    def fake_stream(seq, device, config=None):
        now['factor'] = next(speed)
        frame = 0.02 / now['factor']
        return [frame] * 5, [frame] * 5, DepthFilter(seq.camera, config)

    monkeypatch.setattr(bench_filter, 'stream_seconds', fake_stream)
    monkeypatch.setattr(bench_filter, '_sweep_seconds', lambda seq, key, device: (0.1 / now['factor'],) * 2)
    monkeypatch.setattr(bench_filter, 'estimate_semidense', lambda *a, **k: None)
    monkeypatch.setattr(bench_filter, '_keyframe_inputs', lambda seq, key: ())
    monkeypatch.setattr(bench_filter, '_stage_rows', lambda label, seq, device: [])

    class Seq:
        camera = filter_module.PinholeCamera(100.0, 100.0, 40.0, 30.0, 80, 60)

        def __len__(self) -> int:
            return 5

    rows, _ = bench_filter._cost_rows('fake', Seq(), BenchOptions(repeats=3))
    ratio = {r.name: r.value for r in rows}
    assert ratio['fake: filter per frame / sweep per keyframe (CPU)'] == pytest.approx(0.2)
    assert ratio['fake: filter per frame / sweep per keyframe (wall)'] == pytest.approx(0.2)


@pytest.mark.parametrize(
    ('patch', 'stride', 'channels', 'margin'), [('box', 2, 6, 3), ('cross', 1, 0, None), ('box', 1, 8, 0)]
)
def test_opencv_descriptors_match_the_torch_ones(
    patch: str, stride: int, channels: int, margin: int | None
) -> None:
    """On a CPU the descriptors come from OpenCV (a filter2D per channel, the planes merged
    channels-last); the torch code CUDA runs gives the same numbers to float32 rounding,
    border band and visibility channel included, in both layouts."""
    from depth_fusion_ros.multiview import descriptors

    images = descriptors.gaussian_blur(torch.rand(2, 30, 40, generator=torch.Generator().manual_seed(5)), 0.5)
    # Two images, and one (a filter frame's: written as the native kernels' table where its
    # channels fit one block, native_cost._table_in_place; a pixel's channels adjoin either way).
    for batch, channels_last in ((images, False), (images, True), (images[:1], True)):
        spec = descriptors._Spec(patch, stride, 0.01, margin, channels, channels_last)
        fast = descriptors._opencv_descriptors(batch, spec)
        reference = descriptors._torch_descriptors(batch, spec)
        assert fast.shape == reference.shape
        assert (fast.stride(1) == 1) == channels_last
        torch.testing.assert_close(fast, reference, rtol=1e-5, atol=3e-6)
