"""A relocalisation in a posed stream: the test room seen from a frame's place turned by an angle,
what the filter's and the feed's jump tests feed after a stretch of the fixture's frames."""

from __future__ import annotations

import numpy as np

from depth_fusion_ros.data.sequence import Frame
from depth_fusion_ros.geometry import make_pose


def jumped_views(seq, start: int, turn_deg: float, steps_m: tuple[float, ...]) -> list[Frame]:
    """Frames of the fixture's room seen from frame ``start``'s place turned ``turn_deg`` about
    the camera's vertical axis (a relocalisation), then moved sideways by each of ``steps_m``."""
    from conftest import SYNTHETIC_FIXTURE_CONFIG

    from depth_fusion_ros.data.synthetic import SynthConfig, build_world, render_frame

    cfg = SynthConfig(**SYNTHETIC_FIXTURE_CONFIG, parallax='high')
    scene, _ = build_world(cfg)
    half = np.radians(turn_deg) / 2.0
    T_jump = seq.frames[start].pose @ make_pose([0.0, 0.0, 0.0], [0.0, np.sin(half), 0.0, np.cos(half)])
    frames = []
    for i, step in enumerate((0.0, *steps_m)):
        T = T_jump @ make_pose([step, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
        view = render_frame(scene, cfg.camera(), T)
        frames.append(Frame(index=100 + i, stamp=10.0 + i, rgb=view.rgb, pose=T, depth=view.depth))
    return frames
