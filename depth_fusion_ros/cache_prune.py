"""Old libraries in the user cache deleted: what a build replaced and nobody loads any more.

Every kernel library the package builds (the AOT fusion kernels, ``fusion/aot_kernels.py``;
the native matching cost, ``native_build.py``) is named by a digest of what it was built from,
so a changed source, option or compiler leaves the old file behind. A load touches the file's
modification time, so "not modified for ``days``" means "not loaded for ``days``": another
checkout of another version sharing the cache keeps its own files alive by using them.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

log = logging.getLogger(__name__)

#: Days without a load after which a library is deleted at the next build.
UNUSED_DAYS = 60


def prune_unused(cache: Path, pattern: str, keep: list[Path], days: float = UNUSED_DAYS) -> list[Path]:
    """Delete the files of ``cache`` matching ``pattern`` not loaded (nor built) for ``days``,
    except ``keep``; returns those deleted. Another process may have one mapped: on POSIX it
    keeps its mapping, and one about to load it finds no file and builds it again (as for a
    cache never built). A file that cannot be deleted stays (logged)."""
    cutoff = time.time() - days * 86400.0
    kept = {Path(p).resolve() for p in keep}
    removed = []
    for path in sorted(cache.glob(pattern)):
        try:
            if path.resolve() in kept or path.stat().st_mtime >= cutoff:
                continue
            path.unlink()
            removed.append(path)
        except OSError as exc:
            log.warning('could not remove the unused kernel library %s (%s)', path, exc)
    return removed
