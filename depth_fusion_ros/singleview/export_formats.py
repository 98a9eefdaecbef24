"""The model file formats the package writes and reads, by name and file suffix.

Kept apart from the exporters and loaders (which import torch and ONNX Runtime) so that the
command line can offer ``--format`` without importing either: ``depth-fusion --help`` built
every parser and paid 2 s of torch imports for these three names.
"""

from __future__ import annotations

ONNX_SUFFIX = '.onnx'
PT2_SUFFIX = '.pt2'
TORCHSCRIPT_SUFFIX = '.pt'

#: ``depth-fusion export --format`` choices and the suffix each one's file takes.
FORMATS = {'onnx': ONNX_SUFFIX, 'pt2': PT2_SUFFIX, 'torchscript': TORCHSCRIPT_SUFFIX}
