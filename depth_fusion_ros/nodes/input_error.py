"""The error a node raises for a message it cannot use, with the counter key that says why.

Kept apart from the decoding (``image_input.py``) and the stamp checks (``stamp_guard.py``),
which both raise it: a callback catches one kind and counts the drop under its ``reason``.
"""

from __future__ import annotations


class InputError(ValueError):
    """A message the node cannot use; ``reason`` is the counter key (``bad_encoding`` ...)."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason
