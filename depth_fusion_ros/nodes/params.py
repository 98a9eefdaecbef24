"""Parameters declared from one table per node: description, range, choices, validation.

Why a table instead of ``declare_parameter`` calls scattered through a constructor:

* every parameter gets a description (and a range where one applies) that
  ``ros2 param describe`` shows, and the same table writes ``config/depth_fusion.yaml`` and
  the parameter table in docs/nodes.md, so the three never drift apart;
* the core configs (``MultiViewConfig``, ``FusionConfig``) are dataclasses; their fields are
  turned into parameters by :func:`dataclass_specs`, so a field added to the core becomes a
  ROS parameter without touching the node;
* bad values fail at start with a ``ValueError`` naming the node and the parameter, instead
  of a type error deep inside the algorithm.

Parameters are read once at start-up (the nodes build their pipelines from them), so they
are declared read-only: ``ros2 param set`` is refused rather than silently ignored.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from .ignored_params import warn_ignored

ParamValue = bool | int | float | str | list[float] | list[int] | list[str]


def torch_device(value: str) -> None:
    """A ``device`` parameter's check: a typo, CUDA on a CPU build of torch or a CUDA index
    the machine lacks fails at start (``fusion_node -p device:=cuda`` on a CPU build once
    started and failed its compilation in the background). ``cpu`` needs no torch import."""
    if value != 'cpu':
        from ..torch_device import resolve_device

        resolve_device(value)


@dataclass(frozen=True)
class ParamSpec:
    """One node parameter: its default (which also fixes its type), what it means, its limits."""

    name: str
    default: ParamValue
    description: str
    #: Inclusive numeric bounds (``None``: unbounded on that side).
    min_value: float | None = None
    max_value: float | None = None
    #: Allowed values of a string parameter (empty: any string).
    choices: tuple[str, ...] = ()
    #: Required length of an array parameter (``None``: any length).
    length: int | None = None
    #: A further check of a string value: raises ``ValueError`` with a message that names
    #: what is wrong (e.g. :func:`torch_device`); the node's name is put before it.
    validate: Callable[[str], object] | None = None

    @property
    def kind(self) -> type:
        """Python type of the value: ``bool``, ``int``, ``float``, ``str`` or ``list``."""
        for candidate in (bool, int, float, str, list):
            if isinstance(self.default, candidate):
                return candidate
        if isinstance(self.default, tuple):
            return list
        raise TypeError(f'parameter {self.name}: unsupported default {self.default!r}')

    def check(self, value: Any, where: str = '') -> ParamValue:
        """``value`` converted to this parameter's type, or ``ValueError`` saying what is wrong."""
        label = f'{where}parameter {self.name!r}'
        kind = self.kind
        if kind is bool:
            if not isinstance(value, bool):
                raise ValueError(f'{label} must be true or false, got {value!r}')
            return value
        if kind is int:
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f'{label} must be an integer, got {value!r}')
            self._check_range(value, label)
            return int(value)
        if kind is float:
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f'{label} must be a number, got {value!r}')
            value = float(value)
            if math.isnan(value):
                raise ValueError(f'{label} must not be NaN')
            self._check_range(value, label)
            return value
        if kind is str:
            if isinstance(value, bool) and {'true', 'false'} <= set(self.choices or ()):
                # YAML reads an unquoted `adapt: false` (or `--set ...adapt=false`) as a bool
                value = 'true' if value else 'false'
            elif value is False and 'off' in (self.choices or ()):
                value = 'off'  # YAML 1.1 reads an unquoted `mode: off` as false too
            if not isinstance(value, str):
                raise ValueError(f'{label} must be a string, got {value!r}')
            if self.choices and value not in self.choices:
                raise ValueError(f'{label} is {value!r}: expected one of {", ".join(self.choices)}')
            if self.validate is not None:
                try:
                    self.validate(value)
                except ValueError as exc:
                    raise ValueError(f'{where}{exc}') from None
            return value
        return self._check_list(value, label)

    def _check_range(self, value: float, label: str) -> None:
        if self.min_value is not None and value < self.min_value:
            raise ValueError(f'{label} is {value}: must be >= {self.min_value}')
        if self.max_value is not None and value > self.max_value:
            raise ValueError(f'{label} is {value}: must be <= {self.max_value}')

    def _check_list(self, value: Any, label: str) -> list:
        if isinstance(value, str) or not isinstance(value, Sequence | Iterable):
            raise ValueError(f'{label} must be a list, got {value!r}')
        items = list(value)
        if self.length is not None and len(items) != self.length:
            raise ValueError(f'{label} must have {self.length} elements, got {len(items)}')
        element = type(self.default[0]) if len(self.default) else float
        if element is float:
            if any(isinstance(v, bool) or not isinstance(v, int | float) for v in items):
                raise ValueError(f'{label} must be a list of numbers, got {items!r}')
            return [float(v) for v in items]
        if any(not isinstance(v, element) for v in items):
            raise ValueError(f'{label} must be a list of {element.__name__}, got {items!r}')
        return items

    def range_text(self) -> str:
        """Human-readable limits for docs and descriptors (empty when unconstrained)."""
        if self.choices:
            return 'one of ' + ', '.join(self.choices)
        if self.min_value is None and self.max_value is None:
            return f'{self.length} values' if self.length else ''
        low = '-inf' if self.min_value is None else f'{self.min_value:g}'
        high = 'inf' if self.max_value is None else f'{self.max_value:g}'
        return f'range [{low}, {high}]'


