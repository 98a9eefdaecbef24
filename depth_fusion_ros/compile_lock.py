"""One process-wide lock between ``torch.compile`` sessions and the code they break.

torch (2.13) marks a compile session with one *global* flag (``torch.compiler.is_compiling()``,
held for the whole session: seconds on a CPU), not a per-thread one. Code in another thread
that branches on it takes the traced path meanwhile. ``torch.optim.Adam``'s grouped step
reads it once per parameter, so a session that starts or ends in the middle of a step gives
it a list of tensors and floats, and the step raises (``TypeError: expected Tensor as element
94 in argument 1, but got float``). Measured in the composed graph: the fusion node compiles
its kernel (in the background, and again for a new shape) while the single-view node's
adaptation thread trains.

Compiled calls (which compile when they meet a new shape) and optimiser steps therefore hold
:data:`COMPILE_LOCK`. Neither is long (a kernel call is a chunk of one keyframe, a step a few
grouped updates), and an uncontended lock costs nothing next to them.

The first *import* of the compiler stack needs it too. ``torch.compile(fn)`` imports
``torch._dynamo`` and ``torch._inductor`` when it is called, and so does building a torch
optimiser (``Optimizer.__init__`` is wrapped by ``torch._disable_dynamo``). Two threads that
import them for the first time at once see each other's partially initialised modules:
measured on an H200 in the composed graph (2026-11-28), the fusion node's background compile
and the adaptation thread's optimiser raised ``ImportError: cannot import name
'IndentedBuffer' from partially initialized module 'torch._inductor.utils'``; the fusion
stayed eager and every adaptation update failed (``torch._dynamo`` stayed broken in that
process). So :func:`compile_serialised` makes compiled functions holding the lock, and the adapter
builds its optimiser holding it.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable
from typing import TypeVar

T = TypeVar('T')

#: Held by every call that may compile and by every step that branches on the compile flag.
COMPILE_LOCK = threading.RLock()


def serialised(fn: Callable[..., T]) -> Callable[..., T]:
    """``fn`` holding :data:`COMPILE_LOCK` for each call."""

    @functools.wraps(fn)
    def call(*args: object, **kwargs: object) -> T:
        with COMPILE_LOCK:
            return fn(*args, **kwargs)

    return call


def compile_serialised(fn: Callable[..., T], **options: object) -> Callable[..., T]:
    """``torch.compile(fn, **options)``, created and called holding :data:`COMPILE_LOCK`.

    The only way the package compiles (``test_compile_lock.py`` checks): creating it imports
    the compiler stack, which must not race another thread's first import (module docstring).
    """
    import torch

    with COMPILE_LOCK:
        return serialised(torch.compile(fn, **options))
