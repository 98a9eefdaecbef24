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
* ``stress``      named stress cases (``STRESS_CASES``, ``stress_config``).

Import from here (``from depth_fusion_ros.data.synthetic import SynthConfig, ...``); the
module split is an implementation detail.
"""

from __future__ import annotations

from .config import DEFAULT_FOCAL_640, MOTIONS, PARALLAX_MODES, SynthConfig
from .motions import MOTION_FUNCTIONS
from .render import RenderedFrame, render_frame
from .scene import Scene, build_scene
from .stress import STRESS_CASES, stress_config
from .trajectory import Trajectory, look_at, make_trajectory
from .world import build_world, iter_frames, render_sequence, sequence_name
from .writer import source_markdown, write_synthetic_sequence

__all__ = [
    'DEFAULT_FOCAL_640',
    'MOTIONS',
    'MOTION_FUNCTIONS',
    'PARALLAX_MODES',
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
