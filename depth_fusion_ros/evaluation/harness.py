"""Runs registered depth methods over TUM-layout sequences and scores them (no ROS).

``evaluate_sequences`` is what ``depth-fusion evaluate`` calls. It loads each sequence at
the working resolution, treats every ``stride``-th frame of the first ``frames`` as a
keyframe, runs each method, upsamples its depth to the ground-truth resolution and pools
the metrics (overall and split into high/low image gradient, paper Table I).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections import defaultdict
from collections.abc import Sequence as Seq
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..data.sequence import Sequence
from ..metrics import MetricAccumulator, good_density, high_gradient_mask, upsample_depth
from ..progress import progress
from . import mount, time_offset
from .context import EvalOptions, KeyframeContext, SequenceContext, keyframe_indices
from .focal import SHARED_KEY as FOCAL_SHARED_KEY
from .focal import check_focal, estimate_json, take_lens
from .registry import MethodSpec, SequenceOutput, get_method

log = logging.getLogger(__name__)


@dataclass
class MethodRecord:
    """Everything measured for one method on one sequence."""

    spec: MethodSpec
    all: MetricAccumulator = field(default_factory=MetricAccumulator)
    high_gradient: MetricAccumulator = field(default_factory=MetricAccumulator)
    low_gradient: MetricAccumulator = field(default_factory=MetricAccumulator)
    extras: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    seconds: list[float] = field(default_factory=list)
    #: Working-resolution depth of the sample frames, for figures.
    samples: dict[int, np.ndarray] = field(default_factory=dict)
    #: What a sequence-level method (``spec.finish``) reported.
    sequence_output: SequenceOutput | None = None

    def to_json(self) -> dict[str, Any]:
        if self.spec.finish is not None:
            return self._sequence_json()
        out: dict[str, Any] = dict(self.all.summary())
        out['per_frame_mae'] = [_finite_or_none(v) for v in self.all.mae_per_frame]
        out['gradient'] = {
            'high': self.high_gradient.summary(),
            'low': self.low_gradient.summary(),
        }
        for key, values in self.extras.items():
            out[key] = _mean_extra(values)
        if self.extras:
            out['per_frame_extras'] = {k: [_finite_or_none(v) for v in vs] for k, vs in self.extras.items()}
        out['seconds_per_frame'] = float(np.mean(self.seconds)) if self.seconds else float('nan')
        return out

    def _sequence_json(self) -> dict[str, Any]:
        out: dict[str, Any] = dict(self.sequence_output.metrics if self.sequence_output else {})
        for key, values in self.extras.items():
            out[key] = _mean_extra(values)
        out['seconds_per_frame'] = float(np.mean(self.seconds)) if self.seconds else float('nan')
        return out


@dataclass
class SequenceResult:
    name: str
    path: str
    keyframes: list[int]
    records: dict[str, MethodRecord]
    sequence: Sequence
    #: The focal length check (``evaluation/focal.py``), or ``None`` when it did not run.
    focal_check: dict[str, Any] | None = None
    #: The time offset check (``evaluation/time_offset.py``), or ``None`` when it did not run.
    time_offset_check: dict[str, Any] | None = None
    #: The mount check (``evaluation/mount.py``), or ``None`` when it did not run.
    mount_check: dict[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            'path': self.path,
            'frames': len(self.keyframes),
            'keyframes': self.keyframes,
            'dropped': dict(self.sequence.dropped),
            'focal_check': self.focal_check,
            'time_offset_check': self.time_offset_check,
            'mount_check': self.mount_check,
            'methods': {name: rec.to_json() for name, rec in self.records.items()},
        }


def _finite_or_none(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def run_keyframes(sequence: Sequence, options: EvalOptions) -> list[int]:
    """The keyframes a sequence is scored on: the options' (stride or list), or with
    ``recorded_keyframes`` those the recorded node graph published fused depth for."""
    if not options.recorded_keyframes:
        return keyframe_indices(len(sequence), options)
    from .methods.recorded import TOPICS, recorded_bag, recorded_keyframes

    recorded = options.params.get('recorded', {})
    bag = recorded_bag(recorded, '--recorded-keyframes')
    keyframes = recorded_keyframes(sequence, bag, recorded.get('graph_fused', TOPICS['graph_fused']))
    if not keyframes:
        raise ValueError(
            f'{bag} holds no fused depth at any of the first {len(sequence)} frames of {sequence.name}'
        )
    log.info('%s: scoring the %d keyframes the recorded graph fused (%s)', sequence.name, len(keyframes), bag)
    return keyframes


def sample_indices(keyframes: list[int], count: int) -> list[int]:
    """``count`` keyframes spread evenly over the run, for the figures."""
    if not keyframes or count <= 0:
        return []
    picks = np.linspace(0, len(keyframes) - 1, min(count, len(keyframes))).round().astype(int)
    return sorted({keyframes[i] for i in picks})


def evaluate_sequence(
    sequence: Sequence,
    methods: Seq[str],
    options: EvalOptions,
    path: str = '',
    n_samples: int = 3,
    show_progress: bool = True,
) -> SequenceResult:
    """Run ``methods`` on the keyframes of an already loaded sequence (first the time offset,
    mount and focal length checks, which may correct its poses and camera, and a lens the focal
    check finds, taken before the mount check as the node does: ``evaluation/time_offset.py``,
    ``evaluation/mount.py``, ``evaluation/focal.py``)."""
    read, timing = time_offset.check_time_offset(sequence, options.params)
    timing_json = time_offset.estimate_json(timing, corrected=read is not sequence)
    sequence = read
    sequence, first, lens_k1 = take_lens(sequence, options.params)
    read, mount_estimate = mount.check_mount(sequence, options.params)
    mount_json = mount.estimate_json(mount_estimate, corrected=read is not sequence)
    again = read is not sequence or lens_k1 != 0.0  # the focal check's first look no longer holds
    sequence = read
    told_camera = sequence.camera
    sequence, focal = check_focal(sequence, options.params, first, again, after_lens=lens_k1 != 0.0)
    if focal is None and lens_k1:  # too few frames to finish again: the look that found the lens
        focal = first
    focal_corrected = sequence.camera != told_camera
    focal_json = estimate_json(focal, corrected=focal_corrected, lens_k1=lens_k1)
    specs = [get_method(m) for m in methods]
    keyframes = run_keyframes(sequence, options)
    samples = set(sample_indices(keyframes, n_samples))
    records = {s.name: MethodRecord(s) for s in specs}
    shared: dict[str, Any] = {FOCAL_SHARED_KEY: (focal, focal_corrected)}
    for i in progress(keyframes, desc=sequence.name, unit='kf', disable=not show_progress):
        ctx = KeyframeContext(sequence, i, options, shared)
        gt = ctx.gt_depth
        if gt is None:
            raise ValueError(f'{sequence.name}: frame {i} has no ground-truth depth to evaluate against')
        high = (
            upsample_depth(
                high_gradient_mask(sequence.frames[i].gray).astype(np.float32), gt.shape[1], gt.shape[0]
            )
            > 0.5
        )
        for spec in specs:
            t0 = time.perf_counter()
            out = spec.fn(ctx)
            records[spec.name].seconds.append(time.perf_counter() - t0)
            for key, value in out.extras.items():
                records[spec.name].extras[key].append(float(value))
            if spec.finish is not None:
                continue  # scored once for the whole sequence, below
            _score(records[spec.name], out.depth, gt, high)
            if i in samples:
                records[spec.name].samples[i] = out.depth
    whole = SequenceContext(sequence, keyframes, options, shared)
    for spec in specs:
        if spec.finish is not None:
            records[spec.name].sequence_output = spec.finish(whole)
    return SequenceResult(
        sequence.name, path, keyframes, records, sequence, focal_json, timing_json, mount_json
    )


def _mean_extra(values: list[float]) -> float:
    """Mean of a per-frame extra over the frames that have it; NaN where none has (e.g.
    ``certainty`` where no keyframe was interpolated)."""
    return float(np.nanmean(values)) if np.isfinite(values).any() else float('nan')


def _score(rec: MethodRecord, depth: np.ndarray, gt: np.ndarray, high: np.ndarray) -> None:
    pred = upsample_depth(depth, gt.shape[1], gt.shape[0])
    rec.all.add(pred, gt)
    rec.high_gradient.add(pred, gt, high)
    rec.low_gradient.add(pred, gt, ~high)
    if rec.spec.sparse:
        rec.extras['density'].append(float(np.isfinite(depth).mean()))
        rec.extras['good_density'].append(good_density(pred, gt))


def evaluate_sequences(
    paths: Seq[str | Path],
    methods: Seq[str],
    options: EvalOptions,
    out_dir: str | Path | None = None,
    show_progress: bool = True,
    figures: bool = True,
) -> dict[str, Any]:
    """Evaluate ``methods`` on TUM-layout folders or rosbag2s; write ``results.json`` and ``report.md``."""
    for m in methods:  # fail before loading data when a name is wrong
        get_method(m)
    results: list[SequenceResult] = []
    for p in paths:
        seq = load_evaluation_sequence(p, options)
        log.info('%s: %d frames loaded (dropped: %s)', seq.name, len(seq), seq.dropped)
        results.append(evaluate_sequence(seq, methods, options, str(p), show_progress=show_progress))
    doc = results_document(results, methods, options)
    if out_dir is not None:
        write_outputs(doc, results, Path(out_dir), figures=figures)
    return doc


def load_evaluation_sequence(path: str | Path, options: EvalOptions, with_depth: bool = True) -> Sequence:
    """Load a TUM folder or a rosbag2 as the options say (working size, frames, colour-camera
    override, a rosbag2's topics, the camera's mount on the posed body). ``with_depth``: frames
    without ground-truth depth are dropped (scoring needs it; ``adapt`` does not read it)."""
    from ..data.bag_recovery import readable_rosbag2
    from ..data.recording import load_recording
    from ..data.tum import read_camera_yaml

    name = Path(path).resolve().name
    override = options.rgb_cameras.get(name, options.rgb_cameras.get('*'))
    return load_recording(
        path,
        options.width,
        options.height,
        options.frames,
        calibration=read_camera_yaml(override) if override else None,
        topics=options.topics if readable_rosbag2(path) else None,  # a bag's topics; a TUM folder has none
        camera_from_pose_frame=options.camera_from_pose_frame,
        with_depth=with_depth,
    )


def results_document(
    results: list[SequenceResult], methods: Seq[str], options: EvalOptions
) -> dict[str, Any]:
    return {
        'options': dataclasses.asdict(options),
        'methods': {m: get_method(m).description for m in methods},
        'sequences': {r.name: r.to_json() for r in results},
    }


def write_outputs(
    doc: dict[str, Any], results: list[SequenceResult], out_dir: Path, figures: bool = True
) -> None:
    from .report import write_report

    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / 'results.json').write_text(json.dumps(doc, indent=2, allow_nan=True))
    write_report(doc, results, out_dir, figures=figures)
