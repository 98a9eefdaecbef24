"""Entry point of ``depth-fusion``.

Each subcommand lives in its own module of this package and exposes
``register(subparsers)``, which adds its parser and sets ``func`` (called with the parsed
arguments, returning an exit code). Heavy imports (torch, rclpy) happen inside ``func`` so
``depth-fusion --help`` answers instantly.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from ..malloc_tuning import keep_freed_memory

#: Subcommands in the order ``--help`` lists them.
SUBCOMMANDS = (
    'demo',
    'synth',
    'convert',
    'evaluate',
    'check_focal',
    'check_sync',
    'check_mount',
    'train',
    'adapt',
    'export',
    'kernels',
    'run',
    'launch',
    'mesh',
    'bench',
)

DESCRIPTION = """\
depth_fusion_ros: dense monocular depth by fusing single-view CNN depth with semi-dense
multi-view depth from posed frames (Facil et al., RA-L 2017), for ROS 2 Jazzy.

typical use:
  depth-fusion demo                               # everything, on a synthetic sequence
  depth-fusion synth artifacts/room               # render a posed RGB-D sequence
  depth-fusion convert artifacts/room room        # TUM folder (or ROS 1 bag) -> rosbag2 folder
  depth-fusion run --bag room --record out        # the ROS 2 node graph on a bag
  depth-fusion launch --pose /slam/camera_pose    # the node graph for a live camera
  depth-fusion evaluate SEQ_DIR --methods tv,single_view,fused
  depth-fusion check-focal SEQ_DIR                # camera.yaml's focal length against the images
  depth-fusion export --format onnx --out model.onnx   # the network as ONNX (+ model.yaml)
  depth-fusion adapt SEQ_DIR --out adapted.pt     # self-supervised adaptation to a scene
  depth-fusion mesh lab.tsdf --out lab.ply        # the mesh of a map file saved by map_node
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='depth-fusion', description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument('-v', '--verbose', action='store_true', help='debug logging')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND')
    for name in SUBCOMMANDS:
        importlib.import_module(f'{__package__}.{name}').register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format='%(levelname)s %(name)s: %(message)s',
    )
    if not getattr(args, 'func', None):
        parser.print_help()
        return 2
    keep_freed_memory()  # freed tensor memory reused (DEPTH_FUSION_MALLOC_TUNING=0: off), malloc_tuning.py
    try:
        _check_device(args)
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print('interrupted', file=sys.stderr)
        return 130
    except (FileNotFoundError, ValueError, KeyError) as exc:
        # Bad input is the user's to fix: say what and where, no traceback.
        if args.verbose:
            raise
        print(f'depth-fusion {args.command}: error: {_message(exc)}', file=sys.stderr)
        return 1


def _check_device(args: argparse.Namespace) -> None:
    """Every command's ``--device`` checked before its work starts: ``adapt`` and ``bench``
    with ``--device cuda`` on a CPU build, or ``evaluate --device gpu``, ended in a torch
    traceback where ``run`` and ``demo`` said it in one line."""
    device = getattr(args, 'device', None)
    if isinstance(device, str) and device != 'cpu':
        from ..torch_device import resolve_device

        resolve_device(device)


def _message(exc: Exception) -> str:
    """The error's text: a ``KeyError`` prints its message quoted (``str`` gives its key's
    repr), which reads like a key, not a sentence."""
    if isinstance(exc, KeyError) and len(exc.args) == 1 and isinstance(exc.args[0], str):
        return exc.args[0]
    return str(exc)


if __name__ == '__main__':
    sys.exit(main())
