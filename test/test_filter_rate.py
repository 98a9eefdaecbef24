"""The filter's update rate on a live camera: every frame while there is time, the cap when not."""

from __future__ import annotations

import itertools

import pytest

from depth_fusion_ros.nodes.filter_rate import UpdateRate


def _stream(rate: UpdateRate, seconds_per_update: float, frames: int = 60, fps: float = 30.0) -> list[int]:
    """Feed ``frames`` non-keyframes at ``fps``; each update takes ``seconds_per_update``; the
    indices that updated."""
    updated = []
    for i in range(frames):
        stamp = 100.0 + i / fps
        rate.seen(stamp)
        if not rate.too_soon(stamp):
            rate.updated(stamp, seconds_per_update)
            updated.append(i)
    return updated


def test_a_quiet_machine_updates_with_every_frame():
    rate = UpdateRate(max_rate=10.0, load_share=1.0)
    assert _stream(rate, 0.011) == list(range(60))  # 11 ms of a 33 ms interval
    assert not rate.loaded() and rate.frame_gap_s == pytest.approx(1 / 30)


def test_a_loaded_machine_keeps_the_cap():
    rate = UpdateRate(max_rate=10.0, load_share=1.0)
    updated = _stream(rate, 0.040)  # 40 ms of a 33 ms interval: it cannot keep up
    assert rate.loaded()
    later = [i for i in updated if i >= 10]
    assert all(b - a == 3 for a, b in itertools.pairwise(later))  # 10 Hz of a 30 Hz stream


def test_share_zero_is_the_cap_always():
    always = UpdateRate(max_rate=10.0, load_share=0.0)
    assert always.loaded()
    assert _stream(always, 0.001)[:4] == [0, 3, 6, 9]
    off = UpdateRate(max_rate=0.0, load_share=0.0)  # no cap at all: every frame
    assert _stream(off, 0.5) == list(range(60))


def test_the_rule_follows_the_load_and_a_new_stream_starts_with_an_update():
    rate = UpdateRate(max_rate=10.0, load_share=1.0)
    _stream(rate, 0.011, frames=30)
    assert not rate.loaded()
    _stream(rate, 0.040, frames=30)  # the same stream, later: the machine got busy
    assert rate.loaded()
    rate.reset()
    rate.seen(500.0)
    assert not rate.too_soon(500.0)  # the first frame of a new stream is never passed over
    rate.updated(500.0, 0.040)
    rate.seen(500.0 + 1 / 30)
    assert rate.too_soon(500.0 + 1 / 30)


def test_frames_the_feed_skips_still_count_for_the_interval():
    """A feed that is behind skips frames before the rule sees them; the interval is the
    stream's (every arrival), not that of the frames the feed reached, so the cap holds."""
    rate = UpdateRate(max_rate=10.0, load_share=1.0)
    for i in range(60):
        stamp = 100.0 + i / 30.0
        rate.seen(stamp)
        if i % 3 == 0:  # only every third frame reached the feed
            rate.updated(stamp, 0.040)
    assert rate.frame_gap_s == pytest.approx(1 / 30) and rate.loaded()


@pytest.mark.parametrize(('max_rate', 'share'), [(-1.0, 0.5), (10.0, -0.1)])
def test_bad_settings_raise(max_rate, share):
    with pytest.raises(ValueError, match='max_update_rate and rate_cap_load'):
        UpdateRate(max_rate, share)
