"""A lens distortion camera_info does not hold, taken once the focal length check finds it
(``data/lens_correction.py``): the radial ``k1`` is added to the calibration the images are
undistorted with, by ``multi_view_node`` (``focal_check.mode`` correct) and by ``evaluate``, and
the multi-view depth of the lens stress case is then that of a pinhole camera again."""

from __future__ import annotations

import dataclasses
import threading
from types import SimpleNamespace

import numpy as np
import pytest

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.data import messages as m
from depth_fusion_ros.data.lens_correction import add_radial, can_add_radial, undistort_sequence
from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence, stress_config
from depth_fusion_ros.data.undistort import CameraCalibration
from depth_fusion_ros.multiview.focal_check import FocalCheckConfig, FocalEstimate
from depth_fusion_ros.multiview.lens_fit import LensFit
from depth_fusion_ros.nodes.image_input import CameraInput

CAMERA = PinholeCamera(160, 120, 150.0, 150.0, 79.5, 59.5)
#: A sure lens of k1 -0.09 over 12 pairs (``LensFit.distorted``).
LENS = LensFit(-0.09, 0.01, 0.6, 0, 12)


def _pair(k1: float):
    """The same room through a pinhole lens and through a radial ``k1`` camera.yaml does not hold."""
    cfg = SynthConfig(width=160, height=120, frames=2, seed=4, parallax='high', boxes=8)
    return render_sequence(cfg), render_sequence(dataclasses.replace(cfg, lens_k1=k1))


def _apart(a: np.ndarray, b: np.ndarray) -> float:
    inner = (slice(8, -8), slice(8, -8))
    return float(np.abs(a.astype(float) - b.astype(float))[inner].mean())


def test_a_radial_term_is_added_to_the_calibration():
    plain = CameraCalibration(CAMERA)
    assert add_radial(plain, 0.0) is plain
    assert add_radial(plain, -0.09) == CameraCalibration(CAMERA, 'plumb_bob', (-0.09, 0.0, 0.0, 0.0, 0.0))
    told = CameraCalibration(CAMERA, 'plumb_bob', (0.1, -0.2, 0.001, 0.002, 0.0))
    np.testing.assert_allclose(add_radial(told, -0.09).D, (0.01, -0.2, 0.001, 0.002, 0.0), atol=1e-15)
    fisheye = CameraCalibration(CAMERA, 'equidistant', (0.1, 0.0, 0.0, 0.0))
    assert not can_add_radial(fisheye) and can_add_radial(told) and can_add_radial(plain)
    with pytest.raises(ValueError, match='equidistant'):
        add_radial(fisheye, -0.09)


def test_a_sequence_undistorted_with_its_k1_is_the_pinhole_one():
    """Images and ground truth both: the depth to a median 1e-3, the colour closer to the
    pinhole render than the lens's by more than half."""
    pinhole, bent = _pair(-0.2)
    back = undistort_sequence(bent, -0.2)
    assert back.camera == bent.camera and len(back.frames) == len(bent.frames)
    frame, seen, truth = back.frames[0], bent.frames[0], pinhole.frames[0]
    assert _apart(frame.rgb, truth.rgb) < 0.5 * _apart(seen.rgb, truth.rgb)
    inner = (slice(8, -8), slice(8, -8))
    error = np.abs(frame.depth / truth.depth - 1.0)[inner]
    assert np.nanmedian(error) < 1e-3 < np.nanmedian(np.abs(seen.depth / truth.depth - 1.0)[inner])
    assert frame.gray.shape == (120, 160)  # the grey image is made again, from the new colour


def test_the_camera_input_undistorts_with_the_lens_it_was_given():
    """A camera_info without distortion, images through a lens: with ``lens_k1`` set, the
    working image is the pinhole one (the JPEG path takes the same calibration)."""
    pinhole, bent = _pair(-0.2)
    inp = CameraInput(160, 120)
    header = m.header_msg(1_000, 'cam', kind=m.RCLPY)
    inp.update(m.camera_info_msg(bent.camera, header, kind=m.RCLPY))
    image = m.rgb_image_msg(bent.frames[0].rgb, header, kind=m.RCLPY)
    assert inp.can_correct_lens()
    np.testing.assert_array_equal(inp.working_image(image).rgb, bent.frames[0].rgb)
    inp.lens_k1 = -0.2
    work = inp.working_image(image)
    assert work.camera == bent.camera  # K kept: only the pixels move
    assert _apart(work.rgb, pinhole.frames[0].rgb) < 0.5 * _apart(bent.frames[0].rgb, pinhole.frames[0].rgb)
    assert not CameraInput(160, 120).can_correct_lens()  # nothing to add it to before camera_info


