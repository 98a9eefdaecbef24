"""Bring-your-own network: a TorchScript ``.pt`` plus a metadata YAML beside it.

Modern single-view networks (MiDaS/DPT, Depth Anything, ZoeDepth, Metric3D...) are exported
once with ``torch.jit.trace``/``torch.jit.script`` and used here without their source code.
The YAML (``ModelMetadata`` fields, see ``docs/single_view.md``) says how to feed the network
and what its output means. It is looked up as ``<model>.yaml`` (same stem), then
``<model>.pt.yaml``, unless a path is given.

``export_torchscript`` does the same for our own networks (it bakes the ``exp`` of the log
depth into the traced graph, so the exported model outputs metric depth in metres).
"""

from __future__ import annotations

import contextlib
import copy
import warnings
from collections.abc import Iterator
from pathlib import Path

import torch
from torch import nn

from .. import vml_warmup  # noqa: F401  (MKL VML dispatch resolved before the first parallel exp)
from .architectures import model_input_size
from .metadata import ModelMetadata, read_metadata_yaml, write_metadata_yaml
from .metadata import metadata_path_for as _metadata_path_for


@contextlib.contextmanager
def _quiet_jit() -> Iterator[None]:
    """Recent torch releases deprecate TorchScript in favour of torch.export, but TorchScript is what
    most released depth networks are exported as; keep its DeprecationWarnings out of logs."""
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', DeprecationWarning)
        yield


class MetricDepthHead(nn.Module):
    """Wraps a log-depth network so its output is depth in metres (what predictors consume)."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.exp(self.net(x))


def metadata_path_for(model_path: str | Path) -> Path:
    """The YAML beside a TorchScript model: ``x.yaml`` if it exists, else ``x.pt.yaml``."""
    return _metadata_path_for(model_path, 'TorchScript model')


def load_torchscript(
    path: str | Path, metadata_path: str | Path | None = None, device: str | torch.device = 'cpu'
) -> tuple[torch.jit.ScriptModule, ModelMetadata]:
    """Load a TorchScript model and its metadata; errors name the file at fault."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f'TorchScript model not found: {path}')
    metadata = read_metadata_yaml(metadata_path if metadata_path is not None else metadata_path_for(path))
    try:
        with _quiet_jit():
            module = torch.jit.load(str(path), map_location=device)
    except Exception as exc:  # torch raises RuntimeError / ValueError / zip errors for bad files
        raise ValueError(f'{path}: not a loadable TorchScript model ({type(exc).__name__}: {exc})') from None
    module.eval()
    return module, metadata


def export_torchscript(
    net: nn.Module, path: str | Path, metadata: ModelMetadata, metadata_path: str | Path | None = None
) -> tuple[Path, Path]:
    """Trace one of our log-depth networks (``MetricDepthHead`` applied) to ``path`` and write
    its YAML (``metadata`` with ``output_kind: metric_depth``, ``scale: 1``) beside it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    width, height = model_input_size(net)
    if metadata.input_size != (width, height):
        raise ValueError(
            f'metadata input size {metadata.input_size} differs from the network ({width}, {height})'
        )
    head = MetricDepthHead(copy.deepcopy(net)).eval().to('cpu')  # the caller's net stays put
    example = torch.zeros(1, 3, height, width)
    with torch.no_grad(), _quiet_jit():
        traced = torch.jit.trace(head, example, check_trace=False)
        traced.save(str(path))
    meta = ModelMetadata.from_dict({**metadata.to_dict(), 'output_kind': 'metric_depth', 'scale': 1.0})
    yaml_path = Path(metadata_path) if metadata_path is not None else path.with_suffix('.yaml')
    write_metadata_yaml(meta, yaml_path)
    return path, yaml_path
