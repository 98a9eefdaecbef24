"""The multi-view node's filter feed: every frame fed as it comes, keyframe estimates handed over."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest
from jumped_views import jumped_views

from depth_fusion_ros.multiview.filter import DepthFilter
from depth_fusion_ros.multiview.filter_config import FilterConfig
from depth_fusion_ros.multiview.semidense import MultiViewConfig
from depth_fusion_ros.nodes.multi_view_filter import FilterFeed

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _feed(max_queued: int = 100) -> tuple[FilterFeed, list[str], list[str]]:
    drops, errors = [], []
    feed = FilterFeed(FilterConfig(), MultiViewConfig(), 'cpu', max_queued, drops.append, errors.append)
    return feed, drops, errors


def test_keyframe_estimates_are_those_of_feeding_up_to_the_keyframe(small_sequence):
    """Frames after a keyframe, fed before the worker asks, do not change its estimate."""
    seq = small_sequence
    feed, drops, errors = _feed()
    keys = {2, 4}
    try:
        for frame in seq.frames:
            feed.append(frame, seq.camera, keyframe=frame.index in keys)
        got = {k: feed.result_for(seq.frames[k], seq.camera) for k in sorted(keys)}
        deadline = time.monotonic() + 30.0
        while not feed.idle() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert feed.fed == len(seq.frames)  # the frames after the last keyframe too
    finally:
        feed.close()
    reference = DepthFilter(seq.camera, FilterConfig(), MultiViewConfig(), 'cpu')
    for frame in seq.frames[: max(keys) + 1]:
        reference.process(frame.gray, frame.pose)
        if frame.index in keys:
            expected = reference.result(frame.pose)
            np.testing.assert_array_equal(got[frame.index].depth, expected.depth)
            assert np.isfinite(expected.depth).any()
    assert drops == [] and errors == []


def test_a_discarded_keyframe_is_not_kept_and_a_dropped_frame_fails_its_job(small_sequence):
    seq = small_sequence
    feed, drops, _ = _feed(max_queued=1)
    feed.close()  # no feed thread: the queue only fills
    feed.append(seq.frames[0], seq.camera, keyframe=True)
    feed.append(seq.frames[1], seq.camera)  # pushes the keyframe out: counted, its job fails
    assert len(drops) == 1 and 'dropped' in drops[0]
    with pytest.raises(RuntimeError, match='dropped'):
        feed.result_for(seq.frames[0], seq.camera)
    feed.discard(7)  # lost before the filter got there: never kept
    feed._keep(7, RuntimeError('late'))
    assert 7 not in feed._results


def test_a_closed_feed_fails_a_waiting_worker_at_once(small_sequence):
    feed, _, _ = _feed()
    feed.close()
    with pytest.raises(RuntimeError, match='shutting down'):
        feed.result_for(small_sequence.frames[3], small_sequence.camera)


def test_a_live_stream_that_outruns_the_filter_skips_old_frames_but_never_a_keyframe(small_sequence):
    seq = small_sequence
    drops, skips = [], []
    config, matching = FilterConfig(), MultiViewConfig()
    feed = FilterFeed(config, matching, 'cpu', 100, drops.append, max_lag=3, on_skip=skips.append)
    feed.close()  # no feed thread: the queue only fills, as behind a live camera
    for frame in seq.frames:  # 6 frames, frame 1 a keyframe
        feed.append(frame, seq.camera, keyframe=frame.index == 1)
    waiting = [(f.index, key) for f, _, key, _ in feed._frames]
    assert waiting == [(1, True), (4, False), (5, False)]  # the keyframe stays, the newest follow
    assert len(skips) == 3 and all('skipped' in s for s in skips) and drops == []


def test_a_rate_cap_passes_over_frames_between_updates_but_never_a_keyframe(small_sequence):
    """``filter.max_update_rate``: at 10 Hz a 30 Hz stream updates the filter with every third
    frame, and every keyframe, whatever its stamp; the keyframe's estimate is that of the
    frames actually fed."""
    seq = small_sequence
    stamps = [i / 30.0 for i in range(len(seq.frames))]
    keys, drops = {4}, []
    feed = FilterFeed(FilterConfig(), MultiViewConfig(), 'cpu', 100, drops.append, max_rate=10.0)
    try:
        for frame, stamp in zip(seq.frames, stamps, strict=True):
            frame = type(frame)(frame.index, stamp, frame.rgb, frame.pose)
            feed.append(frame, seq.camera, keyframe=frame.index in keys)
        got = feed.result_for(seq.frames[4], seq.camera)
        deadline = time.monotonic() + 30.0
        while not feed.idle() and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        feed.close()
    fed = [i for i in range(len(seq.frames)) if i % 3 == 0 or i in keys]
    assert feed.fed == len(fed) and feed.rate_skipped == len(seq.frames) - len(fed) and drops == []
    reference = DepthFilter(seq.camera, FilterConfig(), MultiViewConfig(), 'cpu')
    for i in [i for i in fed if i <= 4]:
        reference.process(seq.frames[i].gray, seq.frames[i].pose)
    np.testing.assert_array_equal(got.depth, reference.result(seq.frames[4].pose).depth)


def test_with_time_to_spare_the_capped_feed_updates_with_every_frame(small_sequence):
    """``filter.rate_cap_load``: the cap holds only while an update takes longer than that
    share of a frame interval. With a share no update reaches (100 intervals of a 30 Hz
    stream), every frame updates the filter and none is passed over; the feed's rule has
    measured both."""
    seq = small_sequence
    drops: list[str] = []
    feed = FilterFeed(
        FilterConfig(), MultiViewConfig(), 'cpu', 100, drops.append, max_rate=10.0, rate_cap_load=100.0
    )
    try:
        for frame in seq.frames:
            frame = type(frame)(frame.index, frame.index / 30.0, frame.rgb, frame.pose)
            feed.append(frame, seq.camera)
        deadline = time.monotonic() + 30.0
        while not feed.idle() and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        feed.close()
    assert feed.fed == len(seq.frames) and feed.rate_skipped == 0 and drops == []
    assert not feed.rate.loaded() and feed.rate.update_s > 0
    assert feed.rate.frame_gap_s == pytest.approx(1 / 30)


def test_the_feed_counts_the_filters_jumps_across_restarts(synthetic_sequence):
    """The node's diagnostics count the filter keyframes switched across a jump (the carried
    estimates confirmed again) over the feed's life, also after the filter starts over."""
    seq = synthetic_sequence
    feed, drops, errors = _feed()

    def settle() -> None:
        deadline = time.monotonic() + 60.0
        while not feed.idle() and time.monotonic() < deadline:
            time.sleep(0.01)

    try:
        for frame in [*seq.frames[:12], *jumped_views(seq, 11, 40.0, (0.05,))]:
            feed.append(frame, seq.camera)
        settle()
        assert feed.jumps == 1
        feed.restart(200)  # a new stream: the filter is built again, its count kept
        feed.append(dataclasses.replace(seq.frames[0], index=200), seq.camera)
        settle()
        assert feed.jumps == 1 and feed.filter is not None and feed.filter.stats.jumps == 0
    finally:
        feed.close()
    assert drops == [] and errors == []


