"""What a depth network expects and what it returns: the metadata every model carries.

The same record travels inside our checkpoints (``metadata`` key) and beside an exported
model (TorchScript ``.pt``, ONNX ``.onnx``, ``torch.export`` ``.pt2``: a YAML file), so the
predictor can preprocess any network the same way: resize the RGB image to ``input_width`` x
``input_height`` (``dynamic_input`` networks: to its own size rounded to ``size_multiple``),
scale it to ``[0, 1]`` (``pixel_scale``), normalise with ``mean``/``std`` per channel, run the
network, multiply its output by ``scale`` and read it as ``output_kind``.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

#: What the network's output means. Only ``metric_depth`` is metres; the fusion maps the
#: other two to metric with its RANSAC fit (m ≈ a·s + b).
OUTPUT_KINDS = ('metric_depth', 'inverse_depth', 'relative_depth')

#: ImageNet statistics: what VGG-style first scales and most modern encoders were trained with.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass
class ModelMetadata:
    """Input contract and output meaning of a depth network (see ``docs/single_view.md``)."""

    input_width: int = 320
    input_height: int = 240
    #: True: the network takes any input size (dynamic height/width axes); it is fed the
    #: image at its own size, rounded to a multiple of ``size_multiple``. ``input_width`` x
    #: ``input_height`` is then only the size checked at load time.
    dynamic_input: bool = False
    #: Dynamic inputs: both sides are rounded to a multiple of this (14 for ViT/DINOv2
    #: patches, 32 for many CNN encoders).
    size_multiple: int = 1
    #: Per-channel mean and std applied after dividing the uint8 image by ``pixel_scale``.
    mean: tuple[float, float, float] = IMAGENET_MEAN
    std: tuple[float, float, float] = IMAGENET_STD
    #: 255 maps uint8 to [0, 1]; 1 feeds raw 0..255 values (some exported networks want that).
    pixel_scale: float = 255.0
    #: 'rgb' or 'bgr': the channel order the network was trained with.
    channel_order: str = 'rgb'
    output_kind: str = 'metric_depth'
    #: The network's output is multiplied by this (e.g. 0.001 for a millimetre network).
    scale: float = 1.0
    #: Plausible output range in metres (metric networks clamp to it); informative otherwise.
    depth_min: float = 0.1
    depth_max: float = 10.0
    #: Free-form provenance: training data, git commit, seed, metrics, command line...
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.mean = tuple(float(v) for v in self.mean)  # type: ignore[assignment]
        self.std = tuple(float(v) for v in self.std)  # type: ignore[assignment]
        self.validate()

    def validate(self, source: str = 'metadata') -> None:
        """Raise ``ValueError`` naming ``source`` and the field when a value cannot work."""

        def bad(msg: str) -> ValueError:
            return ValueError(f'{source}: {msg}')

        if int(self.input_width) <= 0 or int(self.input_height) <= 0:
            raise bad(f'input size must be positive, got {self.input_width}x{self.input_height}')
        if not isinstance(self.dynamic_input, bool):
            raise bad(f'dynamic_input must be true or false, got {self.dynamic_input!r}')
        if (
            isinstance(self.size_multiple, bool)
            or not isinstance(self.size_multiple, int)
            or self.size_multiple < 1
        ):
            raise bad(f'size_multiple must be an integer >= 1, got {self.size_multiple!r}')
        if len(self.mean) != 3 or len(self.std) != 3:
            raise bad(f'mean and std need 3 values (one per channel), got {self.mean} and {self.std}')
        if not all(math.isfinite(s) and s > 0 for s in self.std):
            raise bad(f'std values must be positive, got {self.std}')
        if self.output_kind not in OUTPUT_KINDS:
            raise bad(f'output_kind must be one of {", ".join(OUTPUT_KINDS)}, got {self.output_kind!r}')
        if self.channel_order not in ('rgb', 'bgr'):
            raise bad(f"channel_order must be 'rgb' or 'bgr', got {self.channel_order!r}")
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise bad(f'scale must be a positive number, got {self.scale}')
        if not (math.isfinite(self.pixel_scale) and self.pixel_scale > 0):
            raise bad(f'pixel_scale must be a positive number, got {self.pixel_scale}')
        if not (0 < self.depth_min < self.depth_max):
            raise bad(f'need 0 < depth_min < depth_max, got {self.depth_min} and {self.depth_max}')

    @property
    def input_size(self) -> tuple[int, int]:
        """``(width, height)``, the order OpenCV expects."""
        return (int(self.input_width), int(self.input_height))

    def network_size(self, width: int, height: int) -> tuple[int, int]:
        """``(width, height)`` the network is fed for an image of that size: the fixed input
        size, or (dynamic inputs) the image's own size rounded to ``size_multiple``."""
        if not self.dynamic_input:
            return self.input_size
        k = int(self.size_multiple)
        return (max(k, round(width / k) * k), max(k, round(height / k) * k))

    def to_dict(self) -> dict[str, Any]:
        """Plain types only, so checkpoints stay loadable with ``weights_only=True``."""
        out = dataclasses.asdict(self)
        out['mean'] = list(self.mean)
        out['std'] = list(self.std)
        # JSON round trip: tuples become lists and odd objects strings, so YAML and
        # weights_only torch.load both accept the result.
        out['info'] = json.loads(json.dumps(self.info, default=str))
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = 'metadata') -> ModelMetadata:
        """Build from a dict; unknown keys and wrong types raise ``ValueError`` naming ``source``."""
        if not isinstance(data, dict):
            raise ValueError(f'{source}: expected a mapping of metadata fields, got {type(data).__name__}')
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f'{source}: unknown metadata field(s) {unknown}; known: {sorted(known)}')
        try:
            meta = cls(**data)
        except (TypeError, ValueError) as exc:
            raise ValueError(f'{source}: {exc}') from None
        meta.validate(source)
        return meta


