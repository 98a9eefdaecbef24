"""A native kernel's entry point watched by a test (which calls it took and which it declined), and
the filter stream the kernels' tests run."""

from __future__ import annotations

import functools
from types import ModuleType

import torch


def count_native_calls(monkeypatch, module: ModuleType, name: str) -> list[bool]:
    """Wrap ``module.name``, a kernel's entry that returns None where it declines, so that each
    call appends whether the kernel ran (True) or left the work to the reference code (False)."""
    calls: list[bool] = []
    real = getattr(module, name)

    def counting(*args):
        out = real(*args)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(module, name, counting)
    return calls


@functools.cache
def _room(frames: int):
    from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence

    return render_sequence(SynthConfig(width=160, height=120, frames=frames, seed=4, parallax='high'))


def filter_end_state(frames: int) -> dict[str, torch.Tensor]:
    """The filter's keyframe state (``mu``, ``var``, ``a``, ``b``) after the first ``frames``
    frames of a rendered 160x120 room, whichever kernels run: the stream the native kernels'
    tests put through the whole filter (the room rendered once per length)."""
    from depth_fusion_ros.multiview.filter import DepthFilter

    seq = _room(frames)
    filt = DepthFilter(seq.camera, None, device='cpu')
    for frame in seq.frames:
        filt.process(frame.gray, frame.pose)
    return {k: getattr(filt.key.state, k).clone() for k in ('mu', 'var', 'a', 'b')}
