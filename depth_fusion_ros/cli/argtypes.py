"""argparse types whose errors name the option (``argument --frames: must be at least 1, got 0``),
and the sub-command parser every command shares."""

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


def subcommand(
    sub: argparse._SubParsersAction, name: str, help_text: str, description: str
) -> argparse.ArgumentParser:
    """The parser of ``depth-fusion NAME``: one ``--help`` line, and a description whose
    examples keep their layout."""
    return sub.add_parser(
        name, help=help_text, description=description, formatter_class=argparse.RawDescriptionHelpFormatter
    )
