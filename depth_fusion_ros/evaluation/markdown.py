"""Markdown building blocks of the evaluation report: a number as a table cell, a table.

Kept apart so that every table of the report (``report.py``, ``check_tables.py``) writes its
cells and its alignment row the same way.
"""

from __future__ import annotations

import math
from typing import Any


def fmt(value: Any, pattern: str = '{:.3f}') -> str:
    """``value`` in ``pattern``, or a dash where it is missing or not finite."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return '–'
    return pattern.format(value)


def table(header: list[str], rows: list[list[str]], align_first_left: bool = True) -> str:
    """A markdown table: the first column left-aligned (or right), the others right."""
    lines = ['| ' + ' | '.join(header) + ' |']
    lines.append('|' + ('---|' if align_first_left else '---:|') + '---:|' * (len(header) - 1))
    lines += ['| ' + ' | '.join(r) + ' |' for r in rows]
    return '\n'.join(lines)
