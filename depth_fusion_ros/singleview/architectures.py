"""The trainable architectures by name, so checkpoints can say which one they hold."""

from __future__ import annotations

from typing import Any

from torch import nn

from .compact_net import CompactConfig, CompactDepthNet
from .eigen_net import EigenConfig, EigenFergusNet

ARCHITECTURES = ('compact', 'eigen')


def arch_config_class(architecture: str) -> type[CompactConfig] | type[EigenConfig]:
    if architecture == 'compact':
        return CompactConfig
    if architecture == 'eigen':
        return EigenConfig
    raise ValueError(f'unknown architecture {architecture!r}; available: {", ".join(ARCHITECTURES)}')


def arch_input_size(architecture: str, arch_config: dict[str, Any] | None = None) -> tuple[int, int]:
    """``(width, height)`` a network would take, without building it (Eigen's is 870 MB)."""
    cfg = arch_config_class(architecture).from_dict(dict(arch_config or {}))
    return (int(cfg.input_width), int(cfg.input_height))


def build_model(architecture: str, arch_config: dict[str, Any] | None = None) -> nn.Module:
    """A freshly initialised network; its forward returns log depth (B, 1, h, w)."""
    cfg = arch_config_class(architecture).from_dict(dict(arch_config or {}))
    return CompactDepthNet(cfg) if architecture == 'compact' else EigenFergusNet(cfg)


def model_arch_config(model: nn.Module) -> dict[str, Any]:
    """The ``arch_config`` that rebuilds ``model`` with ``build_model``."""
    cfg = getattr(model, 'cfg', None)
    if cfg is None or not hasattr(cfg, 'to_dict'):
        raise ValueError(f'{type(model).__name__} is not one of the architectures {ARCHITECTURES}')
    return cfg.to_dict()


def model_input_size(model: nn.Module) -> tuple[int, int]:
    """``(width, height)`` the network was built for."""
    cfg = model.cfg
    return (int(cfg.input_width), int(cfg.input_height))


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