def _node(mode: str, D: tuple[float, ...] = ()):
    """The node's state ``CheckCorrections`` reads, with a focal check that found ``LENS``, and
    a camera_info of distortion ``D``."""
    from depth_fusion_ros.nodes.stats import NodeStats

    warnings, infos, restarts = [], [], []
    result = FocalEstimate(1.05, 0.004, 12, 4000, 'disagrees', 150.0, 150.0, LENS)
    inp = CameraInput(160, 120)
    info = m.camera_info_msg(CAMERA, m.header_msg(1, 'cam', kind=m.RCLPY), kind=m.RCLPY)
    if D:
        info.distortion_model, info.d = 'plumb_bob', list(D)
    inp.update(info)
    node = SimpleNamespace(
        stats=NodeStats(warnings.append),
        get_logger=lambda: SimpleNamespace(info=infos.append),
        focal_check=SimpleNamespace(
            config=SimpleNamespace(mode=mode), result=result, restart=lambda: restarts.append('focal')
        ),
        mount_check=SimpleNamespace(restart=lambda: restarts.append('mount')),
        camera_input=inp,
        _lens_taken=None,
        _frame_tilt_unchecked=False,  # no frame turn taken (a lens then waits: test_nodes_mount_check)
        _restart_from_ns=None,
        _mount_unsaid=object(),
        _mount_unsaid_lock=threading.Lock(),
        _lens_pub=SimpleNamespace(sent=[]),
    )
    node._lens_pub.publish = node._lens_pub.sent.append
    return node, result, warnings, infos, restarts


def test_the_node_takes_a_lens_once_and_starts_over():
    """``focal_check.mode`` correct: the verdict is not said by the check's thread; the image
    callback adds the ``k1`` to the calibration, starts the history, the filter and both image
    checks over at that image, says so once, and does not take the same result twice. The
    focal length the lens read as is not taken (``FocalEstimate.applied``)."""
    from depth_fusion_ros.nodes.multi_view_checks import CheckCorrections

    node, result, warnings, infos, restarts = _node('correct')
    node._lens_correctable = lambda: CheckCorrections._lens_correctable(node)
    assert not result.applied('correct')
    CheckCorrections._on_focal_estimate(node, CAMERA, result)
    assert not warnings and not infos and node.stats.snapshot().noted == {}
    CheckCorrections._take_lens_correction(node, 5_000)
    CheckCorrections._take_lens_correction(node, 6_000)
    assert node.camera_input.lens_k1 == pytest.approx(-0.09)
    assert not result.applied('correct', after_lens=node.camera_input.lens_k1 != 0.0)
    assert node._restart_from_ns == 5_000 and restarts == ['focal', 'mount'] and node._mount_unsaid is None
    assert node.stats.snapshot().noted == {'lens_corrected': 1}
    said = 'k1 -0.090 added to the calibration the images are undistorted with, from the image stamped 0.0'
    assert said in warnings[0]
    assert 'camera_info D [-0.090, 0, 0, 0, 0]' in warnings[0]
    # The calibration taken, published once for the nodes reading the raw camera (lens_topic.py).
    (info,) = node._lens_pub.sent
    assert m.stamp_to_ns(info.header.stamp) == 5_000 and (info.width, info.height) == (160, 120)
    assert info.distortion_model == 'plumb_bob'
    np.testing.assert_allclose(info.d, (-0.09, 0, 0, 0, 0), atol=1e-15)
    # A camera_info with a distortion of its own: the fit adds to its k1, and the hint says so.
    node, *_, warnings, _, _ = _node('correct', (0.1, -0.2, 0.0, 0.0, 0.0))
    node._lens_correctable = lambda: CheckCorrections._lens_correctable(node)
    CheckCorrections._take_lens_correction(node, 5_000)
    assert 'camera_info -0.090 added to D[0] would do it' in warnings[0]
    taken = node.camera_input._calibration_for(160, 120)
    np.testing.assert_allclose(taken.D, (0.01, -0.2, 0, 0, 0), atol=1e-15)
    np.testing.assert_allclose(node._lens_pub.sent[0].d, (0.01, -0.2, 0, 0, 0), atol=1e-15)


