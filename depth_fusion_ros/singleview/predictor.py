"""Single-view depth from one RGB image, whatever network produces it.

``load_predictor(spec, device)`` is the one entry point the single-view node and the
evaluation use. ``spec`` is:

* ``'default'``: the compact model shipped in ``depth_fusion_ros/models/`` (found next to
  this package, not through ament_index, so it works from a pip install and a colcon one);
* a checkpoint path (``.pt`` written by ``depth-fusion train``, see ``checkpoint.py``);
* an exported model with its metadata YAML beside it: ONNX ``.onnx`` run by ONNX Runtime
  (``onnx_model.py``), a ``torch.export`` program ``.pt2`` (``pt2_model.py``), or TorchScript
  ``.pt`` (``torchscript_model.py``). An exported model is run once at load on a blank image
  of its input size, so one that rejects that input fails at start, naming the file.

Weights come from local files only; nothing is downloaded. A ``DepthPredictor`` resizes the
image to the network's input size, normalises it as its metadata says, runs the network
and resizes the output back to the image size: ``predict(rgb) -> HxW float32`` holding
``output_kind`` values (metres for ``metric_depth``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)
from torch import nn

from ..ros_home import expand_ros_home
from ..torch_device import resolve_device
from .checkpoint import is_torchscript_file, load_checkpoint
from .export_formats import ONNX_SUFFIX, PT2_SUFFIX
from .metadata import ModelMetadata
from .onnx_model import load_onnx
from .pt2_model import load_pt2
from .torchscript_model import MetricDepthHead, load_torchscript

log = logging.getLogger(__name__)

#: The shipped model, relative to the package (``setup.py`` installs ``models/*.pt``).
MODELS_DIR = Path(__file__).resolve().parents[1] / 'models'
DEFAULT_MODEL_NAME = 'compact_synthetic.pt'
#: The simulated prior is an evaluation tool, never a network the nodes may load.
SIMULATED_SPEC = 'simulated'
#: The simulated prior as a disparity network gives it (inverse depth, unknown scale and shift).
SIMULATED_RELATIVE_SPEC = 'simulated_relative'
SIMULATED_SPECS = (SIMULATED_SPEC, SIMULATED_RELATIVE_SPEC)


def default_model_path() -> Path:
    return MODELS_DIR / DEFAULT_MODEL_NAME


def model_path(spec: str | Path) -> Path:
    """The file a model spec names: the shipped network for ``'default'``, else the path with
    ``~`` and a leading ``$ROS_HOME`` expanded (the adapted checkpoint's default place). One
    rule for the predictor, the adapter, the exporter and the node's ``adapt: auto``."""
    return default_model_path() if str(spec) == 'default' else expand_ros_home(str(spec))


def check_rgb(rgb: np.ndarray, what: str = 'image') -> np.ndarray:
    """Raise ``ValueError`` unless ``rgb`` is an HxWx3 uint8 array (the package's RGB convention)."""
    if not isinstance(rgb, np.ndarray):
        raise ValueError(f'{what} must be a numpy array (HxWx3 uint8 RGB), got {type(rgb).__name__}')
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f'{what} must be HxWx3 RGB, got shape {rgb.shape}')
    if rgb.dtype != np.uint8:
        raise ValueError(f'{what} must be uint8 RGB, got dtype {rgb.dtype}')
    if rgb.shape[0] < 2 or rgb.shape[1] < 2:
        raise ValueError(f'{what} is too small: {rgb.shape[1]}x{rgb.shape[0]}')
    return rgb


