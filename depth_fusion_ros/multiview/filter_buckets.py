"""Which search each keyframe row gets: buckets by the length of its interval in pixels.

A frame's searches run in a few buckets, each one ``grid_sample`` call with its own sample
count (``filter_search.search_interval``): the shorter a row's interval along the epipolar
line, the fewer samples it needs. This file says which buckets there are and which rows go
into each; ``filter_frame_update.search_rows`` runs them.
"""

from __future__ import annotations

import torch

from ..true_indices import true_indices
from .filter_config import FilterConfig


def search_buckets(config: FilterConfig) -> tuple[tuple[int, int, bool], ...]:
    """``(samples, refine, distinctiveness)`` of the search buckets, by increasing interval.

    ``verify`` (a converged estimate at the ``min_search_px`` floor), ``short`` (an
    estimate), ``medium`` (at most ``medium_samples - 1`` px: one sample a pixel, no
    refinement) and ``long`` (``long_samples``, then ``refine_samples`` each side of the best).
    Wherever the interval allows, the samples are no denser than the cost's basin needs: more
    would only sample the same basin again. Each bucket is one ``grid_sample``: more buckets
    would save samples but add a fixed cost per frame (tried: a 16-sample refined bucket up to
    30 px saved 1.5 % of the samples).
    """
    c = config
    return (
        (c.verify_samples, 0, False),
        (c.short_samples, 0, False),
        (c.medium_samples, 0, True),
        (c.long_samples, c.refine_samples, True),
    )


def bucket_limits(config: FilterConfig) -> tuple[float, float, float]:
    """The interval lengths (px) at most of the ``short``, ``verify`` and ``medium`` buckets
    (:func:`bucket_members`' tests; the native searches, ``native_rows``, take the same). The
    verify and medium limits carry a tolerance: the floor, computed, lands a rounding error
    above its length."""
    c = config
    tolerance = 1.0 + 1e-4
    verify = (c.verify_samples - 1) * c.max_step_px * tolerance
    medium = (c.medium_samples - 1) * c.max_step_px * tolerance
    return c.short_samples * c.max_step_px, verify, medium


def bucket_members(span_px: torch.Tensor, fresh: torch.Tensor, config: FilterConfig) -> list[torch.Tensor]:
    """Rows of each bucket of :func:`search_buckets`, in row order, from each search's interval
    length in px.

    ``span_px``: the interval's length along the epipolar line (for a whole-range search the
    largest epipolar motion at its ends times its length, so no sample step exceeds it);
    ``fresh``: pixels without an estimate, which always get a distinctiveness test. The first
    bucket whose test a row passes takes it (verify, short, medium, else long). Straight from
    the tests' masks: on CPU a bucket index per row (three ``where`` into int64, then a
    comparison and a ``nonzero`` per bucket) cost more (with the indices: 14.5 against 9.4 ms
    over TUM's 37 frames, ``torch.profiler``, one thread, part of it ``true_indices``' share).
    """
    c = config
    short_px, verify_px, medium_px = bucket_limits(c)
    known = ~fresh
    short = known & (span_px <= short_px)
    if c.verify_samples:
        verify = known & (span_px <= verify_px)
        not_verify = ~verify
        short &= not_verify
    else:
        verify = not_verify = None
    rest = ~short if not_verify is None else ~short & not_verify  # neither verify nor short
    if c.medium_samples:
        medium = span_px <= medium_px
        long = rest & ~medium
        medium &= rest
    else:
        medium, long = None, rest
    return [
        true_indices(m) if m is not None else span_px.new_zeros(0, dtype=torch.long)
        for m in (verify, short, medium, long)
    ]
