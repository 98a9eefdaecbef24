"""``depth-fusion convert``."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser('convert', help='(not implemented yet)')
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    raise NotImplementedError('depth-fusion convert is not implemented yet')
