"""``python -m snn_tools.run.warm_cache [--jobs N] [--demo]``: fill numba's on-disk cache.

``--demo`` (``make`` at install) compiles only what ``make demo`` runs (the default estimator's
kernels, ~20 s), so a newcomer's first demo does not wait for every kind; without it (``make
warm``, which ``make test`` runs first) every part below.

Compiles each filter kind's kernels and closed loop, and the Basilisk truth's sample writer, on
``--jobs`` worker processes (default: the CPUs, at most 4), each taking the next part when it is
done with one: the spiking kinds first (the longest, ~20-45 s each), so the workers end
together: ~106 s on a 2-core machine for ~210 s of compiling. Each kernel is compiled once and
then loaded by every node and Monte Carlo. Exits non-zero, naming the part, if one fails.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
import time
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed


def parts() -> list[str]:
    """The parts, longest first: each filter kind (its kernels, then its closed loop, in one
    process: the loop reuses them), the spiking kinds first, the later ones of each group (the
    costlier gain laws) first; the Basilisk truth (~10 s) before them, so it does not end the run
    alone."""
    from snn_estimator import FILTER_KINDS
    kinds = list(FILTER_KINDS)[::-1]
    return ['basilisk truth'] + sorted(kinds, key=lambda kind: not FILTER_KINDS[kind].spiking)


def warm(part: str) -> str:
    """Compile one part (in a worker process); the traceback as text if it failed, else ''."""
    try:
        from snn_estimator import warm_up
        if part == 'demo':
            warm_up.demo()
        elif part == 'basilisk truth':
            warm_up.closed_loops(kinds=(), basilisk=True)
        else:
            warm_up.filter_kernels([part])
            warm_up.closed_loops(kinds=[part], basilisk=False)
    except Exception:  # noqa: BLE001 - reported by name, the others go on
        return traceback.format_exc()
    return ''


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='warm_cache', description=__doc__.split('\n\n')[0])
    parser.add_argument('--demo', action='store_true',
                        help="only what make demo runs (the default estimator's kernels)")
    parser.add_argument('--jobs', type=int, default=min(os.cpu_count() or 1, 4),
                        help='worker processes (default: the CPUs, at most 4)')
    args = parser.parse_args(argv)
    if args.jobs < 1:
        parser.error('--jobs must be >= 1')
    begun, failed = time.monotonic(), []
    with ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context('spawn')) as pool:
        futures = {pool.submit(warm, part): part for part in (['demo'] if args.demo else parts())}
        for future in as_completed(futures):
            error = future.result()
            if error:
                failed.append(futures[future])
                print(error, file=sys.stderr)
            print(f'warm_cache: {futures[future]} {"FAILED" if error else "done"} at '
                  f'{time.monotonic() - begun:.0f} s', flush=True)
    if failed:
        print(f'warm_cache: failed: {", ".join(failed)}', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
