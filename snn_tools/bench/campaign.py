"""``snn_campaign_bench``: Monte-Carlo runs per second of a campaign with 1 and 2 local workers.

Runs config/campaigns/bench.yaml (at least a minute with one worker) on a fresh LocalCluster
per worker count, into a temporary directory. The clock starts before the cluster does and
stops when the table is written, so worker start-up (imports, loading the numba kernels) is
counted. With ``--repeat`` the worker counts alternate (1, 2, 1, 2, ...) so that a change in
the machine's load hits both alike; each count reports its best pass and every pass. Writes
``{"workers": {"1": {"runs_per_s": ...}, "2": {...}}, ...}`` to --out.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from importlib.metadata import version
from pathlib import Path

from snn_tools.campaign.cells import code_version
from snn_tools.campaign.run import CampaignProgress, dask_client, run_campaign
from snn_tools.campaign.spec import load_spec, validate


def cpu_model() -> str:
    """The CPU's model name (Linux), or the platform's processor string."""
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.startswith('model name'):
                return line.split(':', 1)[1].strip()
    except OSError:
        pass  # not Linux
    return platform.processor() or 'unknown'


def time_campaign(spec, workers: int, progress: CampaignProgress) -> tuple[dict, list[dict]]:
    """One timed campaign on a new LocalCluster of ``workers``; returns (timings, table rows)."""
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix='snn_campaign_bench_') as out:
        started = time.perf_counter()
        with dask_client(workers) as client:
            ready = time.perf_counter()
            outcome = run_campaign(spec, Path(out), client, progress)
            finished = time.perf_counter()
            worker_cpu = sum(client.run(time.process_time).values())
    runs = outcome.computed * spec.runs
    timings = {
        'runs_per_s': round(runs / (finished - started), 2),
        'wall_s': round(finished - started, 2),
        'cluster_start_s': round(ready - started, 2),
        'worker_seconds_in_cells': round(sum(r['wall_time_s'] for r in outcome.rows), 1),
        # below 1: the workers waited for a core (other load on the machine), or sat idle
        'worker_cpu_per_wall': round(worker_cpu / (workers * (finished - ready)), 3),
        # independent of other load: what one fully available core would give
        'runs_per_worker_cpu_s': round(runs / worker_cpu, 2),
        'load_average_before': round(load_before, 2),
        'load_average_after': round(os.getloadavg()[0], 2),
    }
    return timings, outcome.rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='snn_campaign_bench', description=__doc__.split('\n\n')[0])
    parser.add_argument('--spec', default='campaigns/bench.yaml', help='campaign to time')
    parser.add_argument('--workers', type=int, nargs='+', default=[1, 2], help='worker counts (default 1 2)')
    parser.add_argument('--repeat', type=int, default=1, help='passes per worker count, alternating (default 1)')
    parser.add_argument('--out', type=Path, default=Path('results/campaign_bench.json'))
    parser.add_argument('--quiet', action='store_true', help='no progress bar')
    args = parser.parse_args(argv)
    spec = load_spec(args.spec)
    validate(spec)
    cells = len(spec.cells())
    passes, tables = {str(w): [] for w in args.workers}, []
    for attempt in range(args.repeat):
        for workers in args.workers:
            print(f'pass {attempt + 1}/{args.repeat}, {workers} worker(s): {cells} cells x {spec.runs} runs',
                  file=sys.stderr)
            timings, rows = time_campaign(spec, workers, CampaignProgress(args.quiet))
            passes[str(workers)].append(timings)
            tables.append(rows)
            print(f'  {timings}', file=sys.stderr)
    best = {k: max(v, key=lambda t: t['runs_per_s']) for k, v in passes.items()}
    # the readings only: wall times differ, and the code may change under a long benchmark
    readings = [[{k: v for k, v in row.items() if k not in ('wall_time_s', 'code_version')} for row in rows]
                for rows in tables]
    first = best[str(args.workers[0])]['runs_per_s']
    report = {
        'workers': {k: {**best[k], 'passes': v} for k, v in passes.items()},
        'speedup': {k: round(b['runs_per_s'] / first, 2) for k, b in best.items()},
        'tables_identical': all(t == readings[0] for t in readings),
        'code_versions': sorted({row['code_version'] for rows in tables for row in rows}),
        'campaign': {'spec': args.spec, 'cells': cells, 'runs_per_cell': spec.runs,
                     'runs_per_task': spec.runs_per_task, 'filters': list(spec.filters),
                     'scenario': spec.scenario},
        'machine': {'cpus': os.cpu_count(), 'cpu': cpu_model(), 'python': platform.python_version(),
                    'dask': version('dask'), 'numba': version('numba'), 'code': code_version(),
                    'date': time.strftime('%Y-%m-%d %H:%M')},
        'timing': 'wall clock from cluster start to the written table (worker start-up, kernel '
                  'loading and the report included); runs_per_s = cells x runs / wall_s; the '
                  'figures of a worker count are those of its best pass',
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + '\n')
    print(json.dumps({'runs_per_s': {k: b['runs_per_s'] for k, b in best.items()},
                      'speedup': report['speedup']}), f'-> {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
