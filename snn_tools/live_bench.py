"""How much the live view slows the lockstep loop: ``python -m snn_tools.live_bench --pairs 8``
(``make bench-live``) -> results/live_view_bench.json.

Runs the lockstep demo pipeline (recorder included) in pairs, one run without the live view and
one with it *and* a Foxglove WebSocket client connected and subscribed to every channel (the
costly case: every frame is encoded and sent), the order alternating from pair to pair so a
trend in the machine's load does not favour either. Reports the real-time factor of each run
(from the plant's diagnostics in the bag), the medians and the median of the per-pair ratios.
On a shared machine the spread is large: compare the ratio, not the absolute figures.
"""

from __future__ import annotations

import argparse
import json
import signal
import statistics
import time
from pathlib import Path
from tempfile import TemporaryDirectory

from scenario_nodes.parameters import DEFAULT_FILTER

from .demo import run_pipeline
from .live_client import FoxgloveClient, free_port
from .progress import track


def one_run(folder: Path, live: bool, estimator: str, duration: float, domain_id: int | None) -> dict:
    from .bag_tools import read_bag, summarize
    port = free_port()
    client = FoxgloveClient(port, keep=False) if live else None
    if client:
        client.start()
    started = time.perf_counter()
    result = run_pipeline(folder, estimator, 'lockstep', duration=duration, domain_id=domain_id, live_view=live,
                          extra={'live_view': {'port': port}} if live else None)
    if client:
        client.stop()
    summary = summarize(read_bag(result['bag']))
    return {'live_view': live, 'real_time_factor': summary['real_time_factor'],
            'final_range_m': summary['final_range_m'], 'wall_s': round(time.perf_counter() - started, 2),
            'messages_to_client': client.count if client else None}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='snn_live_bench', description=__doc__.split('\n\n')[0])
    parser.add_argument('--pairs', type=int, default=8, help='pairs of runs without / with the live view')
    parser.add_argument('--duration', type=float, default=360.0, help='simulated s per run')
    parser.add_argument('--estimator', default=DEFAULT_FILTER)
    parser.add_argument('--domain-id', type=int, help='ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID or random)')
    parser.add_argument('--out', type=Path, default=Path('results/live_view_bench.json'))
    args = parser.parse_args(argv)
    if args.pairs < 1:
        parser.error('--pairs must be >= 1')
    from .demo import _raise_interrupt
    signal.signal(signal.SIGTERM, _raise_interrupt)  # a SIGTERM stops the node processes too
    pairs = []
    with TemporaryDirectory(prefix='snn_live_bench_') as folder:
        for index in track(range(args.pairs), 'pairs', 'snn_live_bench'):
            order = (False, True) if index % 2 == 0 else (True, False)
            runs = {live: one_run(Path(folder) / f'{index}_{int(live)}', live, args.estimator, args.duration,
                                  args.domain_id) for live in order}
            pair = {'without': runs[False], 'with': runs[True],
                    'ratio': runs[True]['real_time_factor'] / runs[False]['real_time_factor']}
            pairs.append(pair)
            print(f"pair {index + 1}: real-time factor {runs[False]['real_time_factor']:.0f} without, "
                  f"{runs[True]['real_time_factor']:.0f} with the live view and a client "
                  f"({runs[True]['messages_to_client']} messages to it), ratio {pair['ratio']:.2f}", flush=True)
    without = [p['without']['real_time_factor'] for p in pairs]
    with_live = [p['with']['real_time_factor'] for p in pairs]
    ratios = [p['ratio'] for p in pairs]
    data = {'estimator': args.estimator, 'duration_s': args.duration, 'mode': 'lockstep', 'pairs': pairs,
            'median_without': statistics.median(without), 'median_with': statistics.median(with_live),
            'median_ratio': statistics.median(ratios), 'min_ratio': min(ratios), 'max_ratio': max(ratios),
            'date': time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime()),
            'note': 'interleaved pairs on a shared 2-core machine: compare the ratio'}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(data, indent=2) + '\n')
    print(f"real-time factor median {data['median_without']:.0f} without, {data['median_with']:.0f} with; "
          f"ratio median {data['median_ratio']:.2f} (min {data['min_ratio']:.2f}, max {data['max_ratio']:.2f}) "
          f'over {len(pairs)} pairs -> {args.out}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
