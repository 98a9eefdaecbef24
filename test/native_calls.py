"""A native kernel's entry point watched by a test: which calls it took and which it declined."""

from __future__ import annotations

from types import ModuleType


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