def declare_parameters(node: Any, specs: Sequence[ParamSpec]) -> dict[str, ParamValue]:
    """Declare ``specs`` on an rclpy node and return their validated values by name.

    Declared with ``dynamic_typing`` so that ``1`` in a YAML file is accepted for a float
    parameter (rclpy's static typing would refuse it with an obscure message); the type and
    range are then checked here, with an error that names the node and the parameter.
    """
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
    from rclpy.exceptions import InvalidParameterValueException

    where = f'{node.get_name()}: '
    values: dict[str, ParamValue] = {}
    for spec in specs:
        descriptor = ParameterDescriptor(
            description=spec.description,
            additional_constraints=spec.range_text(),
            read_only=True,
            dynamic_typing=True,
        )
        if spec.kind is float and (spec.min_value is not None or spec.max_value is not None):
            descriptor.floating_point_range = [
                FloatingPointRange(
                    from_value=-math.inf if spec.min_value is None else float(spec.min_value),
                    to_value=math.inf if spec.max_value is None else float(spec.max_value),
                )
            ]
        elif spec.kind is int and (spec.min_value is not None or spec.max_value is not None):
            descriptor.integer_range = [
                IntegerRange(
                    from_value=-(2**63) if spec.min_value is None else int(spec.min_value),
                    to_value=2**63 - 1 if spec.max_value is None else int(spec.max_value),
                )
            ]
        default = list(spec.default) if isinstance(spec.default, tuple | list) else spec.default
        try:
            parameter = node.declare_parameter(spec.name, default, descriptor)
        except InvalidParameterValueException as exc:
            raise ValueError(f'{where}parameter {spec.name!r}: {exc}') from None
        value = parameter.value
        if isinstance(value, tuple) or type(value).__name__ == 'array':
            value = list(value)
        values[spec.name] = spec.check(value, where)
    warn_ignored(node, [spec.name for spec in specs])  # a misspelt -p is said, not ignored
    return values


# --- core dataclasses as parameters -------------------------------------------------------------


def _field_kind(annotation: Any) -> type | None:
    """``bool``/``int``/``float``/``str`` of a dataclass field annotation, ``None`` otherwise."""
    if isinstance(annotation, type):
        return annotation if annotation in (bool, int, float, str) else None
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        kinds = [_field_kind(a) for a in typing.get_args(annotation) if a is not type(None)]
        return kinds[0] if len(kinds) == 1 else None
    return None


def dataclass_specs(
    config_cls: type,
    prefix: str,
    descriptions: Mapping[str, str],
    limits: Mapping[str, tuple[float | None, float | None] | tuple[str, ...]] | None = None,
    skip: Iterable[str] = (),
    defaults: Mapping[str, Any] | None = None,
) -> list[ParamSpec]:
    """One :class:`ParamSpec` per scalar field of the dataclass ``config_cls``, named ``prefix.field``.

    ``limits`` maps a field to ``(min, max)`` or to a tuple of string choices; ``defaults``
    overrides a field's default for the node (e.g. the fast fusion mode). Fields without a
    scalar type (arrays, nested configs) and fields in ``skip`` are left out. A field whose
    default is ``None`` becomes a string (``'auto'`` = ``None``), a float or an int parameter
    with the sentinel documented in its description, chosen from the field's annotation.
    Descriptions come from ``descriptions``, else from the ``#:`` comment above the field in the
    dataclass (:func:`field_comments`), else the field's name (``missing_descriptions`` lists
    those for tests); so a field added to the core becomes a described parameter by itself.
    """
    limits = limits or {}
    defaults = defaults or {}
    skip = set(skip)
    hints = typing.get_type_hints(config_cls)
    descriptions = {**field_comments(config_cls), **descriptions}
    specs = []
    for field in dataclasses.fields(config_cls):
        if field.name in skip or field.name.startswith('_'):
            continue
        kind = _field_kind(hints.get(field.name))
        if kind is None:
            continue
        default = defaults.get(field.name, _field_default(field))
        if default is dataclasses.MISSING:
            continue
        description = descriptions.get(field.name, f'{config_cls.__name__}.{field.name}')
        limit = limits.get(field.name)
        choices = tuple(limit) if limit and all(isinstance(v, str) for v in limit) else ()
        if default is None:
            default, description = _none_sentinel(kind, description)
            if kind is bool:
                choices = (NONE_STRING, 'true', 'false')
            elif kind is str and choices:
                choices = (NONE_STRING, *choices)
        else:
            default = kind(default)
        low, high = limit if limit and not choices else (None, None)  # type: ignore[misc]
        specs.append(ParamSpec(f'{prefix}.{field.name}', default, description, low, high, choices))
    return specs


