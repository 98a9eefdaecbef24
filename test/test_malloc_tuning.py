"""The allocator tuning (malloc_tuning.py): on by default, off with DEPTH_FUSION_MALLOC_TUNING=0,
applied once on glibc, the user's settings win."""

from __future__ import annotations

import platform
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith('linux') or platform.libc_ver()[0] != 'glibc', reason='glibc only'
)

#: Whether the tuning applies in a fresh interpreter (the page faults it saves are a benchmark
#: figure, docs/performance.md "Allocator": glibc's reuse of freed blocks depends on the
#: allocation pattern, so a fault count is not asserted here).
_PROBE = """
from depth_fusion_ros.malloc_tuning import keep_freed_memory
first = keep_freed_memory()
print(first, keep_freed_memory() == first)
"""


def _probe(**env: str) -> str:
    import os

    out = subprocess.run(
        [sys.executable, '-c', _PROBE],
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    )
    return out.stdout.strip()


def test_on_by_default_applied_once_and_off_when_asked():
    assert _probe(DEPTH_FUSION_MALLOC_TUNING='') == 'True True'
    assert _probe(DEPTH_FUSION_MALLOC_TUNING='1') == 'True True'
    assert _probe(DEPTH_FUSION_MALLOC_TUNING='0') == 'False True'


def test_the_users_own_settings_win():
    assert _probe(DEPTH_FUSION_MALLOC_TUNING='1', MALLOC_TRIM_THRESHOLD_='131072') == 'False True'


def test_free_memory_can_be_handed_back():
    """malloc_trim on glibc (what map_node calls after its keyframe store is thinned); a no-op
    elsewhere."""
    import platform
    import sys

    from depth_fusion_ros.malloc_tuning import release_free_memory

    glibc = sys.platform.startswith('linux') and platform.libc_ver()[0] == 'glibc'
    assert release_free_memory() is glibc
