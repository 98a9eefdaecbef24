"""Checkpoints of our trainable networks: weights plus everything needed to use them.

Format (``format_version`` 1), a ``torch.save`` dict of plain types and tensors only, so it
loads with ``torch.load(..., weights_only=True)`` (no pickled code runs at load time)::

    format_version  int, 1
    architecture    'compact' | 'eigen'
    arch_config     dict: the architecture's config (CompactConfig / EigenConfig fields)
    state_dict      the network's parameters and buffers (float32, or float16 when shipped
                    small; converted back to float32 at load)
    metadata        ModelMetadata.to_dict(): input size, mean/std, output kind, depth range,
                    info (training data, git commit, seed, metrics, command)
    training_state  optional: optimizer state, step, epoch, best validation error (resume)

A missing, corrupt or mismatched checkpoint raises at load time (``FileNotFoundError`` or
``CheckpointError``, a ``ValueError``) with the file name and what is wrong.
"""

from __future__ import annotations

import logging
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from .architectures import ARCHITECTURES, build_model, model_arch_config
from .metadata import ModelMetadata

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
REQUIRED_KEYS = ('format_version', 'architecture', 'arch_config', 'state_dict', 'metadata')


class CheckpointError(ValueError):
    """A checkpoint file exists but cannot be used (corrupt, wrong format, mismatched weights)."""


@dataclass
class Checkpoint:
    """A loaded checkpoint: the network (eval mode, on ``device``) and what came with it."""

    path: Path
    architecture: str
    arch_config: dict[str, Any]
    model: nn.Module
    metadata: ModelMetadata
    training_state: dict[str, Any] | None = None


def is_torchscript_file(path: str | Path) -> bool:
    """TorchScript archives hold compiled code (``<name>/code/...``); plain checkpoints do not."""
    try:
        with zipfile.ZipFile(path) as zf:
            return any('/code/' in name for name in zf.namelist())
    except (zipfile.BadZipFile, OSError):
        return False


def is_exported_model(path: str | Path) -> bool:
    """An exported network (ONNX, torch.export .pt2, TorchScript): inference only, no
    trainable weights the adapter could update."""
    return Path(path).suffix.lower() in ('.onnx', '.pt2') or is_torchscript_file(path)


def save_checkpoint(
    path: str | Path,
    model: nn.Module,
    metadata: ModelMetadata,
    *,
    training_state: dict[str, Any] | None = None,
    half: bool = False,
) -> Path:
    """Write ``model`` (one of ``ARCHITECTURES``) with its metadata; atomic (tmp + rename).

    ``half=True`` stores floating-point weights as float16 (half the size, for the shipped
    model); ``load_checkpoint`` converts them back to float32.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().to('cpu').clone() for k, v in model.state_dict().items()}
    if half:
        state = {k: v.half() if v.is_floating_point() else v for k, v in state.items()}
    doc: dict[str, Any] = {
        'format_version': FORMAT_VERSION,
        'architecture': model.architecture,
        'arch_config': model_arch_config(model),
        'state_dict': state,
        'metadata': metadata.to_dict(),
    }
    if training_state is not None:
        doc['training_state'] = training_state
    tmp = path.with_name(path.name + '.tmp')
    torch.save(doc, tmp)
    os.replace(tmp, path)
    return path


def read_checkpoint_dict(path: str | Path) -> dict[str, Any]:
    """The raw checkpoint dict, checked for the required keys and version."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f'checkpoint not found: {path}')
    if is_torchscript_file(path):
        raise CheckpointError(
            f'{path} is a TorchScript model, not a training checkpoint: load it with '
            'load_predictor (it needs its metadata YAML beside it)'
        )
    try:
        doc = torch.load(path, map_location='cpu', weights_only=True)
    except Exception as exc:  # torch raises many types for truncated / foreign files
        raise CheckpointError(f'{path}: not a readable checkpoint ({type(exc).__name__}: {exc})') from None
    if not isinstance(doc, dict):
        raise CheckpointError(f'{path}: expected a checkpoint dict, found {type(doc).__name__}')
    missing = [k for k in REQUIRED_KEYS if k not in doc]
    if missing:
        raise CheckpointError(f'{path}: not a depth_fusion_ros checkpoint (missing {", ".join(missing)})')
    if doc['format_version'] != FORMAT_VERSION:
        raise CheckpointError(
            f'{path}: checkpoint format_version {doc["format_version"]!r}, this code reads {FORMAT_VERSION}'
        )
    if doc['architecture'] not in ARCHITECTURES:
        raise CheckpointError(
            f'{path}: unknown architecture {doc["architecture"]!r} (known: {", ".join(ARCHITECTURES)})'
        )
    return doc


def load_checkpoint(path: str | Path, device: str | torch.device = 'cpu') -> Checkpoint:
    """Rebuild the network of a checkpoint, load its weights (strictly) and its metadata."""
    path = Path(path)
    doc = read_checkpoint_dict(path)
    try:
        model = build_model(doc['architecture'], doc['arch_config'])
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f'{path}: bad arch_config for {doc["architecture"]!r}: {exc}') from None
    try:
        model.load_state_dict(doc['state_dict'], strict=True)
    except RuntimeError as exc:
        summary = str(exc).strip().splitlines()
        detail = '; '.join(line.strip() for line in summary[1:4]) or summary[0]
        raise CheckpointError(
            f'{path}: weights do not match architecture {doc["architecture"]!r} '
            f'with its arch_config ({detail})'
        ) from None
    try:
        metadata = ModelMetadata.from_dict(doc['metadata'], source=f'{path} metadata')
    except ValueError as exc:
        raise CheckpointError(str(exc)) from None
    model.to(device).eval()
    log.debug('loaded %s checkpoint %s', doc['architecture'], path)
    return Checkpoint(
        path=path,
        architecture=doc['architecture'],
        arch_config=dict(doc['arch_config']),
        model=model,
        metadata=metadata,
        training_state=doc.get('training_state'),
    )
