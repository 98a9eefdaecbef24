"""A check fitted once to the image pairs of a posed stream (the focal length check, the mount
check): what the two share, so each says only what it fits.

The stream's frames come one at a time; a frame far enough from the last sample (by the told
poses: :class:`~.image_pairs.ImagePairs`) is the next sample and makes a pair with the one
before; once ``config.pairs`` pairs are in, the subclass fits its parameter to them
(:meth:`PairedCheck._estimate`), once. A subclass may also conclude before that, when it is
already sure (:meth:`PairedCheck._early_look`: the mount check). The time offset check reads
poses at other times and keeps its own loop.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from ..camera import PinholeCamera
from .image_pairs import ImagePairs, MatchedPair


@dataclass
class PairedCheck:
    """Collects image pairs from a posed stream and checks them once (see module)."""

    camera: PinholeCamera
    config: Any
    result: Any = None
    frames: int = 0
    pairs: list[MatchedPair] = field(default_factory=list)
    #: How the pairs' matches are tracked to sub-pixel (``ImagePairs.tracking``). The focal check
    #: shifts a window (``FocalCheck``): the detected positions carry an outward bias under
    #: forward motion, which it reads as a focal length too short. The mount check warps it
    #: (``MountCheck``), and reads how sure a turn is from the spread between image regions too:
    #: shifted windows alone turned six level streams (docs/multi_view.md, "Matches tracked to
    #: sub-pixel" and "Matches tracked with an affine window"). The time offset check keeps the
    #: positions as detected.
    TRACKING: ClassVar[str] = 'none'

    def __post_init__(self) -> None:
        screen = self._screen_ratio()
        self._images = ImagePairs.for_config(self.camera.K, self.config, self.TRACKING, screen)

    def _screen_ratio(self) -> float:
        """The pairs' outline screen (``ImagePairs.screen``; 0: every match kept): the mount
        check's config says it (``MountCheck``); the focal check keeps every match."""
        return 0.0

    @property
    def done(self) -> bool:
        return self.result is not None or self.config.mode == 'off'

    def wants(self, pose: np.ndarray, since: np.ndarray | None = None) -> bool:
        """Whether a frame at ``pose`` is the next sample: moved or turned enough since the last
        (or since ``since``, a sample chosen but not yet added: ``ImagePairs.far_enough``)."""
        return not self.done and self._images.far_enough(pose, since)

    def add(self, gray: np.ndarray, pose: np.ndarray) -> Any:
        """One posed frame of the stream (grey image on this camera's grid, camera-to-world);
        returns the estimate on the frame that completes it, else ``None``."""
        self.frames += 1
        if not self.wants(pose):
            return None
        matched = self._images.add(gray, pose)
        if matched is not None:
            self.pairs.append(matched)
            early = self._early_look()
            if early is not None:
                return self._conclude(early)
        if len(self.pairs) < self.config.pairs:
            return None
        return self._conclude(self._estimate())

    def _conclude(self, result: Any) -> Any:
        self.result = result
        self.pairs = []
        self._images.reset()
        return result

    def _estimate(self) -> Any:
        """The estimate from ``self.pairs`` (all of them in)."""
        raise NotImplementedError

    def _early_look(self) -> Any:
        """An estimate that ends the check before ``config.pairs`` pairs are in, else None
        (this base class: always None, the check looks once)."""
        return None


def feed(check: PairedCheck, frames: Iterable) -> PairedCheck:
    """``check`` fed with ``frames`` (anything with ``.gray`` and ``.pose``, in stream order) until
    it has its estimate (``.result``; ``None`` when they ran out first)."""
    for frame in frames:
        if check.done or check.add(frame.gray, frame.pose) is not None:
            break
    return check
