"""Where the composed node graph spends its time, every thread at once (yappi, wall clock).

    DEPTH_FUSION_BENCH_GRAPH_SET=multi_view_node.keyframe_every=1 \
        python scripts/diag/graph_profile.py cuda [OUT_DIR]

(``YAPPI_CLOCK=cpu``: CPU time per function instead of wall time, which counts waits too.
``YAPPI_ONLY=depth_fusion_ros/``: list only the functions whose file path holds that string;
on a fresh GPU machine the fusion kernels' compilation in the same process fills the lists
otherwise, as it did on 2026-12-04.)

Runs ``bench --only node_graph`` composed, paced at 10x (``DEPTH_FUSION_BENCH_GRAPH_RUNS``
defaults to ``composed:paced:10`` here), under yappi (``pip install yappi``; not a project
dependency), then prints the functions with the most own time and the most inclusive time,
and each thread's total. cProfile sees only the main thread; the nodes' callbacks and workers
run in executor and worker threads.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import yappi

from depth_fusion_ros.bench import BenchOptions, node_graph


def main() -> None:
    device = sys.argv[1] if len(sys.argv) > 1 else 'cpu'
    out = Path(sys.argv[2]) if len(sys.argv) > 2 else None
    os.environ.setdefault(node_graph.RUNS_ENV, 'composed:paced:10')
    yappi.set_clock_type(os.environ.get('YAPPI_CLOCK', 'wall'))
    yappi.start(builtins=False)
    rows = node_graph.run(BenchOptions(device=device, repeats=1))
    yappi.stop()
    for row in rows:
        if 'fused' in row.name or 'latency image' in row.name:
            print(f'{row.name:60s} {row.value:10.4g} {row.unit}')
    stats = yappi.get_func_stats()
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        stats.save(str(out / 'graph.prof'), type='pstat')
    only = os.environ.get('YAPPI_ONLY', '')
    clock = os.environ.get('YAPPI_CLOCK', 'wall')
    for key, title in (('tsub', 'own time'), ('ttot', 'inclusive time')):
        print(f'== top by {title} ({clock}, all threads{f", {only} only" if only else ""})')
        stats.sort(key, 'desc')
        for s in [s for s in stats if only in s.module][:45]:
            name = f'{Path(s.module).name}:{s.lineno} {s.name}'
            print(f'{s.ncall:8d} {s.tsub:9.2f} {s.ttot:9.2f}  {name[:110]}')
    print('== threads')
    for t in yappi.get_thread_stats():
        print(f'{t.name:30s} {t.id:4d} {t.ttot:9.2f} s  {t.sched_count} switches')


if __name__ == '__main__':
    main()
