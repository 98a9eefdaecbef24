"""The one-command demo: synthesise (or take) a sequence, bag it, run the ROS 2 graph, score it.

``depth-fusion demo`` is what a new user runs first. Every step is the real thing a user
would run by hand:

1. ``depth-fusion synth`` a seeded room (or ``--sequence DIR``, any TUM-layout folder);
2. ``depth-fusion convert`` it to a rosbag2 with rosbags;
3. ``depth-fusion run --record``: bag_replayer, multi_view_node, single_view_node and
   fusion_node over DDS, their outputs recorded into a second rosbag2;
4. ``depth-fusion evaluate``: the recorded fused depth (``graph_fused``) scored against
   ground truth beside the offline methods on the same keyframes (``tv``, ``single_view``,
   ``multi_view``, ``fused``, ``fused_oracle``), with report.md, results.json and figures;
5. the map: the fused depth of the evaluated keyframes integrated offline into a TSDF with the
   sequence's poses (method ``map``, scored against the ground-truth-depth map, pictured in
   the report) and saved as ``map.ply``. (The graph's own ``map_node`` is not started by
   ``depth-fusion run`` yet; this map is integrated offline from the same fused depth.)
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

#: Offline methods scored beside the graph's output, on the graph's keyframes.
OFFLINE_METHODS = ('tv', 'single_view', 'multi_view', 'fused', 'fused_oracle', 'map')
GRAPH_METHODS = ('graph_fused', 'graph_single_view', 'graph_multi_view')


@dataclass
class DemoOptions:
    out: Path = Path('demo_out')
    #: A TUM-layout folder to use instead of a synthetic room.
    sequence: Path | None = None
    frames: int = 60
    seed: int = 0
    parallax: str = 'high'
    processes: bool = False
    device: str = 'cpu'
    single_view: str = 'default'
    rate: float = 1.0
    offline_methods: tuple[str, ...] = OFFLINE_METHODS
    timings: dict[str, float] = field(default_factory=dict)


def _step(opts: DemoOptions, name: str, t0: float) -> None:
    opts.timings[name] = round(time.perf_counter() - t0, 2)
    log.info('demo: %s done in %.1f s', name, opts.timings[name])


def prepare_sequence(opts: DemoOptions, work: Path) -> Path:
    """The TUM folder the demo runs on: the user's, or a freshly rendered synthetic room."""
    if opts.sequence is not None:
        if not (Path(opts.sequence) / 'rgb.txt').is_file():
            raise FileNotFoundError(f'{opts.sequence} is not a TUM-layout folder (no rgb.txt)')
        return Path(opts.sequence)
    from .data.synthetic import SynthConfig, write_synthetic_sequence

    cfg = SynthConfig(frames=opts.frames, seed=opts.seed, parallax=opts.parallax)
    name = f'synthetic_room_seed{opts.seed}_{opts.parallax}_parallax'
    return write_synthetic_sequence(work / name, cfg, overwrite=True, show_progress=True)


def run_demo(opts: DemoOptions) -> dict[str, Any]:
    """Run every step; returns the results document (also written to ``opts.out``)."""
    from .data.rosbag_convert import convert
    from .data.staging import staging_folder
    from .data.tum import load_tum_sequence
    from .evaluation.context import EvalOptions
    from .evaluation.harness import evaluate_sequence, results_document, write_outputs
    from .nodes.graph import RunOptions, run_graph
    from .nodes.graph.summary import drop_reasons, keyframe_summary

    out = Path(opts.out)
    work = out / 'work'
    work.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    seq_dir = prepare_sequence(opts, work)
    _step(opts, 'sequence', t0)

    t0 = time.perf_counter()
    bag = work / 'input_bag'
    # The demo's own work folder: an input bag from an earlier demo goes, whichever version
    # wrote it (convert's overwrite replaces only bags that carry its mark).
    shutil.rmtree(bag, ignore_errors=True)
    convert(seq_dir, bag, max_frames=opts.frames, overwrite=True)
    _step(opts, 'convert', t0)

    t0 = time.perf_counter()
    record = work / 'graph_output'
    shutil.rmtree(record, ignore_errors=True)
    shutil.rmtree(staging_folder(record), ignore_errors=True)  # an earlier demo's, if it failed
    run = run_graph(
        RunOptions(
            bag=bag,
            record=record,
            processes=opts.processes,
            rate=opts.rate,
            device=opts.device,
            single_view_model=opts.single_view,
            # Paced (the default): the replayer waits while the graph is busy, so a slow
            # machine fuses every keyframe the policy chooses and the report scores them all.
        )
    )
    _step(opts, 'node_graph', t0)
    if run.recorded is None or not run.fused:
        raise RuntimeError(f'the node graph published no fused depth (lost: {run.missing})')

    t0 = time.perf_counter()
    sequence = load_tum_sequence(seq_dir, max_frames=opts.frames)
    options = EvalOptions(
        frames=opts.frames,
        recorded_keyframes=True,  # the graph's keyframes (the report header says so)
        seed=opts.seed,
        device=opts.device,
        single_view=opts.single_view,
        neighbour_mode='online',  # what the multi-view node does
        params={'recorded': {'bag': str(run.recorded)}},
    )
    methods = [*GRAPH_METHODS, *opts.offline_methods]
    result = evaluate_sequence(sequence, methods, options, path=str(seq_dir))
    _step(opts, 'evaluate', t0)

    doc = results_document([result], methods, options)
    doc['demo'] = {
        'sequence': str(seq_dir),
        'input_bag': str(bag),
        'recorded_bag': str(run.recorded),
        'processes': opts.processes,
        'keyframes_chosen': len(run.chosen),
        'keyframes_announced': len(run.announced),
        'keyframes_fused': len(run.fused),
        'keyframes_dropped': drop_reasons(run),
        'graph_summary': keyframe_summary(run, 'processes' if opts.processes else 'composed'),
        'keyframes_lost': {str(k): v for k, v in run.missing.items()},
        'graph_seconds': round(run.seconds, 2),
        'cpu_budget': run.cpu_budget,
        'step_seconds': dict(opts.timings),
    }
    map_ply = _write_map(result, out)
    if map_ply is not None:
        doc['demo']['map_ply'] = str(map_ply)
    write_outputs(doc, [result], out)
    return doc


def _write_map(result: Any, out: Path) -> Path | None:
    """``out/map.ply``: the mesh of the ``map`` method, when it ran (``ValueError`` if empty)."""
    from .mapping.ply import write_ply

    record = result.records.get('map')
    if record is None or record.sequence_output is None:
        return None
    mesh = record.sequence_output.artifacts['mesh']
    if mesh.is_empty:
        raise ValueError('the map of the fused depth is empty: no map.ply written')
    path = write_ply(out / 'map.ply', mesh)
    log.info(
        'demo: map written to %s (%d vertices, %d triangles)', path, len(mesh.vertices), len(mesh.triangles)
    )
    return path