def test_every_frame_is_consumed_once_whatever_the_feed_does_with_it(small_sequence):
    """``on_consumed`` (the node's "image handled" event, which paces a replay) hears every
    frame's token exactly once: updated, passed over by the rate cap, skipped behind a live
    stream or dropped from a full queue. A frame left out would stall a paced replay; one said
    twice would let it run ahead."""
    seq = small_sequence
    consumed: list[int] = []
    drops: list[str] = []
    stamps = [i / 30.0 for i in range(len(seq.frames))]
    frames = [type(f)(f.index, t, f.rgb, f.pose) for f, t in zip(seq.frames, stamps, strict=True)]
    config, matching = FilterConfig(), MultiViewConfig()
    feed = FilterFeed(config, matching, 'cpu', 100, drops.append, max_rate=10.0, on_consumed=consumed.append)
    try:
        for frame in frames:
            feed.append(frame, seq.camera, keyframe=frame.index == 4, token=1000 + frame.index)
        feed.result_for(frames[4], seq.camera)
        deadline = time.monotonic() + 30.0
        while len(consumed) < len(frames) and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        feed.close()
    assert consumed == [1000 + f.index for f in frames]  # in order, each once
    assert feed.rate_skipped > 0 and feed.fed > 0  # both kinds were consumed

    done: list[int] = []
    full: list[str] = []
    skips: list[str] = []
    behind = FilterFeed(
        config, matching, 'cpu', 2, full.append, max_lag=2, on_skip=skips.append, on_consumed=done.append
    )
    behind.close()  # no feed thread: the queue only fills, skipping behind the stream and dropping
    for frame in frames:  # frames 1-3 keyframes: the lag skips 0, 4 and 5, the queue of 2 drops 1
        behind.append(frame, seq.camera, keyframe=frame.index in (1, 2, 3), token=frame.index)
    assert [item.token for item in behind._frames] == [2, 3]
    assert sorted(done) == [0, 1, 4, 5] and len(skips) == 3 and len(full) == 1
    assert drops == []


def test_a_keyframe_is_published_with_the_focal_uncertainty_the_node_hands_in(small_sequence):
    """The node hands in its focal check's uncertainty (``FocalCheckRunner.uncertainty``), read at
    each keyframe: the estimate's std is a filter's with that uncertainty, not the prior's."""
    seq = small_sequence
    feed, drops, errors = _feed()
    feed.focal_uncertainty = lambda: 0.0  # as a check that verified the focal length exactly
    key = 4
    try:
        for frame in seq.frames[: key + 1]:
            feed.append(frame, seq.camera, keyframe=frame.index == key)
        got = feed.result_for(seq.frames[key], seq.camera)
    finally:
        feed.close()
    stds = {}
    for uncertainty in (0.0, FilterConfig().focal_uncertainty):
        config = FilterConfig(focal_uncertainty=uncertainty)
        reference = DepthFilter(seq.camera, config, MultiViewConfig(), 'cpu')
        for frame in seq.frames[: key + 1]:
            reference.process(frame.gray, frame.pose)
        stds[uncertainty] = reference.result(seq.frames[key].pose).depth_std
    np.testing.assert_array_equal(got.depth_std, stds[0.0])
    assert not np.array_equal(stds[0.0], stds[FilterConfig().focal_uncertainty], equal_nan=True)
    assert drops == [] and errors == []
