"""The three-scale depth network of Eigen & Fergus (ICCV 2015), the one the paper used (§III-B).

Built from ``torch.nn`` only (no torchvision, no downloaded weights) and trainable:

* **Scale 1** (global, coarse): VGG-16 convolutions (13 conv 3x3 + 5 max-pools) on the whole
  image, then two fully connected layers (4096, then 64 x H/16 x W/16) whose output is
  reshaped to a coarse 64-channel map. The fully connected layers see the whole image, which
  is what lets the network reason about absolute (metric) scale.
* **Scale 2** (mid-level): a 9x9 stride-2 convolution + 2x2 pooling of the image gives 1/4
  resolution features; concatenated with the upsampled scale-1 map, four 5x5 convolutions
  predict a first depth map (74x55 for the 304x228 input).
* **Scale 3** (fine): a 9x9 stride-2 convolution + 2x2 stride-1 pooling of the image gives
  1/2-resolution features; concatenated with the upsampled scale-2 depth, 5x5 convolutions
  refine it to the final 147x109 map.

The network predicts **log depth** (the scale-invariant loss is defined on logs); ``depth``
exponentiates. Input size: Eigen et al. run the 320x240 image through the central 304x228
region; we resize the whole 320x240 working image to 304x228 instead (``ModelMetadata``
input size), so the 147x109 output covers the full field of view and upsamples back onto
the working grid without a border. Every width is a parameter (``EigenConfig``) so tests can
build a small instance; the defaults are the paper's (~218 M parameters, 870 MB in fp32).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)
from torch import nn

#: VGG-16: convolutions per block (each block ends with a 2x2 max-pool).
VGG16_DEPTHS = (2, 2, 3, 3, 3)
VGG16_WIDTHS = (64, 128, 256, 512, 512)


@dataclass
class EigenConfig:
    """Sizes of the three scales (defaults: Eigen & Fergus 2015, VGG version, depth task)."""

    input_width: int = 304
    input_height: int = 228
    vgg_widths: tuple[int, ...] = VGG16_WIDTHS
    vgg_depths: tuple[int, ...] = VGG16_DEPTHS
    fc_dim: int = 4096
    coarse_channels: int = 64
    scale2_image_channels: int = 96
    scale2_channels: int = 64
    scale2_layers: int = 3
    scale3_image_channels: int = 64
    scale3_channels: int = 64
    scale3_layers: int = 2
    dropout: float = 0.5
    #: Initial output (log metres): the last bias starts at log(2 m), a typical indoor depth.
    init_log_depth: float = math.log(2.0)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> EigenConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f'unknown eigen arch_config field(s) {unknown}; known: {sorted(known)}')
        cfg = cls(**data)
        cfg.vgg_widths = tuple(int(v) for v in cfg.vgg_widths)
        cfg.vgg_depths = tuple(int(v) for v in cfg.vgg_depths)
        if len(cfg.vgg_widths) != 5 or len(cfg.vgg_depths) != 5:
            raise ValueError('eigen arch_config: vgg_widths and vgg_depths need 5 entries (VGG blocks)')
        if cfg.input_width < 64 or cfg.input_height < 64:
            raise ValueError(f'eigen input must be at least 64x64, got {cfg.input_width}x{cfg.input_height}')
        return cfg

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out['vgg_widths'] = list(self.vgg_widths)
        out['vgg_depths'] = list(self.vgg_depths)
        return out

    @property
    def coarse_size(self) -> tuple[int, int]:
        """(height, width) of the reshaped scale-1 output: 1/16 of the input (14x19 for 304x228)."""
        return (self.input_height // 16, self.input_width // 16)

    @property
    def vgg_out_size(self) -> tuple[int, int]:
        """(height, width) after the five VGG pools (7x9 for 304x228)."""
        h, w = self.input_height, self.input_width
        for _ in range(5):
            h, w = h // 2, w // 2
        return (h, w)


def _conv_relu(cin: int, cout: int, k: int, stride: int = 1, padding: int = 0) -> list[nn.Module]:
    return [nn.Conv2d(cin, cout, k, stride=stride, padding=padding), nn.ReLU(inplace=True)]


class Scale1Vgg(nn.Module):
    """VGG-16 features + two fully connected layers -> coarse (B, C, H/16, W/16) map."""

    def __init__(self, cfg: EigenConfig):
        super().__init__()
        layers: list[nn.Module] = []
        cin = 3
        for width, depth in zip(cfg.vgg_widths, cfg.vgg_depths, strict=True):
            for _ in range(depth):
                layers += _conv_relu(cin, width, 3, padding=1)
                cin = width
            layers.append(nn.MaxPool2d(2, 2))
        self.features = nn.Sequential(*layers)
        vh, vw = cfg.vgg_out_size
        ch, cw = cfg.coarse_size
        self.coarse_shape = (cfg.coarse_channels, ch, cw)
        self.fc = nn.Sequential(
            nn.Flatten(),
            nn.Linear(cin * vh * vw, cfg.fc_dim),
            nn.ReLU(inplace=True),
            nn.Dropout(cfg.dropout),
            nn.Linear(cfg.fc_dim, cfg.coarse_channels * ch * cw),
            nn.ReLU(inplace=True),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(self.features(x)).view(x.shape[0], *self.coarse_shape)


class RefineScale(nn.Module):
    """Image conv 9x9/2 + pool, concatenated with the previous scale, then 5x5 convolutions."""

    def __init__(self, image_channels: int, prev_channels: int, channels: int, layers: int, pool_stride: int):
        super().__init__()
        self.image = nn.Sequential(
            *_conv_relu(3, image_channels, 9, stride=2), nn.MaxPool2d(2, stride=pool_stride)
        )
        body: list[nn.Module] = []
        cin = image_channels + prev_channels
        for _ in range(layers):
            body += _conv_relu(cin, channels, 5, padding=2)
            cin = channels
        self.body = nn.Sequential(*body)
        self.out = nn.Conv2d(cin, 1, 5, padding=2)

    def forward(self, x: torch.Tensor, prev: torch.Tensor) -> torch.Tensor:
        feats = self.image(x)
        prev = F.interpolate(prev, size=feats.shape[-2:], mode='bilinear', align_corners=False)
        return self.out(self.body(torch.cat((feats, prev), dim=1)))


class EigenFergusNet(nn.Module):
    """Three-scale network: ``forward(x)`` takes normalised (B, 3, H, W), returns log depth
    (B, 1, h, w) with ``(h, w) = output_size`` (109x147 for the default 228x304 input)."""

    architecture = 'eigen'

    def __init__(self, cfg: EigenConfig | None = None):
        super().__init__()
        self.cfg = cfg or EigenConfig()
        c = self.cfg
        self.scale1 = Scale1Vgg(c)
        self.scale2 = RefineScale(
            c.scale2_image_channels, c.coarse_channels, c.scale2_channels, c.scale2_layers, 2
        )
        self.scale3 = RefineScale(c.scale3_image_channels, 1, c.scale3_channels, c.scale3_layers, 1)
        self._init_weights()

    def _init_weights(self) -> None:
        for m in self.modules():
            if isinstance(m, nn.Conv2d | nn.Linear):
                nn.init.kaiming_normal_(m.weight, nonlinearity='relu')
                nn.init.zeros_(m.bias)
        for head in (self.scale2.out, self.scale3.out):
            nn.init.normal_(head.weight, std=1e-3)
            nn.init.constant_(head.bias, self.cfg.init_log_depth)

    @property
    def output_size(self) -> tuple[int, int]:
        """(height, width) of the final map for the configured input size."""
        h = (self.cfg.input_height - 9) // 2 + 1 - 1
        w = (self.cfg.input_width - 9) // 2 + 1 - 1
        return (h, w)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        coarse = self.scale1(x)
        mid = self.scale2(x, coarse)
        return self.scale3(x, mid)
