"""``python -m snn_tools.warm_cache [--jobs N]``: fill numba's on-disk cache at install (``make``).

Compiles every filter kernel (split by filter kind over the jobs), the Basilisk truth's sample
writer and the compiled closed loop, in ``--jobs`` processes at a time (default: the CPUs, at most
4). One process took ~155 s on a 2-core machine, most of it the kernels; each is compiled once and
then loaded by every node and Monte Carlo. Exits non-zero, naming the part, if one fails.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time


def parts(jobs: int) -> list[tuple[str, str]]:
    """(name, Python statement) of each part, the longest first: the kernels in ``jobs`` shares,
    then the closed loop (it reuses the kernels) and the Basilisk writer."""
    kernels = [(f'kernels {i + 1}/{jobs}', f'from snn_estimator.filters.estimators import warm_up_all; '
                                            f'warm_up_all({i}, {jobs})') for i in range(jobs)]
    return kernels + [('closed loop', 'from snn_estimator.offline.compiled_loop import warm_up; warm_up()'),
                      ('basilisk truth', 'from snn_estimator.offline.basilisk_truth import warm_up; warm_up()')]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='warm_cache', description=__doc__.split('\n\n')[0])
    parser.add_argument('--jobs', type=int, default=min(os.cpu_count() or 1, 4),
                        help='processes at a time (default: the CPUs, at most 4)')
    args = parser.parse_args(argv)
    if args.jobs < 1:
        parser.error('--jobs must be >= 1')
    waiting, running, failed = parts(args.jobs), {}, []
    begun = time.monotonic()
    while waiting or running:
        while waiting and len(running) < args.jobs:
            name, statement = waiting.pop(0)
            running[name] = subprocess.Popen([sys.executable, '-c', statement])
        for name, process in list(running.items()):
            if process.poll() is not None:
                del running[name]
                if process.returncode != 0:
                    failed.append(name)
                print(f'warm_cache: {name} {"done" if process.returncode == 0 else "FAILED"} '
                      f'at {time.monotonic() - begun:.0f} s', flush=True)
        time.sleep(0.2)
    if failed:
        print(f'warm_cache: failed: {", ".join(failed)}', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
