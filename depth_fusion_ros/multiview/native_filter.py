"""The temporal filter's own native kernels, named once.

Beside the matching cost's (``native_cost``: the searches), the filter's frame runs four: the
frame's descriptors (``native_descriptors``), the choice of rows (``native_choose``), the seed
bracket (``native_bracket``) and the update of the matches (``native_apply``). A node builds
them before it says it is ready, and the bench says whether they ran; both read this list, so
a new kernel is added in one place.
"""

from __future__ import annotations

from . import native_apply, native_bracket, native_choose, native_descriptors

#: The filter's kernels in the order a frame runs them.
KERNELS = (native_descriptors, native_choose, native_bracket, native_apply)


def prepare() -> bool:
    """Build (first run on this machine) or load every filter kernel now; whether all will be
    used (each one that cannot is said once by ``native_build`` and its torch code runs)."""
    return all([kernel.prepare() for kernel in KERNELS])