class DepthPredictor:
    """A network that maps RGB images to a depth-like map, with its preprocessing.

    ``module`` takes the normalised (B, 3, h, w) float tensor and returns (B, 1, h', w') or
    (B, h', w'); its output times ``metadata.scale`` is read as ``output_kind``.
    """

    def __init__(
        self, module: nn.Module, metadata: ModelMetadata, device: str | torch.device = 'cpu', name: str = ''
    ):
        self.device = resolve_device(device)
        self.module = module.to(self.device).eval()
        self.metadata = metadata
        self.name = name or type(module).__name__
        self._mean = torch.tensor(metadata.mean, dtype=torch.float32, device=self.device).view(1, 3, 1, 1)
        self._std = torch.tensor(metadata.std, dtype=torch.float32, device=self.device).view(1, 3, 1, 1)

    @property
    def output_kind(self) -> str:
        return self.metadata.output_kind

    @property
    def input_size(self) -> tuple[int, int]:
        """``(width, height)`` the network sees."""
        return self.metadata.input_size

    def __repr__(self) -> str:
        w, h = self.input_size
        return f'DepthPredictor({self.name}, {w}x{h}, {self.output_kind}, {self.device})'

    def preprocess(self, images: Sequence[np.ndarray]) -> torch.Tensor:
        """Resize each image to the input size and normalise: (B, 3, h, w) float32 on ``device``."""
        width, height = self.metadata.network_size(images[0].shape[1], images[0].shape[0])
        batch = []
        for i, rgb in enumerate(images):
            check_rgb(rgb, f'image {i}')
            if rgb.shape[:2] != (height, width):
                shrink = rgb.shape[1] > width and rgb.shape[0] > height
                rgb = cv2.resize(
                    rgb, (width, height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
                )
            batch.append(rgb)
        array = np.stack(batch)
        if self.metadata.channel_order == 'bgr':
            array = array[..., ::-1]
        x = torch.from_numpy(np.ascontiguousarray(array)).to(self.device)
        x = x.permute(0, 3, 1, 2).float() / self.metadata.pixel_scale
        return (x - self._mean) / self._std

    def _postprocess(
        self, raw: torch.Tensor | tuple | list, sizes: list[tuple[int, int]]
    ) -> list[np.ndarray]:
        if isinstance(raw, tuple | list):  # some exported networks return (depth, extras...)
            raw = raw[0]
        if not isinstance(raw, torch.Tensor):
            raise ValueError(f'{self.name}: network returned {type(raw).__name__}, expected a tensor')
        if raw.ndim == 3:
            raw = raw[:, None]
        if raw.ndim != 4 or raw.shape[1] != 1:
            raise ValueError(
                f'{self.name}: network output has shape {tuple(raw.shape)}, expected (B, 1, h, w)'
            )
        out = raw.float() * self.metadata.scale
        if self.output_kind == 'metric_depth':
            out = out.clamp(self.metadata.depth_min, self.metadata.depth_max)
        results = []
        for i, (h, w) in enumerate(sizes):
            o = out[i : i + 1]
            if o.shape[-2:] != (h, w):
                o = F.interpolate(o, size=(h, w), mode='bilinear', align_corners=False)
            results.append(o[0, 0].to('cpu', torch.float32).numpy())
        return results

    @torch.inference_mode()
    def predict_batch(self, images: Sequence[np.ndarray] | np.ndarray) -> list[np.ndarray]:
        """One forward pass for several images (each may have its own size)."""
        images = list(images)
        if not images:
            return []
        x = self.preprocess(images)
        return self._postprocess(self.module(x), [im.shape[:2] for im in images])

    def predict(self, rgb: np.ndarray) -> np.ndarray:
        """HxW float32 ``output_kind`` map at the size of ``rgb`` (HxWx3 uint8 RGB)."""
        return self.predict_batch([check_rgb(rgb)])[0]

    def check_network(self, source: str | Path) -> None:
        """Run the network once on a blank image of its input size; ``ValueError`` naming
        ``source`` when it rejects that input or returns something that is not a depth map."""
        width, height = self.input_size
        try:
            out = self.predict_batch([np.zeros((height, width, 3), dtype=np.uint8)])[0]
        except Exception as exc:  # a foreign network raises anything: shape guards, ORT errors...
            lines = str(exc).strip().splitlines()
            detail = f'{type(exc).__name__}: {lines[0] if lines else ""}'
            raise ValueError(
                f'{source}: the network fails on a {width}x{height} input as its YAML describes ({detail})'
            ) from None
        if out.shape != (height, width):
            raise ValueError(f'{source}: the network returned {out.shape}, expected {(height, width)}')


def predictor_from_network(
    net: nn.Module, metadata: ModelMetadata, device: str | torch.device = 'cpu', name: str = ''
) -> DepthPredictor:
    """A predictor around one of our log-depth networks (a training-time model, say); the
    network is moved to ``device`` and put in eval mode."""
    meta = ModelMetadata.from_dict({**metadata.to_dict(), 'output_kind': 'metric_depth', 'scale': 1.0})
    return DepthPredictor(MetricDepthHead(net), meta, device, name=name or getattr(net, 'architecture', ''))


def load_predictor(
    spec: str | Path = 'default', device: str | torch.device = 'cpu', metadata_path: str | Path | None = None
) -> DepthPredictor:
    """The predictor named by ``spec``: 'default', a checkpoint, or an exported model
    (``.onnx``, ``.pt2``, TorchScript ``.pt``) with its YAML.

    Raises ``FileNotFoundError`` for a missing file and ``ValueError`` for anything unusable,
    always naming the file, so a node fails at start rather than at the first image.
    """
    device = resolve_device(device)
    if str(spec) in SIMULATED_SPECS:
        raise ValueError(
            f'{str(spec)!r} is the evaluation-only simulated CNN prior, not a network: '
            f'use it through depth-fusion evaluate --single-view {spec}'
        )
    path = model_path(spec)
    if not path.is_file():
        hint = ' (the shipped model is missing: reinstall the package)' if str(spec) == 'default' else ''
        raise FileNotFoundError(f'single-view model not found: {path}{hint}')
    exported = _load_exported(path, metadata_path, device)
    if exported is not None:
        module, metadata, host = exported
        log.info('single-view model: %s %s (%s)', host, path, metadata.output_kind)
        predictor = DepthPredictor(module, metadata, device, name=path.name)
        predictor.check_network(path)
        return predictor
    ckpt = load_checkpoint(path, device)
    log.info('single-view model: %s checkpoint %s', ckpt.architecture, path)
    return predictor_from_network(ckpt.model, ckpt.metadata, device, name=f'{ckpt.architecture}:{path.name}')


def _load_exported(
    path: Path, metadata_path: str | Path | None, device: torch.device
) -> tuple[nn.Module, ModelMetadata, str] | None:
    """``(module, metadata, host)`` of an exported model (by suffix, then by content); None
    for a training checkpoint."""
    suffix = path.suffix.lower()
    if suffix == ONNX_SUFFIX:
        return (*load_onnx(path, metadata_path, device), 'ONNX Runtime')
    if suffix == PT2_SUFFIX:
        return (*load_pt2(path, metadata_path, device), 'torch.export')
    if is_torchscript_file(path):
        return (*load_torchscript(path, metadata_path, device), 'TorchScript')
    return None


def check_model(
    spec: str | Path, device: str | torch.device = 'cpu', *, allow_simulated: bool = False
) -> None:
    """Load ``spec`` once and drop it: what a command calls before it starts any work, so a
    model that cannot be loaded is a one-line error naming the file and the reason
    (``FileNotFoundError`` / ``ValueError``). The simulated sources pass when allowed."""
    if allow_simulated and str(spec) in SIMULATED_SPECS:
        return
    load_predictor(spec, device)
