"""The stream's scale between a metric single view and the multi-view points, taken when they disagree.

Why: stage 2 trusts a metric network's scale to a factor of ``metric_scale_range`` (2) per
keyframe, and the interpolation bends the single view onto the points only near them (the
certainty floor, the guard's reach). Two common sources break that on a whole stream:

* **poses not in metres**: a monocular SLAM (ORB-SLAM3 mono, DSO, ...) gives positions in a
  unit its initialisation chose, often a third of a metre; the multi-view depth is in that
  unit. 7-Scenes 0-499 with its positions scaled by 0.3, live: every keyframe but 4 fell back
  to the single view (stage 2 found no plausible scale), and what was published was in
  metres against poses in another unit (a map built from it is nothing);
* **a network off in scale on this camera**: the shipped network reads TUM fr1_xyz about 2x
  too far (the points' scale 0.40-0.56 of it, live). The fusion then corrects the depth near
  the points and leaves it 2x too far between them: two scales in one image.

Both show the same way: over several keyframes, the points sit at one factor of the single
view, well away from 1, and agree on it. The multi-view depth is the poses' own unit (it is
triangulated from them), so the single view is then scaled into it, for the rest of the
stream, before each keyframe is fused: ``s <- u s`` (``u`` below). Nothing changes where the
factor stays within ``engage_ratio`` of 1 (a metric pose source and a network about right in
scale: the per-keyframe fusion as before).

Per keyframe the factor is the median of ``m / s`` over the stage-1 points; a keyframe counts
only if at least ``min_share`` of its points lie within ``relative_tolerance`` of that factor
(one consensus, not two clusters) and it has ``min_points``. The stream's factor is taken
once ``min_keyframes`` of the last ``window`` counted keyframes agree (every log factor within
``max_spread`` of their median) and their median is beyond ``engage_ratio``.
From then on, for the rest of the stream, each keyframe is scaled by its own factor where it
counts and lies within ``max_spread`` of the window's median (a network that adapts to the
points moves towards 1 between keyframes, and a median would lag it), else by that median; a
stream whose stamps go back starts over.

**A keyframe off the stream** (``max_jump``): the same factors judge each keyframe's points
against the stream's. A metric network's scale moves with the view, but slowly; the points
are in the poses' unit. So a keyframe whose factor lies beyond ``max_jump`` (1.8) of the median
of the window before it (at least ``min_keyframes`` factors) has points that disagree with the
stream as a whole, and the fusion keeps its single view (``single_view``, reason
``scale_jump``; ``pipeline.fuse_keyframe``). Measured: a SLAM keyframe stream (15 cm and 7 deg a
frame, 0.3 deg of rotation noise) whose floor is papered with wavy stripes, where 74-83 % of a
keyframe's points matched a wave a period along the line (2-3 measurements each, frames at
equal baselines agree on the alias), read 0.43 against 1.0-1.08 on the keyframes around it,
and fused 2.6-2.8x its input (docs/fusion.md, "A keyframe off the stream"). The jumped factor
still joins the window, so a stream whose scale really moves (a network adapting to the points)
is judged against its new level after a few keyframes. After a step forward of
``NEW_STREAM_STEPS`` keyframe periods (another sequence played into running nodes, or a camera
that stopped a while) no keyframe is judged until ``min_keyframes`` have come since; the stream's
factor itself is kept (a monocular SLAM's unit does not change with a pause).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from ..check_modes import check_mode
from .subsample import seeded_subsample

log = logging.getLogger(__name__)

#: A step between keyframe stamps at least this many times the median of the recent steps
#: (and at least three of them seen) may begin another stream (multi_view_node's image gap
#: rule: 10 of its recent periods): another sequence played into the running nodes with later
#: stamps, whose network and points need not share the last one's ratio. Keyframes are judged
#: again once ``min_keyframes`` have come after it.
NEW_STREAM_STEPS = 10.0

STREAM_SCALE_PARAMETER_DESCRIPTIONS = {
    'mode': (
        'a metric single view whose scale the multi-view points disagree with over the stream (poses not '
        'in metres, e.g. a monocular SLAM; or a network off in scale on this camera): correct (scale the '
        "single view into the poses' unit before fusing, noted once as stream_scale), warn (note it "
        'only), off'
    ),
    'window': "keyframes whose factors (median multi-view / single-view depth) make the stream's",
    'min_keyframes': "counted keyframes in the window before the stream's factor is judged",
    'engage_ratio': 'the factor is taken once it is beyond this ratio of 1 (either way)',
    'max_spread': 'every keyframe factor of the window must lie within this (log) of their median',
    'min_points': 'stage-1 points a keyframe needs to count',
    'min_share': "share of a keyframe's points within relative_tolerance of its factor for it to count",
    'relative_tolerance': "relative distance of a point from the keyframe's factor that still agrees",
    'max_jump': "a keyframe whose factor is beyond this ratio of the median of the window's factors before "
    'it (at least min_keyframes) keeps its single view (decision single_view, scale_jump): its points '
    'disagree with the stream (also with mode off); 0: off',
}


@dataclass(frozen=True)
class StreamScaleConfig:
    """Thresholds of :class:`StreamScale` (the ``stream_scale.*`` parameters of fusion_node)."""

    mode: str = 'correct'
    window: int = 5
    min_keyframes: int = 3
    #: 2, stage 2's ``metric_scale_range``: within it each keyframe's own fit takes the scale
    #: (and the adaptation learns it); beyond it no keyframe can be fused. 1.5 was tried: a
    #: real stream's network is off in scale by view, not by stream (7-Scenes played
    #: backwards, live: 5-keyframe stretches at 0.52-0.62, taken, then 12 keyframes above
    #: their input against none), docs/fusion.md "The stream's scale".
    engage_ratio: float = 2.0
    #: 0.25 (x1.28 either way): TUM fr1_xyz's first five factors lie within 0.18 of theirs.
    max_spread: float = 0.25
    min_points: int = 200
    min_share: float = 0.5
    relative_tolerance: float = 0.35
    #: 1.8 (0.59 in log): between the largest jump of a keyframe that fused well, 0.48 (1.62x,
    #: over 674 other keyframes of 47 stress streams; 0.43 on the real sequences, live and played
    #: backwards), and the wrong ones of the striped-floor SLAM stream, 0.76-0.77 (2.13x). 2
    #: (stage 2's ``metric_scale_range``) left 0.06 of margin on the wrong side (docs/fusion.md,
    #: "A keyframe off the stream"). A keyframe judged off wrongly keeps its single view: a gain
    #: lost, never a loss.
    max_jump: float = 1.8
    #: Points a keyframe's factor is computed from at most (a seeded subsample: the median
    #: of 4096 is as good as of 16k, at a quarter of the cost).
    sample: int = 4096

    def __post_init__(self) -> None:
        object.__setattr__(self, 'mode', check_mode('stream_scale', self.mode))
        if not 1 <= self.min_keyframes <= self.window:
            raise ValueError(
                f'stream_scale.min_keyframes must be in [1, window={self.window}], got {self.min_keyframes}'
            )
        if not (math.isfinite(self.engage_ratio) and self.engage_ratio > 1.0):
            raise ValueError(f'stream_scale.engage_ratio must be a number > 1, got {self.engage_ratio}')
        for name in ('max_spread', 'relative_tolerance'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f'stream_scale.{name} must be a positive number, got {value}')
        if not (self.max_jump == 0.0 or (math.isfinite(self.max_jump) and self.max_jump > 1.0)):
            raise ValueError(f'stream_scale.max_jump must be 0 (off) or a number > 1, got {self.max_jump}')
        if not 0.0 <= self.min_share <= 1.0:
            raise ValueError(f'stream_scale.min_share must be in [0, 1], got {self.min_share}')
        if self.min_points < 1 or self.sample < 1:
            raise ValueError('stream_scale.min_points and stream_scale.sample must be >= 1')


def keyframe_factor(
    single: np.ndarray, mv_depth: np.ndarray, stage1: np.ndarray | None, config: StreamScaleConfig
) -> float | None:
    """The median ``m / s`` of one keyframe's stage-1 points, or None when it does not count
    (fewer than ``min_points``, or fewer than ``min_share`` of them within
    ``relative_tolerance`` of the median: no single consensus). Images of different sizes
    count for nothing here: the fusion refuses them, naming them."""
    shape = np.shape(single)
    if np.shape(mv_depth) != shape or (stage1 is not None and np.shape(stage1) != shape):
        return None
    with np.errstate(invalid='ignore'):
        usable = np.isfinite(single) & (single > 0) & np.isfinite(mv_depth) & (mv_depth > 0)
    if stage1 is not None:
        usable &= stage1
    index = np.flatnonzero(usable)
    if index.size < config.min_points:
        return None
    if index.size > config.sample:
        index = index[seeded_subsample(index.size, config.sample, 0)]
    ratio = mv_depth.ravel()[index].astype(np.float64) / single.ravel()[index]
    factor = float(np.median(ratio))
    share = float(np.mean(np.abs(ratio / factor - 1.0) <= config.relative_tolerance))
    return factor if share >= config.min_share else None


class StreamScale:
    """The stream's factor from the single view to the points' unit (1 until taken)."""

    def __init__(self, config: StreamScaleConfig | None = None) -> None:
        self.config = config or StreamScaleConfig()
        self.reset()

    def reset(self) -> None:
        """Forget the stream (a new one began)."""
        self.factors: deque[float] = deque(maxlen=self.config.window)
        self.taken = False
        self.disagrees = False
        self.last_stamp: int | None = None
        self._steps: deque[int] = deque(maxlen=2 * self.config.window)
        #: The last keyframe's own factor (None where it did not count).
        self.current: float | None = None
        #: The last keyframe's log factor less the log median of the window before it (None
        #: where either is missing): :attr:`jumped`.
        self.jump: float | None = None
        self._jump_centre = float('nan')
        #: Factors counted since the last gap of ``NEW_STREAM_STEPS`` (None: no gap).
        self._since_gap: int | None = None

    def _median(self) -> float:
        """The median factor of the window (NaN when empty)."""
        return float(np.exp(np.median(np.log(self.factors)))) if self.factors else float('nan')

    @property
    def factor(self) -> float:
        """What the single view is multiplied by before fusing: 1 unless taken (``correct``);
        then the last keyframe's own factor where it counted and lies within ``max_spread`` of
        the window's median (no lag behind a network that adapts to the points), else that
        median (a keyframe whose points did not agree, or one far off the stream)."""
        if not self.taken or not self.factors:
            return 1.0
        centre = self._median()
        if self.current is not None and abs(np.log(self.current / centre)) <= self.config.max_spread:
            return float(self.current)
        return centre

    def observe(
        self,
        single: np.ndarray,
        mv_depth: np.ndarray,
        stage1: np.ndarray | None,
        stamp: int | None = None,
    ) -> bool:
        """Take one keyframe's factor into the window (raw single view: before any factor).

        Returns True on the keyframe where the stream is first found to disagree (the caller
        notes it once, with :meth:`describe`). A ``stamp`` older than the last starts over, one
        far ahead pauses the jump judgement (:meth:`_new_stream`); the last one again is not
        taken twice (``evaluate`` fuses a keyframe once per method).
        """
        if stamp is not None and stamp == self.last_stamp:
            return False
        if self.config.mode == 'off' and self.config.max_jump == 0.0:
            return False
        if stamp is not None:
            self._new_stream(stamp)
            self.last_stamp = stamp
        factor = keyframe_factor(single, mv_depth, stage1, self.config)
        self.current = factor
        self.jump = None
        if factor is None:
            return False
        settled = self._since_gap is None or self._since_gap >= self.config.min_keyframes
        if settled and len(self.factors) >= self.config.min_keyframes:
            self._jump_centre = self._median()
            self.jump = math.log(factor / self._jump_centre)
        self.factors.append(factor)
        if self._since_gap is not None:
            self._since_gap += 1
        if self.disagrees or self.config.mode == 'off':
            return False
        if len(self.factors) < self.config.min_keyframes:
            return False
        logs = np.log(np.asarray(self.factors))
        centre = float(np.median(logs))
        spread = float(np.max(np.abs(logs - centre)))
        if abs(centre) <= math.log(self.config.engage_ratio) or spread > self.config.max_spread:
            return False
        self.disagrees = True
        self.taken = self.config.mode == 'correct'
        return True

    def _new_stream(self, stamp: int) -> None:
        """Start over where ``stamp`` goes back (a new stream); where it steps forward by
        ``NEW_STREAM_STEPS`` of the recent steps, judge no keyframe until ``min_keyframes`` have
        come since (the factor is kept)."""
        last = self.last_stamp
        if last is None:
            return
        if stamp < last:
            log.info('stream scale: stamps went back, a new stream: starting over')
            self.reset()
        elif len(self._steps) >= 3 and stamp - last >= NEW_STREAM_STEPS * float(np.median(self._steps)):
            log.info(
                'stream scale: a gap of %.0f keyframe periods (another stream?): keyframes are judged '
                'against the stream again after %d more',
                (stamp - last) / float(np.median(self._steps)),
                self.config.min_keyframes,
            )
            self._since_gap = 0
        else:
            self._steps.append(stamp - last)

    @property
    def jumped(self) -> bool:
        """Whether the last keyframe's factor lies beyond ``max_jump`` of the stream's."""
        limit = self.config.max_jump
        return limit > 0 and self.jump is not None and abs(self.jump) > math.log(limit)

    def jump_reason(self) -> str | None:
        """The decision's reason where the last keyframe :attr:`jumped`, else None."""
        if not self.jumped:
            return None
        return (
            f'scale_jump: the points sit at {self.current:.3f}x the single view, '
            f"{math.exp(abs(self.jump)):.2f}x off the stream's {self._jump_centre:.3f}x "
            f'(> stream_scale.max_jump {self.config.max_jump:g}): points untrusted'
        )

    def scaled(
        self, single: np.ndarray, mv_depth: np.ndarray, stage1: np.ndarray | None, stamp: int | None = None
    ) -> tuple[np.ndarray, float, bool]:
        """:meth:`observe` this keyframe, then ``single`` times :attr:`factor`: the single view to
        fuse, the factor, and whether the stream was first found to disagree here."""
        found = self.observe(single, mv_depth, stage1, stamp)
        factor = self.factor
        return (single * np.float32(factor) if factor != 1.0 else single), factor, found

    def describe(self) -> str:
        """One line for the note: the factor, what it may mean and what was done."""
        u = self._median()
        done = (
            "the single view is scaled into the poses' unit before fusing from now on (fusion_node "
            'stream_scale.mode: warn to keep metres)'
            if self.taken
            else 'not corrected (stream_scale.mode: warn)'
        )
        return (
            f'the multi-view points sit at {u:.3f}x the single-view depth over '
            f'{len(self.factors)} keyframes: '
            'the poses are not in metres (a monocular SLAM?) or the network is off in scale on this camera; '
            f'{done}'
        )


__all__ = [
    'STREAM_SCALE_PARAMETER_DESCRIPTIONS',
    'StreamScale',
    'StreamScaleConfig',
    'keyframe_factor',
]
