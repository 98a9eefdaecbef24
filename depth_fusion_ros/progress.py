"""Progress bars for long work (tqdm on stderr, silent when not wanted)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import TypeVar

from tqdm.auto import tqdm

T = TypeVar('T')


def progress(
    items: Iterable[T], desc: str = '', unit: str = 'it', disable: bool = False, **kw
) -> Iterable[T]:
    """Wrap ``items`` in a progress bar (``disable=True`` returns a plain iterator)."""
    if disable:
        return iter(items)
    return tqdm(items, desc=desc, unit=unit, dynamic_ncols=True, leave=False, **kw)
