"""The weights and optimiser state from before an update, kept to roll the update back.

Every keyframe update starts with a snapshot and a rejected one restores it. Deep copies of
``state_dict()`` (the obvious way) allocate every tensor anew and walk Python object graphs
each time; here the copies live in buffers allocated once and are refreshed in place with a
few grouped copies (``torch._foreach_copy_``), on the network's own device, without waiting
for it. Restoring copies back in place, so every tensor the optimiser and the network hold
stays the same object.
"""

from __future__ import annotations

import torch
from torch import nn


def _copy(dst: list[torch.Tensor], src: list[torch.Tensor]) -> None:
    """``d.copy_(s)`` for every pair, grouped by devices (Adam's step counts stay on the CPU)."""
    groups: dict[tuple[torch.device, torch.device], tuple[list, list]] = {}
    for d, s in zip(dst, src, strict=True):
        group = groups.setdefault((d.device, s.device), ([], []))
        group[0].append(d)
        group[1].append(s)
    for d, s in groups.values():
        torch._foreach_copy_(d, s)


class WeightSnapshot:
    """``save()`` / ``restore()`` of a module's parameters and buffers and an optimiser's state."""

    def __init__(self, net: nn.Module, optimizer: torch.optim.Optimizer):
        self.net = net
        self.optimizer = optimizer
        self._tensors = [t for t in [*net.parameters(), *net.buffers()]]
        self._saved = [t.detach().clone() for t in self._tensors]
        #: Optimiser state at the last save: per parameter, its tensors (copied into buffers
        #: allocated on first use) and other values; parameters without state then are absent.
        self._state: dict[nn.Parameter, dict[str, object]] = {}
        self._state_buffers: dict[tuple[int, str], torch.Tensor] = {}

    @torch.no_grad()
    def save(self) -> None:
        _copy(self._saved, [t.detach() for t in self._tensors])
        self._state = {}
        dst, src = [], []
        for param, state in self.optimizer.state.items():
            kept: dict[str, object] = {}
            for name, value in state.items():
                if isinstance(value, torch.Tensor):
                    key = (id(param), name)
                    buf = self._state_buffers.get(key)
                    same = buf is not None and (buf.shape, buf.dtype, buf.device) == (
                        value.shape,
                        value.dtype,
                        value.device,
                    )
                    if not same:
                        buf = self._state_buffers[key] = torch.empty_like(value)
                    dst.append(buf)
                    src.append(value)
                    kept[name] = buf
                else:
                    kept[name] = value
            self._state[param] = kept
        _copy(dst, src)

    @torch.no_grad()
    def restore(self) -> None:
        _copy([t.detach() for t in self._tensors], self._saved)
        dst, src = [], []
        for param in list(self.optimizer.state):
            if param not in self._state:  # no state at save time (the very first update)
                del self.optimizer.state[param]
        for param, kept in self._state.items():
            state = self.optimizer.state[param]
            for name, value in kept.items():
                current = state.get(name)
                if isinstance(value, torch.Tensor):
                    if isinstance(current, torch.Tensor) and current.shape == value.shape:
                        dst.append(current)
                        src.append(value)
                    else:
                        state[name] = value.clone()
                else:
                    state[name] = value
            for name in [n for n in state if n not in kept]:
                del state[name]
        _copy(dst, src)
