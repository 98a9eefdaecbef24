"""``depth-fusion export``: the shipped network (or a trained checkpoint) as ONNX, .pt2 or TorchScript."""

from __future__ import annotations

import argparse

DESCRIPTION = """\
Write a single-view network as a file any host loads: ONNX (ONNX Runtime), pt2 (torch.export)
or TorchScript, with its metadata YAML beside it (OUT with .yaml). The result works as it is
with --single-view OUT (evaluate, run, demo) and the single_view_node parameter model:=OUT.

examples:
  depth-fusion export --format onnx --out artifacts/compact.onnx
  depth-fusion export --format pt2 --out artifacts/mine.pt2 --model runs/train/best.pt
"""


def register(sub: argparse._SubParsersAction) -> None:
    from ..singleview.export_formats import FORMATS

    p = sub.add_parser(
        'export',
        help='export the single-view network to ONNX, torch.export (.pt2) or TorchScript, with its YAML',
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        '--format',
        choices=tuple(FORMATS),
        help='onnx | pt2 | torchscript (default: from the suffix of --out: .onnx, .pt2, .pt)',
    )
    p.add_argument('--out', required=True, metavar='PATH', help='the exported model file')
    p.add_argument(
        '--overwrite',
        action='store_true',
        help='replace PATH, and the YAML beside it if it describes another model',
    )
    p.add_argument(
        '--model',
        default='default',
        metavar='SRC',
        help="'default' (the shipped network) or a checkpoint written by depth-fusion train",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..singleview.export import export_network
    from .paths import check_new_file, check_output

    out = check_new_file(args.out, '--out', args.overwrite)
    check_output(out.with_suffix('.yaml'), '--out', folder=False)  # its YAML: see export_network
    model_path, yaml_path = export_network(out, args.format, args.model, overwrite=args.overwrite)
    print(f'wrote {model_path} and {yaml_path}; use it with --single-view {model_path}')
    return 0
