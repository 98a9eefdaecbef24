"""Images that came before their camera_info wait for it, briefly, instead of being dropped.

A camera driver (or a replay) often publishes the first image a moment before the first
camera_info. Dropping those images as ``no_camera_info`` loses the start of every stream, so a
node keeps them, bounded in number and in stream time like images waiting for their pose,
and handles them in order as soon as a camera_info arrives. A stream that never gets one is
dropped as before, only ``wait`` seconds (stamp time) later.
"""

from __future__ import annotations

from collections import deque
from typing import Any


class AwaitingCalibration:
    """Raw image messages waiting for the first camera_info, oldest first."""

    def __init__(self, wait_s: float, max_images: int) -> None:
        self.wait_ns = round(wait_s * 1e9)
        self.max_images = int(max_images)
        self._held: deque[tuple[int, Any]] = deque()

    def __len__(self) -> int:
        return len(self._held)

    def hold(self, stamp_ns: int, msg: Any) -> list[tuple[int, Any]]:
        """Keep ``msg``; returns the held messages now given up (too old or too many).

        With ``wait`` 0 nothing is held: the message itself comes back at once.
        """
        if self.wait_ns <= 0:
            return [(stamp_ns, msg)]
        self._held.append((stamp_ns, msg))
        expired = []
        while self._held and (
            len(self._held) > self.max_images or stamp_ns - self._held[0][0] > self.wait_ns
        ):
            expired.append(self._held.popleft())
        return expired

    def release(self) -> list[tuple[int, Any]]:
        """Every held message, oldest first (a camera_info has come)."""
        out = list(self._held)
        self._held.clear()
        return out
