"""Apply ``{name: value}`` overrides (CLI ``--set stage.name=value``, ROS parameters) to a config dataclass.

Unknown names and values of the wrong type raise a ``ValueError`` that names the stage and
the parameter, so a typo on the command line is reported instead of silently ignored.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any, TypeVar

C = TypeVar('C')


def _coerce(value: Any, default: Any, where: str) -> Any:
    if isinstance(default, bool):
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ('true', 'false'):
            return value.lower() == 'true'
        raise ValueError(f'{where}: expected true/false, got {value!r}')
    if isinstance(default, int):
        try:
            number = float(value)
        except (TypeError, ValueError):
            number = math.nan
        if isinstance(value, bool) or not number.is_integer():
            raise ValueError(f'{where}: expected an integer, got {value!r}')
        return int(number)
    if isinstance(default, float):
        if isinstance(value, bool):
            raise ValueError(f'{where}: expected a number, got {value!r}')
        try:
            return float(value)
        except (TypeError, ValueError):
            raise ValueError(f'{where}: expected a number, got {value!r}') from None
    if isinstance(default, str):
        # YAML 1.1 reads an unquoted off / no / on / yes as a bool: the config's own check
        # decides what it means (FocalCheckConfig.mode takes false as off), str() would not.
        return value if isinstance(value, bool) else str(value)
    return value


def apply_overrides(config: C, params: Mapping[str, Any], stage: str) -> C:
    """A copy of ``config`` (a dataclass instance) with ``params`` applied and type-checked."""
    if not params:
        return config
    fields = {f.name for f in dataclasses.fields(config)}  # type: ignore[arg-type]
    changes: dict[str, Any] = {}
    for name, value in params.items():
        if name not in fields:
            raise ValueError(f'unknown parameter {stage}.{name}; known: {", ".join(sorted(fields))}')
        changes[name] = _coerce(value, getattr(config, name), f'{stage}.{name}')
    return dataclasses.replace(config, **changes)  # type: ignore[type-var]
