"""argparse types whose errors name the option (``argument --frames: must be at least 1, got 0``)."""

from __future__ import annotations

import argparse
from collections.abc import Callable


def at_least(minimum: int, option: str = '') -> Callable[[str], int]:
    """An integer option with a lower bound. argparse reports a violation in one line that names
    the option (``argument --frames: must be at least 1, got 0``), never an internal name."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'expects an integer, got {text!r}') from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f'must be at least {minimum}, got {value}')
        return value

    parse.__name__ = 'int'
    return parse
