"""Every native C kernel of the package, named once: one module per C file, each with
``prepare()`` (build on this machine's first run, or load; whether it will be used) and
``_library()``.

The nodes prepare their own (``multi_view_node``: the matching cost, the sweep's scores and
``multiview.native_filter.KERNELS``; ``fusion_node``: the halo test and the guard's medians);
``depth-fusion kernels`` prepares and counts them all, and the tests hold every one of them
to its builds (``test/test_native_portable.py``, ``test/test_native_aarch64.py``).
"""

from __future__ import annotations

from .fusion import native_halo, neighbour_median
from .multiview import native_cost, native_filter, native_scores

#: The eight kernels: the matching cost, the sweep's scores, the filter's four, the halo test and
#: the guard's medians.
KERNELS = (native_cost, native_scores, *native_filter.KERNELS, native_halo, neighbour_median)


def prepare() -> int:
    """Build or load every kernel now; how many will be used (each one that cannot is said once
    by ``native_build``)."""
    return sum(kernel.prepare() for kernel in KERNELS)
