"""Bring-your-own network as ONNX: a ``.onnx`` file run by ONNX Runtime, plus its metadata YAML.

Most released monocular depth networks (Depth Anything v1/v2/v3, MiDaS, DPT, Metric3D,
UniDepth...) circulate as ONNX files. ONNX Runtime runs them without their source code or
torch: ``CPUExecutionProvider`` by default, ``CUDAExecutionProvider`` when the ``device`` is
CUDA and the installed ``onnxruntime`` has it (``onnxruntime-gpu``); otherwise a one-line
notice and the CPU. The YAML beside the model (``ModelMetadata`` fields, same as for
TorchScript, see ``docs/single_view.md``) says how to feed it and what its output means.

``OnnxDepthModule`` makes a session look like a torch module to ``DepthPredictor``: tensor
in, tensor out, on the caller's device (the copy to and from numpy is the price of a
torch-free runtime). At load time the model's declared input is checked against the YAML
(one float image input, 3 channels, the YAML's size where the model fixes it), so a
mismatch is an error at start, not at the first keyframe.

``export_onnx`` writes one of our networks (or any ``nn.Module``) with a dynamic batch axis,
through torch's ``torch.export``-based exporter (``dynamo=True``; needs ``onnx`` and
``onnxscript``, pinned in ``scripts/venv.sh``).
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from .metadata import ModelMetadata, check_input_size, metadata_path_for, read_metadata_yaml

log = logging.getLogger(__name__)

#: Input element types we can feed (numpy dtype per ONNX type string).
INPUT_TYPES = {'tensor(float)': np.float32, 'tensor(float16)': np.float16, 'tensor(double)': np.float64}


def select_providers(device: torch.device) -> list[Any]:
    """Execution providers for ``device``: CUDA (then CPU) when asked for and available."""
    import onnxruntime as ort

    if device.type == 'cuda':
        if 'CUDAExecutionProvider' in ort.get_available_providers():
            return [('CUDAExecutionProvider', {'device_id': device.index or 0}), 'CPUExecutionProvider']
        log.warning(
            'device %s: onnxruntime %s has no CUDAExecutionProvider (install onnxruntime-gpu); '
            'the ONNX model runs on the CPU',
            device,
            ort.__version__,
        )
    return ['CPUExecutionProvider']


def _dim(d: Any) -> int | None:
    """A fixed dimension as int, ``None`` for a symbolic (dynamic) one."""
    return d if isinstance(d, int) and d > 0 else None


class OnnxDepthModule(nn.Module):
    """An ONNX Runtime session behind the ``nn.Module`` call interface ``DepthPredictor`` uses."""

    def __init__(self, session: Any, path: Path):
        super().__init__()
        self.session = session
        self.path = path
        inp = session.get_inputs()[0]
        self.input_name = inp.name
        self.input_shape = list(inp.shape)
        self.input_dtype = INPUT_TYPES[inp.type]
        self.output_name = session.get_outputs()[0].name
        #: A model exported with a fixed batch of 1 is run image by image.
        self.fixed_batch = _dim(self.input_shape[0])

    @property
    def providers(self) -> list[str]:
        return list(self.session.get_providers())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        array = x.detach().to('cpu').numpy().astype(self.input_dtype, copy=False)
        if self.fixed_batch is not None and array.shape[0] != self.fixed_batch:
            parts = [
                self._run(array[i : i + self.fixed_batch]) for i in range(0, array.shape[0], self.fixed_batch)
            ]
            out = np.concatenate(parts)
        else:
            out = self._run(array)
        return torch.from_numpy(np.ascontiguousarray(out, dtype=np.float32)).to(x.device)

    def _run(self, array: np.ndarray) -> np.ndarray:
        return self.session.run([self.output_name], {self.input_name: array})[0]


def check_onnx_signature(session: Any, metadata: ModelMetadata, path: Path) -> None:
    """Raise ``ValueError`` naming ``path`` when the model cannot take what the YAML promises."""
    inputs = session.get_inputs()
    if len(inputs) != 1:
        names = ', '.join(f'{i.name} {i.shape}' for i in inputs)
        raise ValueError(
            f'{path}: expected one image input (B, 3, H, W), the model has {len(inputs)}: {names}'
        )
    inp = inputs[0]
    if inp.type not in INPUT_TYPES:
        raise ValueError(f'{path}: input {inp.name!r} is {inp.type}, expected a float tensor')
    shape = list(inp.shape)
    if len(shape) != 4:
        raise ValueError(f'{path}: input {inp.name!r} has shape {shape}, expected (B, 3, H, W)')
    if _dim(shape[1]) not in (None, 3):
        raise ValueError(f'{path}: input {inp.name!r} has {shape[1]} channels, expected 3 (B, 3, H, W)')
    check_input_size(path, metadata, shape, _dim(shape[2]), _dim(shape[3]), 'model')


def load_onnx(
    path: str | Path, metadata_path: str | Path | None = None, device: str | torch.device = 'cpu'
) -> tuple[OnnxDepthModule, ModelMetadata]:
    """ONNX Runtime session of ``path`` (on ``device`` where possible) and its metadata;
    errors name the file and the reason."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f'ONNX model not found: {path}')
    try:
        import onnxruntime as ort
    except ImportError:
        raise ValueError(
            f'{path}: ONNX models need onnxruntime (pip install onnxruntime; see scripts/venv.sh)'
        ) from None
    metadata = read_metadata_yaml(
        metadata_path if metadata_path is not None else metadata_path_for(path, 'ONNX model')
    )
    options = ort.SessionOptions()
    # Same CPU budget as torch in this process (depth-fusion run --threads sets it per node).
    options.intra_op_num_threads = max(1, torch.get_num_threads())
    options.inter_op_num_threads = 1
    options.log_severity_level = 3  # errors only: ORT's warnings are not ours to act on
    try:
        session = ort.InferenceSession(
            str(path), sess_options=options, providers=select_providers(torch.device(device))
        )
    except Exception as exc:  # InvalidProtobuf, InvalidGraph, Fail, NotImplemented, ...
        raise ValueError(f'{path}: not a loadable ONNX model ({_first_line(exc)})') from None
    check_onnx_signature(session, metadata, path)
    module = OnnxDepthModule(session, path)
    log.debug('ONNX model %s on %s', path, module.providers)
    return module, metadata


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f'{type(exc).__name__}: {text[0] if text else ""}'.rstrip(': ')


