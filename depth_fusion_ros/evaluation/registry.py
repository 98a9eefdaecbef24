"""Registry of depth methods that ``depth-fusion evaluate`` can run, by name.

A method turns one keyframe (a :class:`~.context.KeyframeContext`) into a depth image at
the working resolution. Stages register their own methods in
``depth_fusion_ros/evaluation/methods/<stage>.py`` so adding a method never touches the
harness.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from .context import KeyframeContext, SequenceContext


@dataclass
class MethodOutput:
    """What a method returns for one keyframe.

    ``depth``: float32 metres at the working resolution, NaN where the method has no
    estimate. ``extras``: per-frame scalars (e.g. ``density``, ``n_selected``) that the
    harness averages over frames into the results.
    """

    depth: np.ndarray
    extras: dict[str, float] = field(default_factory=dict)


@dataclass
class SequenceOutput:
    """What a sequence-level method (one with ``finish``) reports once per sequence.

    ``metrics`` go into results.json under the method; ``figure(out_dir)`` writes the
    method's pictures and returns their paths (methods sharing one figure share the callable,
    and it is called once).
    """

    metrics: dict[str, float]
    figure: Callable[[Path], list[Path]] | None = None
    #: Anything else a caller may want (the map's mesh, for the demo's .ply); not in results.json.
    artifacts: dict[str, Any] = field(default_factory=dict)


MethodFn = Callable[['KeyframeContext'], MethodOutput]
#: Called once after the last keyframe of a sequence (``SequenceContext``) for methods whose
#: result spans keyframes (a map); their per-keyframe depth is not scored.
FinishFn = Callable[['SequenceContext'], SequenceOutput]


@dataclass(frozen=True)
class MethodSpec:
    name: str
    fn: MethodFn
    description: str
    #: Semi-dense methods are scored on their estimated pixels only, and report ``density``.
    sparse: bool = False
    finish: FinishFn | None = None


_METHODS: dict[str, MethodSpec] = {}


def register_method(
    name: str, description: str, *, sparse: bool = False, finish: FinishFn | None = None
) -> Callable[[MethodFn], MethodFn]:
    """Decorator: make ``fn`` available to ``depth-fusion evaluate --methods name``.

    With ``finish``, the method is scored once per sequence by ``finish`` (after ``fn`` ran
    on every keyframe) instead of per keyframe.
    """

    def decorate(fn: MethodFn) -> MethodFn:
        if name in _METHODS:
            raise ValueError(f'evaluation method {name!r} registered twice')
        _METHODS[name] = MethodSpec(name, fn, description, sparse, finish)
        return fn

    return decorate


def get_method(name: str) -> MethodSpec:
    _load_builtin_methods()
    try:
        return _METHODS[name]
    except KeyError:
        known = ', '.join(sorted(_METHODS))
        raise KeyError(f'unknown evaluation method {name!r}; available: {known}') from None


def available_methods() -> dict[str, MethodSpec]:
    _load_builtin_methods()
    return dict(sorted(_METHODS.items()))


def _load_builtin_methods() -> None:
    from . import methods  # noqa: F401  (importing registers every stage's methods)
