"""Synthetic posed RGB-D sequences with exact depth and poses (the project's own test data).

One idea per module:

* ``config``      ``SynthConfig``: every knob of a sequence, validated up front;
* ``texture``     procedural albedo textures in surface (UV) coordinates;
* ``scene``       the seeded room: floor, walls, ceiling, boxes, tables;
* ``trajectory``  camera trajectories with high or low parallax;
* ``motions``     stress motions (rotation-dominant sweep, keyframe stream);
* ``render``      numpy ray casting of one frame (rgb, depth, surface id, textured mask);
* ``world``       config -> (scene, trajectory), frames, an in-memory ``Sequence``;
* ``writer``      a TUM-layout folder with camera.yaml and SOURCE.md;
* ``walkers``     moving objects: person-sized boxes walking across the view;
* ``stress``      named stress cases (``STRESS_CASES``, ``stress_config``).

Import from here (``from depth_fusion_ros.data.synthetic import SynthConfig, ...``); the
module split is an implementation detail.
"""

from __future__ import annotations

import importlib
from typing import Any

#: Each public name and the submodule that defines it. The submodules are imported on first
#: use (PEP 562), so ``from depth_fusion_ros.data.synthetic import SynthConfig`` costs the
#: config alone: the renderer pulls in scipy, and ``depth-fusion --help`` builds the ``synth``
#: parser from these names (0.6 s of imports at every command before).
_SOURCES = {
    'DEFAULT_FOCAL_640': 'config',
    'MOTIONS': 'config',
    'PARALLAX_MODES': 'config',
    'POSE_FRAMES': 'config',
    'SynthConfig': 'config',
    'MOTION_FUNCTIONS': 'motions',
    'RenderedFrame': 'render',
    'render_frame': 'render',
    'Scene': 'scene',
    'build_scene': 'scene',
    'STRESS_CASES': 'stress',
    'stress_config': 'stress',
    'Trajectory': 'trajectory',
    'look_at': 'trajectory',
    'make_trajectory': 'trajectory',
    'build_world': 'world',
    'iter_frames': 'world',
    'render_sequence': 'world',
    'sequence_name': 'world',
    'source_markdown': 'writer',
    'write_synthetic_sequence': 'writer',
}


def __getattr__(name: str) -> Any:
    module = _SOURCES.get(name)
    if module is None:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    value = getattr(importlib.import_module(f'.{module}', __name__), name)
    globals()[name] = value  # looked up once
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_SOURCES])


__all__ = [
    'DEFAULT_FOCAL_640',
    'MOTIONS',
    'MOTION_FUNCTIONS',
    'PARALLAX_MODES',
    'POSE_FRAMES',
    'STRESS_CASES',
    'RenderedFrame',
    'Scene',
    'SynthConfig',
    'Trajectory',
    'build_scene',
    'build_world',
    'iter_frames',
    'look_at',
    'make_trajectory',
    'render_frame',
    'render_sequence',
    'sequence_name',
    'source_markdown',
    'stress_config',
    'write_synthetic_sequence',
]
