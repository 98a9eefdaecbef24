"""The user's cache folder for what the package builds once and reuses (kernels, DDS profiles).

``$XDG_CACHE_HOME`` or ``~/.cache``, then ``depth_fusion_ros``: one place, so clearing it
clears everything the package generated outside the checkout.
"""

from __future__ import annotations

import os
from pathlib import Path


def user_cache(*parts: str) -> Path:
    """``$XDG_CACHE_HOME/depth_fusion_ros/<parts...>`` (``~/.cache`` when the variable is unset)."""
    base = Path(os.environ.get('XDG_CACHE_HOME') or Path.home() / '.cache')
    return base.joinpath('depth_fusion_ros', *parts)