def test_after_a_lens_a_focal_disagreement_is_said_not_taken():
    """On images undistorted with a fitted lens, what the fit leaves of the lens reads as a
    focal error (+12.2 % for a camera 5.3 % short): the check's disagreement is warned, with
    why, and the multi-view depth keeps the told focal length."""
    from depth_fusion_ros.nodes.focal_check_runner import FocalCheckRunner
    from depth_fusion_ros.nodes.multi_view_checks import CheckCorrections
    from depth_fusion_ros.nodes.stats import NodeStats

    disagrees = FocalEstimate(1.122, 0.017, 12, 2000, 'disagrees', 150.0, 150.0)
    assert disagrees.applied('correct') and not disagrees.applied('correct', after_lens=True)
    node, *_ = _node('correct')
    warnings = []
    node.stats = NodeStats(warnings.append)
    node.camera_input.lens_k1 = -0.09
    CheckCorrections._on_focal_estimate(node, CAMERA, disagrees)
    assert node.stats.snapshot().noted == {'focal_disagrees': 1} and 'not taken' in warnings[0]
    runner = FocalCheckRunner(FocalCheckConfig(), lambda *_: None)
    runner._check = SimpleNamespace(camera=CAMERA, result=disagrees)
    assert runner.camera_for(CAMERA).fx == pytest.approx(150.0 * 1.122)
    assert runner.camera_for(CAMERA, after_lens=True) == CAMERA


def test_in_warn_mode_the_node_says_the_lens_and_keeps_its_calibration():
    from depth_fusion_ros.nodes.multi_view_checks import CheckCorrections

    node, result, warnings, _, restarts = _node('warn')
    node._lens_correctable = lambda: CheckCorrections._lens_correctable(node)
    CheckCorrections._on_focal_estimate(node, CAMERA, result)
    CheckCorrections._take_lens_correction(node, 5_000)
    assert node.stats.snapshot().noted == {'lens_distortion': 1} and 'k1 -0.09' in warnings[0]
    assert (
        node.camera_input.lens_k1 == 0.0
        and node._restart_from_ns is None
        and not restarts
        and not node._lens_pub.sent
    )


def test_evaluate_takes_the_lens_and_gets_the_multi_view_depth_back():
    """``evaluate`` on the lens stress case (seed 5, 240x180, 10 pairs): the check finds the
    lens, every method runs on the images undistorted with its ``k1``, scored against the
    ground truth undistorted with them; the multi-view depth is then far more accurate than
    through the lens (``focal_check.mode`` warn: 0.09 against 0.31 m). The lens is taken before
    the mount check, which reads it as a camera turned 2.1 deg otherwise."""
    from depth_fusion_ros.evaluation.context import EvalOptions
    from depth_fusion_ros.evaluation.harness import evaluate_sequence

    size = {'width': 240, 'height': 180, 'frames': 100, 'seed': 5}
    lens = render_sequence(stress_config('lens_distortion', **size))
    maes, entries = {}, {}
    for mode in ('correct', 'warn'):
        options = EvalOptions(
            frames=100,
            keyframes=[60, 80],
            single_view='simulated',
            width=240,
            height=180,
            params={'focal_check': {'pairs': 10, 'mode': mode}},
        )
        result = evaluate_sequence(lens, ['multi_view'], options, show_progress=False)
        entries[mode] = result.to_json()['focal_check']
        maes[mode] = result.records['multi_view'].all.summary()['mae']
    assert -0.12 < entries['correct']['lens_corrected_k1'] < -0.07, entries['correct']
    assert entries['warn']['lens_corrected_k1'] == 0.0
    assert maes['correct'] < 0.5 * maes['warn'], maes