@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
    """torch's ONNX exporter prints progress lines and its graph passes log at INFO; keep the
    CLI's output ours."""
    loggers = [logging.getLogger(name) for name in ('onnx_ir', 'onnxscript', 'torch.onnx')]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.WARNING)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            yield
    finally:
        for lg, level in zip(loggers, levels, strict=True):
            lg.setLevel(level)


def export_onnx(
    module: nn.Module,
    path: str | Path,
    example: torch.Tensor,
    *,
    dynamic_batch: bool = True,
    opset: int | None = None,
) -> Path:
    """Write ``module`` (eval mode, CPU) as one self-contained ONNX file (weights inside).

    ``example``: an input of the size the model is fed, (B, 3, H, W). The batch axis is
    dynamic unless ``dynamic_batch=False``. Atomic: written beside ``path`` and renamed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    module = module.eval().to('cpu')
    if dynamic_batch and example.shape[0] < 2:
        example = example.expand(2, *example.shape[1:]).contiguous()  # batch 1 would be specialised
    dynamic_shapes = ({0: torch.export.Dim('batch', min=1, max=1024)},) if dynamic_batch else None
    tmp = path.with_name(path.name + '.tmp.onnx')
    try:
        with torch.no_grad(), _quiet_exporter():
            torch.onnx.export(
                module,
                (example,),
                str(tmp),
                dynamo=True,
                external_data=False,
                input_names=['image'],
                output_names=['depth'],
                dynamic_shapes=dynamic_shapes,
                opset_version=opset,
                verbose=False,
            )
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
