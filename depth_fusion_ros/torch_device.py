"""The torch device a user names (``device`` parameter, ``--device``), checked once at start.

Every node and command takes a device string. Only the single-view network checked it, so
``fusion_node -p device:=cuda`` on a CPU build of torch started and failed its compilation in
the background, ``device:=gpu`` ended a thread in a traceback, and ``map_node`` died in one.
"""

from __future__ import annotations

import torch


def resolve_device(device: str | torch.device) -> torch.device:
    """``torch.device`` from a user string; a one-line ``ValueError`` for a typo, for CUDA
    where this torch build has none, and for a CUDA index the machine does not have."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise ValueError(f"device must be 'cpu', 'cuda' or 'cuda:N', got {device!r}") from None
    if dev.type == 'cuda':
        if not torch.cuda.is_available():
            raise ValueError(f'device {device!r} requested but CUDA is not available in this torch build')
        count = torch.cuda.device_count()
        if dev.index is not None and dev.index >= count:
            raise ValueError(f'device {device!r} requested but this machine has {count} CUDA device(s)')
    return dev
