"""``depth-fusion export``: one of our networks as an ONNX, ``torch.export`` or TorchScript file.

The shipped compact network (or a checkpoint written by ``depth-fusion train``) is exported
with ``exp`` of its log depth baked in, so the file outputs metres, and the metadata YAML is
written beside it (the same path with ``.yaml``): ``--single-view PATH`` and the node's
``model: PATH`` then load it as they would any third-party model. The host is chosen by
the suffix when the model is loaded, so the suffix must match the format.
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch

from .checkpoint import load_checkpoint
from .export_formats import FORMATS
from .metadata import ModelMetadata, metadata_yaml_text, write_metadata_yaml
from .onnx_model import export_onnx
from .pt2_model import export_pt2
from .torchscript_model import MetricDepthHead, export_torchscript

log = logging.getLogger(__name__)


def format_for(out: Path, fmt: str | None) -> str:
    """The export format: ``fmt``, or the one ``out``'s suffix names; checks they agree."""
    by_suffix = {suffix: name for name, suffix in FORMATS.items()}
    if fmt is None:
        if out.suffix.lower() not in by_suffix:
            raise ValueError(
                f'cannot tell the format from {out}: give --format ({", ".join(FORMATS)}) or a '
                f'{", ".join(FORMATS.values())} file name'
            )
        return by_suffix[out.suffix.lower()]
    if fmt not in FORMATS:
        raise ValueError(f'unknown export format {fmt!r}; known: {", ".join(FORMATS)}')
    if out.suffix.lower() != FORMATS[fmt]:
        raise ValueError(
            f'--out {out} must end in {FORMATS[fmt]} for --format {fmt} '
            '(the loader picks ONNX Runtime, torch.export or TorchScript by the suffix)'
        )
    return fmt


def _check_yaml(yaml_path: Path, text: str, overwrite: bool) -> None:
    """Refuse to replace another model's YAML. One YAML serves every format of a stem
    (``compact.onnx``, ``compact.pt2`` and ``compact.pt`` all read ``compact.yaml``), so the same
    text written again is no loss; different text is someone's model description."""
    if overwrite or not yaml_path.exists() or yaml_path.read_text() == text:
        return
    raise ValueError(
        f'{yaml_path} already exists and describes another model (pass --overwrite to replace it)'
    )


def export_network(
    out: str | Path, fmt: str | None = None, model: str | Path = 'default', overwrite: bool = False
) -> tuple[Path, Path]:
    """Export the checkpoint ``model`` ('default': the shipped network) to ``out`` in ``fmt``
    and write its YAML beside it; returns ``(model_path, yaml_path)``. The YAML carries no
    format (the loader picks the host by the suffix), so every format of one stem shares it."""
    from .predictor import model_path

    out = Path(out)
    fmt = format_for(out, fmt)
    source = model_path(model)
    ckpt = load_checkpoint(source, 'cpu')  # names the file when it is missing or not a checkpoint
    info = {**ckpt.metadata.info, 'exported_from': str(source)}
    meta = ModelMetadata.from_dict(
        {**ckpt.metadata.to_dict(), 'output_kind': 'metric_depth', 'scale': 1.0, 'info': info}
    )
    yaml_path = out.with_suffix('.yaml')
    _check_yaml(yaml_path, metadata_yaml_text(meta), overwrite)
    if fmt == 'torchscript':
        return export_torchscript(ckpt.model, out, meta, yaml_path)
    width, height = meta.input_size
    example = torch.zeros(1, 3, height, width)
    head = MetricDepthHead(ckpt.model).eval()
    if fmt == 'onnx':
        export_onnx(head, out, example)
    else:
        export_pt2(head, out, example)
    write_metadata_yaml(meta, yaml_path)
    log.info('exported %s (%s) to %s with %s', source, ckpt.architecture, out, yaml_path)
    return out, yaml_path
