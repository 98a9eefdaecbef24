"""Bring-your-own network as a ``torch.export`` program: a ``.pt2`` file plus its metadata YAML.

``torch.export`` is what replaces TorchScript in torch 2.x: a network exported once
(``torch.export.export`` then ``torch.export.save``) runs without its source code, and its
file holds a graph and weights, no pickled code. The YAML beside it is the same as for
TorchScript and ONNX (``ModelMetadata``, see ``docs/single_view.md``).

An exported program checks its input shapes with guards (a fixed batch of 1 or a fixed
image size unless exported with dynamic axes). At load time the program's input is read and
compared with the YAML, so a mismatch is an error at start; a fixed batch is run image by
image. ``device`` moves the program with ``torch.export.passes.move_to_device_pass``.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import torch
from torch import nn

from .metadata import ModelMetadata, check_input_size, metadata_path_for, read_metadata_yaml

log = logging.getLogger(__name__)


class ExportedDepthModule(nn.Module):
    """An exported program's module behind the call interface ``DepthPredictor`` uses.

    The program's own module refuses ``.eval()`` and ``.train()`` (an exported graph has no
    modes), so it is held unregistered; ``.to`` is a no-op here (it was placed at load).
    """

    def __init__(self, program: torch.export.ExportedProgram):
        super().__init__()
        object.__setattr__(self, '_graph', program.module())
        shape = input_shape(program)
        self.input_shape = shape
        #: A program exported with a fixed batch runs image by image.
        self.fixed_batch = shape[0] if shape and isinstance(shape[0], int) else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.fixed_batch is not None and x.shape[0] != self.fixed_batch:
            k = self.fixed_batch
            return torch.cat([self._graph(x[i : i + k]) for i in range(0, x.shape[0], k)])
        return self._graph(x)


def input_shape(program: torch.export.ExportedProgram) -> list[int | str] | None:
    """Shape of the program's single user input: ints where fixed, the symbol's name where
    dynamic; None when it has not exactly one tensor input."""
    users = list(program.graph_signature.user_inputs)
    if len(users) != 1:
        return None
    for node in program.graph.nodes:
        if node.op == 'placeholder' and node.name == users[0]:
            val = node.meta.get('val')
            if not isinstance(val, torch.Tensor):
                return None
            return [int(d) if isinstance(d, int) else str(d) for d in val.shape]
    return None


def check_pt2_signature(program: torch.export.ExportedProgram, metadata: ModelMetadata, path: Path) -> None:
    """Raise ``ValueError`` naming ``path`` when the program cannot take what the YAML promises."""
    shape = input_shape(program)
    if shape is None:
        n = len(list(program.graph_signature.user_inputs))
        raise ValueError(f'{path}: expected one image input (B, 3, H, W), the program takes {n} input(s)')
    if len(shape) != 4 or (isinstance(shape[1], int) and shape[1] != 3):
        raise ValueError(f'{path}: the program takes input of shape {shape}, expected (B, 3, H, W)')
    fixed_h = shape[2] if isinstance(shape[2], int) else None
    fixed_w = shape[3] if isinstance(shape[3], int) else None
    check_input_size(path, metadata, shape, fixed_h, fixed_w, 'program')


def load_pt2(
    path: str | Path, metadata_path: str | Path | None = None, device: str | torch.device = 'cpu'
) -> tuple[ExportedDepthModule, ModelMetadata]:
    """Load a ``torch.export`` program and its metadata onto ``device``; errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f'torch.export model not found: {path}')
    metadata = read_metadata_yaml(
        metadata_path if metadata_path is not None else metadata_path_for(path, 'torch.export model')
    )
    device = torch.device(device)
    try:
        program = torch.export.load(str(path))
    except Exception as exc:  # zip, JSON, schema-version and unpickling errors alike
        text = str(exc).strip().splitlines()
        raise ValueError(
            f'{path}: not a loadable torch.export program ({type(exc).__name__}: {text[0] if text else ""})'
        ) from None
    check_pt2_signature(program, metadata, path)
    if device.type != 'cpu':
        from torch.export.passes import move_to_device_pass

        program = move_to_device_pass(program, device)
    return ExportedDepthModule(program), metadata


def export_pt2(
    module: nn.Module, path: str | Path, example: torch.Tensor, *, dynamic_batch: bool = True
) -> Path:
    """Export ``module`` (eval mode, CPU) with ``torch.export`` and save it to ``path``.

    ``example``: an input of the size the model is fed, (B, 3, H, W); the batch axis is
    dynamic unless ``dynamic_batch=False``. Atomic: written beside ``path`` and renamed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    module = module.eval().to('cpu')
    if dynamic_batch and example.shape[0] < 2:
        example = example.expand(2, *example.shape[1:]).contiguous()  # batch 1 would be specialised
    dynamic_shapes = ({0: torch.export.Dim('batch', min=1, max=1024)},) if dynamic_batch else None
    with torch.no_grad():
        program = torch.export.export(module, (example,), dynamic_shapes=dynamic_shapes)
    tmp = path.with_name(path.name + '.tmp.pt2')
    try:
        torch.export.save(program, str(tmp))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
