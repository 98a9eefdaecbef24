"""Eval-mode copies of the training network for inference, reused once nobody holds them.

Every accepted update hands inference a network of its own (training must never mutate a
module that is predicting). Deep-copying the module for each one walks and rebuilds the whole
module tree; instead a few copies are kept, and one is refilled in place with the current
weights (a grouped tensor copy) when nothing outside this pool refers to it any more: no
predictor, no thread in the middle of a forward pass (its frame holds a reference), no saved
checkpoint in progress. CPython's reference counts say so exactly. While every copy is held,
a new one is made by deep copy, as before.
"""

from __future__ import annotations

import copy
import sys
import threading

import torch
from torch import nn


def _idle_references() -> int:
    """``sys.getrefcount`` of a pooled module referred to by the pool's list only (as counted
    inside :meth:`InferenceCopies.take`'s loop)."""
    pool = [nn.Module()]
    for module in pool:
        return sys.getrefcount(module)
    raise AssertionError('unreachable')


class InferenceCopies:
    """``take()``: an eval-mode, no-grad module with ``source``'s current weights."""

    def __init__(self, source: nn.Module, size: int = 3):
        if size < 1:
            raise ValueError(f'inference copy pool size must be >= 1, got {size}')
        self.source = source
        self.size = int(size)
        self._copies: list[nn.Module] = []
        self._lock = threading.Lock()
        self._idle = _idle_references()
        #: How many copies were made by deep copy / refilled in place (for tests and logs).
        self.made = 0
        self.reused = 0

    def _new(self) -> nn.Module:
        net = copy.deepcopy(self.source).eval()
        for p in net.parameters():
            p.requires_grad_(False)
        self.made += 1
        return net

    @torch.no_grad()
    def take(self) -> nn.Module:
        with self._lock:
            for module in self._copies:
                if sys.getrefcount(module) <= self._idle:
                    dst = [*module.parameters(), *module.buffers()]
                    src = [t.detach() for t in [*self.source.parameters(), *self.source.buffers()]]
                    torch._foreach_copy_(dst, src)
                    self.reused += 1
                    return module
            net = self._new()
            self._copies.append(net)
            if len(self._copies) > self.size:
                self._copies.pop(0)  # still held elsewhere: its holders keep it alive
            return net
