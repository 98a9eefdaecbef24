"""A compact encoder-decoder depth network for CPU use (the demo's default single-view model).

Why this shape: the fusion only needs the *local structure* of the single-view depth (its
gradients and planes, paper §III-C) plus a rough global scale, and it must run at camera
rate on a laptop CPU. So: a U-Net with depthwise-separable convolutions (MobileNet-style,
a few hundred thousand to a few million parameters), skip connections that keep edges
where the image has them, and a global-context vector (image-wide average pool + linear)
injected at the bottleneck, which gives every pixel the whole-image view that the fully
connected layers give Eigen's scale 1 (needed for metric scale). The output is log depth
at half the input resolution; the predictor upsamples it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)
from torch import nn


@dataclass
class CompactConfig:
    """Widths and depths of the encoder stages (strides 2, 4, 8, 16, 32) and decoder."""

    input_width: int = 320
    input_height: int = 240
    #: Narrow at high resolution (where FLOPs are), wide at low resolution (where the
    #: parameters are cheap): ~0.45 M parameters, ~0.29 GFLOP (0.14 G multiply-adds) at 320x240.
    encoder_widths: tuple[int, ...] = (16, 24, 48, 128, 256)
    #: Extra stride-1 blocks per encoder stage (after the first, possibly strided, block).
    encoder_blocks: tuple[int, ...] = (0, 1, 1, 2, 2)
    #: Decoder widths at strides 16, 8, 4, 2 (one per skip connection).
    decoder_widths: tuple[int, ...] = (128, 64, 24, 16)
    init_log_depth: float = math.log(2.0)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CompactConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f'unknown compact arch_config field(s) {unknown}; known: {sorted(known)}')
        cfg = cls(**data)
        cfg.encoder_widths = tuple(int(v) for v in cfg.encoder_widths)
        cfg.encoder_blocks = tuple(int(v) for v in cfg.encoder_blocks)
        cfg.decoder_widths = tuple(int(v) for v in cfg.decoder_widths)
        if len(cfg.encoder_widths) != 5 or len(cfg.encoder_blocks) != 5 or len(cfg.decoder_widths) != 4:
            raise ValueError('compact arch_config: 5 encoder widths/blocks and 4 decoder widths are needed')
        if cfg.input_width < 32 or cfg.input_height < 32:
            raise ValueError(
                f'compact input must be at least 32x32, got {cfg.input_width}x{cfg.input_height}'
            )
        return cfg

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        for key in ('encoder_widths', 'encoder_blocks', 'decoder_widths'):
            out[key] = list(out[key])
        return out


class SeparableBlock(nn.Module):
    """Depthwise 3x3 (maybe strided) + pointwise 1x1, each with BatchNorm and ReLU;
    residual when shapes allow it (cheap depth, stable training)."""

    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        self.depthwise = nn.Conv2d(cin, cin, 3, stride=stride, padding=1, groups=cin, bias=False)
        self.bn1 = nn.BatchNorm2d(cin)
        self.pointwise = nn.Conv2d(cin, cout, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.residual = stride == 1 and cin == cout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.bn1(self.depthwise(x)), inplace=True)
        y = self.bn2(self.pointwise(y))
        return F.relu(y + x if self.residual else y, inplace=True)


def _stage(cin: int, cout: int, extra_blocks: int, stride: int) -> nn.Sequential:
    blocks = [SeparableBlock(cin, cout, stride)]
    blocks += [SeparableBlock(cout, cout) for _ in range(extra_blocks)]
    return nn.Sequential(*blocks)


class CompactDepthNet(nn.Module):
    """U-Net of separable convolutions: ``forward(x)`` takes normalised (B, 3, H, W) and
    returns log depth (B, 1, H/2, W/2)."""

    architecture = 'compact'

    def __init__(self, cfg: CompactConfig | None = None):
        super().__init__()
        self.cfg = cfg or CompactConfig()
        enc = self.cfg.encoder_widths
        self.stem = nn.Sequential(
            nn.Conv2d(3, enc[0], 3, stride=2, padding=1, bias=False),
            nn.BatchNorm2d(enc[0]),
            nn.ReLU(inplace=True),
        )
        stages = [_stage(enc[0], enc[0], self.cfg.encoder_blocks[0], 1)]
        for i in range(1, 5):
            stages.append(_stage(enc[i - 1], enc[i], self.cfg.encoder_blocks[i], 2))
        self.encoder = nn.ModuleList(stages)
        self.context = nn.Sequential(
            nn.Linear(enc[4], enc[4]), nn.ReLU(inplace=True), nn.Linear(enc[4], enc[4])
        )
        decoder = []
        cin = enc[4]
        for width, skip in zip(self.cfg.decoder_widths, reversed(enc[:4]), strict=True):
            decoder.append(nn.Sequential(SeparableBlock(cin + skip, width), SeparableBlock(width, width)))
            cin = width
        self.decoder = nn.ModuleList(decoder)
        self.head = nn.Conv2d(cin, 1, 3, padding=1)
        nn.init.normal_(self.head.weight, std=1e-3)
        nn.init.constant_(self.head.bias, self.cfg.init_log_depth)

    @property
    def output_size(self) -> tuple[int, int]:
        """(height, width) of the output map for the configured input size."""
        return ((self.cfg.input_height + 1) // 2, (self.cfg.input_width + 1) // 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        y = self.stem(x)
        for stage in self.encoder:
            y = stage(y)
            skips.append(y)
        y = y + self.context(y.mean(dim=(2, 3)))[:, :, None, None]
        for block, skip in zip(self.decoder, reversed(skips[:4]), strict=True):
            y = F.interpolate(y, size=skip.shape[-2:], mode='bilinear', align_corners=False)
            y = block(torch.cat((y, skip), dim=1))
        return self.head(y)