def field_comments(config_cls: type) -> dict[str, str]:
    """``#:`` comments written above the fields of a dataclass, by field name.

    The core configs document their fields that way (``#: Coarse inverse-depth samples per
    pixel.``); reading them keeps the ROS parameter descriptions in step with the core when a
    field is added, without a second table to maintain. A comment above several fields
    applies to each of them.
    """
    import inspect

    try:
        lines = inspect.getsource(config_cls).splitlines()
    except (OSError, TypeError):
        return {}
    names = {f.name for f in dataclasses.fields(config_cls)}
    comments: dict[str, str] = {}
    block: list[str] = []
    in_comment = False
    for line in lines:
        text = line.strip()
        if text.startswith('#:'):
            if not in_comment:
                block = []  # a new comment block replaces the one above the previous field
            block.append(text[2:].strip())
            in_comment = True
            continue
        in_comment = False
        name = text.split(':', 1)[0].strip()
        if name in names and ':' in text:
            if block:
                comments[name] = ' '.join(block).rstrip('.')
            continue  # the same block may document the next field too
        block = []
    return comments


def _field_default(field: dataclasses.Field) -> Any:
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return dataclasses.MISSING


#: How a ``None`` default is represented in a ROS parameter (ROS has no null).
NONE_STRING = 'auto'


def _none_sentinel(kind: type, description: str) -> tuple[ParamValue, str]:
    if kind is str:
        return NONE_STRING, f"{description} ('{NONE_STRING}': automatic)"
    if kind is bool:
        return NONE_STRING, description  # its choices (auto, true, false) are listed with it
    if kind is float:
        return -1.0, f'{description} (negative: automatic)'
    return -1, f'{description} (negative: automatic)'


def missing_descriptions(
    config_cls: type, descriptions: Mapping[str, str], skip: Iterable[str] = ()
) -> list[str]:
    """Scalar fields of ``config_cls`` described neither in ``descriptions`` nor by a ``#:``
    comment in the dataclass (test helper)."""
    hints = typing.get_type_hints(config_cls)
    descriptions = {**field_comments(config_cls), **descriptions}
    return [
        f.name
        for f in dataclasses.fields(config_cls)
        if f.name not in set(skip)
        and not f.name.startswith('_')
        and _field_kind(hints.get(f.name)) is not None
        and f.name not in descriptions
    ]


def build_dataclass(config_cls: type, values: Mapping[str, ParamValue], prefix: str, **extra: Any) -> Any:
    """Instance of ``config_cls`` from declared ``prefix.field`` values (sentinels back to ``None``)."""
    hints = typing.get_type_hints(config_cls)
    kwargs: dict[str, Any] = {}
    for field in dataclasses.fields(config_cls):
        key = f'{prefix}.{field.name}'
        if key not in values:
            continue
        value = values[key]
        if _field_default(field) is None:
            value = _from_sentinel(_field_kind(hints.get(field.name)), value, key)
        kwargs[field.name] = value
    kwargs.update(extra)
    try:
        return config_cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'parameters {prefix}.*: {exc}') from None


def _from_sentinel(kind: type | None, value: ParamValue, key: str) -> Any:
    if kind is bool:
        if value == NONE_STRING:
            return None
        if value in ('true', 'false'):
            return value == 'true'
        if isinstance(value, bool):
            return value
        raise ValueError(f'parameter {key!r} is {value!r}: expected auto, true or false')
    if kind is str:
        return None if value == NONE_STRING else value
    if kind in (int, float) and isinstance(value, int | float) and value < 0:
        return None
    return value


# --- YAML and documentation ---------------------------------------------------------------------


def yaml_section(node_name: str, specs: Sequence[ParamSpec]) -> str:
    """``node_name: ros__parameters:`` block with every default, its description and limits as comments."""
    import textwrap

    lines = [f'{node_name}:', '  ros__parameters:']
    for spec in specs:
        limits = spec.range_text()
        comment = spec.description + (f' ({limits})' if limits and not limits[0].isdigit() else '')
        lines += textwrap.wrap(comment, width=96, initial_indent='    # ', subsequent_indent='    #   ')
        lines.append(f'    {spec.name}: {_yaml_value(spec.default)}')
    return '\n'.join(lines) + '\n'


def _yaml_value(value: ParamValue) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        return "''" if value == '' else f"'{value}'"
    if isinstance(value, list | tuple):
        return '[' + ', '.join(_yaml_value(v) for v in value) + ']'
    return str(value)


def markdown_table(specs: Sequence[ParamSpec]) -> str:
    """Markdown table of ``specs`` (name, default, limits, description) for docs/nodes.md."""
    rows = ['| parameter | default | range | description |', '|---|---|---|---|']
    for spec in specs:
        description = spec.description.replace('|', '\\|')
        default = _yaml_value(spec.default)
        rows.append(f'| `{spec.name}` | `{default}` | {spec.range_text()} | {description} |')
    return '\n'.join(rows) + '\n'
