"""Drop a memory-mapped file's pages from the process, keeping its data.

Why: a file read or written through a mapping (the map's disk archive, a loaded map file)
leaves every page it touched in the process's resident set, so the process looks as large as
the files it went through, though it holds none of them. ``MADV_DONTNEED`` unmaps those pages:
a shared mapping's data stays in the page cache and goes to disk as usual; a copy-on-write
mapping that was never written reads the file again on the next access.
"""

from __future__ import annotations

import mmap

import numpy as np


def unmap_pages(mapped: np.memmap | None) -> None:
    """Drop the pages of ``mapped`` (a ``numpy.memmap`` that owns its mapping) from the process;
    a no-op for anything else or where ``madvise`` is missing."""
    mapping = getattr(mapped, '_mmap', None)
    if mapping is not None and hasattr(mapping, 'madvise') and hasattr(mmap, 'MADV_DONTNEED'):
        mapping.madvise(mmap.MADV_DONTNEED)