def check_input_size(
    path: Path, metadata: ModelMetadata, shape: list[Any], fixed_h: int | None, fixed_w: int | None, what: str
) -> None:
    """An exported ``what`` ('model', 'program') with input ``shape`` (H, W fixed or None) can
    take what its YAML promises: a dynamic size, or the YAML's fixed one. ``ValueError`` naming
    ``path`` otherwise (shared by the ONNX and torch.export hosts)."""
    width, height = metadata.input_size
    if metadata.dynamic_input and (fixed_h is not None or fixed_w is not None):
        raise ValueError(
            f'{path}: the YAML says dynamic_input but the {what} fixes its input to {shape[3]}x{shape[2]} '
            '(export it with dynamic height/width, or set input_width/input_height instead)'
        )
    if fixed_w not in (None, width) or fixed_h not in (None, height):
        raise ValueError(
            f'{path}: the {what} takes {shape[3]}x{shape[2]} images but its YAML says '
            f'input_width x input_height = {width}x{height}'
        )


def metadata_path_for(model_path: str | Path, what: str = 'model') -> Path:
    """The YAML beside ``model_path``: ``x.yaml`` if it exists, else ``x.<suffix>.yaml``."""
    model_path = Path(model_path)
    same_stem = model_path.with_suffix('.yaml')
    if same_stem.is_file():
        return same_stem
    appended = model_path.with_name(model_path.name + '.yaml')
    if appended.is_file():
        return appended
    raise FileNotFoundError(
        f'metadata YAML for {what} {model_path} not found: expected {same_stem} or {appended} '
        '(input size, mean/std, output_kind, scale; see docs/single_view.md)'
    )


def read_metadata_yaml(path: str | Path) -> ModelMetadata:
    """Read the YAML that sits beside an exported model; errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f'model metadata file not found: {path}')
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        mark = getattr(exc, 'problem_mark', None)
        where = f' line {mark.line + 1}' if mark is not None else ''
        raise ValueError(f'{path}{where}: not valid YAML ({exc})') from None
    return ModelMetadata.from_dict(data or {}, source=str(path))


def metadata_yaml_text(meta: ModelMetadata) -> str:
    """``meta`` as the YAML text :func:`write_metadata_yaml` writes."""
    return yaml.safe_dump(meta.to_dict(), sort_keys=False)


def write_metadata_yaml(meta: ModelMetadata, path: str | Path) -> Path:
    """Write ``meta`` as YAML (the format ``read_metadata_yaml`` reads)."""
    path = Path(path)
    path.write_text(metadata_yaml_text(meta))
    return path
