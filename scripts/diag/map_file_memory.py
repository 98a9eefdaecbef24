"""Peak memory of saving and loading a map larger than memory through ``map_file`` (diagnostic).

    python scripts/diag/map_file_memory.py 20000 1000

builds a torch TSDF of N random blocks with ``max_blocks`` = CAP (the rest archived on disk),
then prints how far the process's memory rose at its peak while the map file was written, and
while it was loaded into a second engine of the same cap: the anonymous memory (``RssAnon``,
sampled every millisecond: what the process holds) and the whole resident set (``VmHWM``
after a reset through ``/proc/self/clear_refs``), which also counts the pages of the archive
and map files mapped into the process (page cache, given back under memory pressure).
"""

from __future__ import annotations

import sys
import tempfile
import threading
import time
from pathlib import Path

import torch

from depth_fusion_ros.mapping.config import MapConfig
from depth_fusion_ros.mapping.map_file import load_tsdf, save_tsdf
from depth_fusion_ros.mapping.torch_tsdf import TorchTSDF


def _status(field: str) -> float:
    for line in Path('/proc/self/status').read_text().splitlines():
        if line.startswith(field + ':'):
            return int(line.split()[1]) / 1024.0
    return float('nan')


def _peak_rise(step) -> tuple[float, float, float]:
    """(MB the anonymous memory and the resident set rose above their level before ``step``
    at their peaks, seconds)."""
    Path('/proc/self/clear_refs').write_text('5')  # VmHWM := VmRSS
    before, anon = _status('VmRSS'), [_status('RssAnon')]
    done = threading.Event()

    def sample() -> None:
        while not done.wait(0.001):
            anon.append(_status('RssAnon'))

    sampler = threading.Thread(target=sample)
    sampler.start()
    t0 = time.perf_counter()
    step()
    seconds = time.perf_counter() - t0
    done.set()
    sampler.join()
    return max(anon) - anon[0], _status('VmHWM') - before, seconds


def main() -> int:
    n, cap = int(sys.argv[1]), int(sys.argv[2])
    with tempfile.TemporaryDirectory() as tmp:
        config = MapConfig(engine='torch', max_blocks=cap, archive_dir=tmp)
        engine = TorchTSDF(config)
        v = engine.block_voxels
        side = round(n ** (1 / 3)) + 1
        grid = torch.stack(torch.meshgrid(*(torch.arange(side),) * 3, indexing='ij'), dim=-1).reshape(-1, 3)[
            :n
        ]
        engine.load_blocks(grid, torch.rand(n, v), torch.rand(n, v), torch.rand(n, 3, v) * 255)
        del grid
        path = Path(tmp) / 'big.tsdf'
        mib = n * engine.config.bytes_per_block / 2**20
        anon, rss, seconds = _peak_rise(lambda: save_tsdf(engine, path, 'map'))
        print(f'map of {n} blocks ({mib:.0f} MiB, {engine.archived_blocks} archived, cap {cap}):')
        size = path.stat().st_size / 2**20
        print(
            f'  save: anonymous +{anon:.0f} MB, resident +{rss:.0f} MB at the peak, {seconds:.1f} s', end=''
        )
        print(f' ({size:.0f} MiB file)')
        loaded = TorchTSDF(config)
        anon, rss, seconds = _peak_rise(lambda: load_tsdf(loaded, path))
        print(
            f'  load: anonymous +{anon:.0f} MB, resident +{rss:.0f} MB at the peak, {seconds:.1f} s '
            f'({loaded.n_blocks} in memory, {loaded.archived_blocks} archived)'
        )
        loaded.close()
        engine.close()
    return 0


if __name__ == '__main__':
    sys.exit(main())
