"""How long ``depth-fusion launch`` takes to stop on Ctrl-C (diagnostic).

Starts the live graph (``depth-fusion launch --log-dir DIR``) with an empty compile cache, so
``fusion_node`` is still compiling its kernels for the first ~30 s as on a fresh machine,
sends SIGINT after each of ``DELAYS`` seconds and prints the delay, the exit code and the
seconds from the signal to the exit. The graph kills a node that has not stopped 15 s after
its signal (``nodes/graph/spawn.py``), so a stop must stay well below that.

    python scripts/diag/stop_time.py 12 20 --domain 187

Use a ROS domain no test run uses (the suite takes 1-100): a graph on a test's domain sends
its messages into the test's graph.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path


def stop_time(delay: float, domain: int, folder: Path) -> tuple[str, float]:
    """(exit code or ``HUNG``, seconds from SIGINT to exit) for one launch stopped at ``delay``."""
    cache = folder / f'inductor_{delay:g}'
    shutil.rmtree(cache, ignore_errors=True)
    env = {
        **os.environ,
        'ROS_DOMAIN_ID': str(domain),
        'DEPTH_FUSION_AOT': '0',  # compile in the node, as CI does
        'TORCHINDUCTOR_CACHE_DIR': str(cache),
    }
    logs = folder / f'logs_{delay:g}'
    with open(folder / f'launch_{delay:g}.out', 'w') as out:
        proc = subprocess.Popen(
            ['depth-fusion', 'launch', '--log-dir', str(logs)],
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # also from a shell's `&`
        )
        time.sleep(delay)
        start = time.monotonic()
        proc.send_signal(signal.SIGINT)
        try:
            code = str(proc.wait(40))
        except subprocess.TimeoutExpired:
            code = 'HUNG'
            proc.kill()
            proc.wait()
    return code, time.monotonic() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('delays', type=float, nargs='+', metavar='DELAYS', help='seconds before SIGINT')
    parser.add_argument('--domain', type=int, default=187, help='ROS domain (default 187)')
    parser.add_argument('--out', type=Path, default=None, help='folder for logs (default: a temporary one)')
    args = parser.parse_args()
    folder = args.out or Path(tempfile.mkdtemp(prefix='stop_time_'))
    folder.mkdir(parents=True, exist_ok=True)
    for delay in args.delays:
        code, seconds = stop_time(delay, args.domain, folder)
        print(f'SIGINT at {delay:g} s: exit {code} after {seconds:.2f} s (logs in {folder})', flush=True)


if __name__ == '__main__':
    main()
