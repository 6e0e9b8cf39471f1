"""How much the live view slows the lockstep loop, and what it sends: ``python -m
snn_tools.bench.live --pairs 8`` (``make bench-live``) -> results/live_view_bench.json.

Runs the lockstep demo pipeline (recorder included) in sets of three: without the live view; with
it as before the gateway (the SDK serving the port, legacy_subprotocol false) and one
foxglove.sdk.v1 client; and with the gateway and two clients subscribed to every channel, one per
subprotocol (both endpoints open: every frame sent twice, each through the gateway). The order
rotates from set to set so a trend in the machine's load favours none. Reports the real-time
factor of each run (from the plant's diagnostics in the bag), the medians and the medians of the
per-set ratios to the run without, and the live view process's CPU time per wall-clock second
while it sent (sampled from /proc: a share of a core, which the machine's other load hardly
changes, unlike the real-time factor). On a shared machine the spread is large: compare the ratio, not
the absolute figures; the load average before and after is recorded.

Then the bandwidth: realtime runs (``--bandwidth-rtf``, ``--bandwidth-duration``) at the default
settings and at those of ``--raster-variants``, each watched by one client of each subprotocol
(by a foxglove.sdk.v1 client alone where legacy_subprotocol is false): bytes per wall-clock
second on each channel, as a client counted them (payload and the 13-byte message header, not
the WebSocket framing), and the live view's CPU.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import threading
import time
from pathlib import Path
from tempfile import TemporaryDirectory

from snn_estimator.catalog import DEFAULT_FILTER
from snn_tools.live.client import LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL, FoxgloveClient, free_port
from snn_tools.progress import track
from snn_tools.run.demo import run_pipeline

SUBPROTOCOLS = (LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL)
#: The runs of a set: no live view; the SDK alone (as before the gateway) with one client; the
#: gateway with a client of each subprotocol (both endpoints open).
ARMS = ('without', 'sdk_only', 'with')
ARM_SETTINGS = {'without': {}, 'sdk_only': {'live_view': {'legacy_subprotocol': False},
                                             'subprotocols': (SDK_SUBPROTOCOL,)}, 'with': {}}


def rates(client: FoxgloveClient) -> dict:
    """Bytes and messages per wall-clock second per topic over the client's receiving time."""
    out = {}
    for topic, (first, last) in sorted(client.received_at.items()):
        span = last - first
        out[topic] = {'bytes': client.bytes[topic], 'seconds': round(span, 2),
                      'bytes_per_s': round(client.bytes[topic] / span) if span > 0 else None}
    return out


class CpuSampler(threading.Thread):
    """Samples a process's CPU time (user + system, s, from /proc) every ``period`` until
    ``stop()`` or the process ends: ``samples`` of (time.monotonic(), CPU s). CPU time, unlike
    the real-time factor, hardly depends on the machine's other load."""

    def __init__(self, pid: int, period: float = 0.1):
        super().__init__(daemon=True)
        self._path, self._period = Path(f'/proc/{pid}/stat'), period
        self._stopping = threading.Event()
        self.samples: list[tuple[float, float]] = []

    def share(self, start: float, end: float) -> float | None:
        """CPU s per wall-clock s between ``start`` and ``end`` (time.monotonic()), from the
        samples nearest inside; None without two of them."""
        inside = [(t, cpu) for t, cpu in self.samples if start <= t <= end]
        if len(inside) < 2 or inside[-1][0] <= inside[0][0]:
            return None
        return (inside[-1][1] - inside[0][1]) / (inside[-1][0] - inside[0][0])

    def run(self) -> None:
        ticks = os.sysconf('SC_CLK_TCK')
        while not self._stopping.is_set():
            try:
                fields = self._path.read_text().rpartition(')')[2].split()
            except OSError:  # the process has ended: keep the last reading
                return
            self.samples.append((time.monotonic(), (int(fields[11]) + int(fields[12])) / ticks))
            self._stopping.wait(self._period)

    def stop(self) -> None:
        self._stopping.set()
        self.join(5.0)


def watched_run(folder: Path, live: bool, estimator: str, mode: str, duration: float, domain_id: int | None,
                real_time_factor: float | None = None, live_view: dict | None = None,
                subprotocols=SUBPROTOCOLS) -> dict:
    """One run; with ``live``, the live view (``live_view``: its parameters) and a client of each
    of ``subprotocols`` (their messages and bytes per second)."""
    from snn_tools.bags.data import read_bag, summarize
    port = free_port()
    clients = [FoxgloveClient(port, keep=False, subprotocol=p) for p in subprotocols] if live else []
    for client in clients:
        client.start()
    samplers = []

    def sample(pipeline) -> None:
        samplers.append(CpuSampler(pipeline.processes['live_view'].pid))
        samplers[0].start()
    started = time.perf_counter()
    result = run_pipeline(folder, estimator, mode, duration=duration, domain_id=domain_id, live_view=live,
                          real_time_factor=real_time_factor, on_start=sample if live else None,
                          extra={'live_view': {'port': port, **(live_view or {})}} if live else None)
    for client in clients + samplers:
        client.stop()
    summary = summarize(read_bag(result['bag']))
    run = {'live_view': live, 'real_time_factor': summary['real_time_factor'],
           'final_range_m': summary['final_range_m'], 'wall_s': round(time.perf_counter() - started, 2),
           'messages_to_client': sum(c.count for c in clients) if live else None}
    if live:
        for client in clients:
            if client.error is not None or client.subprotocol != client.offered:
                raise RuntimeError(f'the {client.offered} client failed: {client.error or client.subprotocol}')
        run['clients'] = {c.offered: {'messages': c.count, 'per_topic': rates(c)} for c in clients}
        # the live view's CPU while it sent (first to last message a client received): a share of a core
        share = samplers[0].share(min(c.received_at[t][0] for c in clients for t in c.received_at),
                                  max(c.received_at[t][1] for c in clients for t in c.received_at))
        run['live_view_cpu_share'] = round(share, 4) if share is not None else None
    return run


def load_average() -> list[float]:
    return [round(v, 2) for v in os.getloadavg()]


def _setting(item: str) -> tuple[str, float | int | bool]:
    """name=value: true/false a bool, an integer (raster_steps=50) an integer, 20.0 a double."""
    name, _, text = item.partition('=')
    if text.strip().lower() in ('true', 'false'):
        return name.strip(), text.strip().lower() == 'true'
    value = float(text)
    return name.strip(), int(value) if '.' not in text and value.is_integer() else value


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='snn_live_bench', description=__doc__.split('\n\n')[0])
    parser.add_argument('--pairs', type=int, default=8, help='sets of runs: without, with the SDK alone, with '
                        'the gateway and both clients')
    parser.add_argument('--duration', type=float, default=360.0, help='simulated s per run')
    parser.add_argument('--estimator', default=DEFAULT_FILTER)
    parser.add_argument('--domain-id', type=int, help='ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID or random)')
    parser.add_argument('--bandwidth-rtf', type=float, default=5.0, help='real-time factor of the bandwidth runs')
    parser.add_argument('--bandwidth-duration', type=float, default=120.0, help='simulated s per bandwidth run')
    parser.add_argument('--raster-variants', default='legacy_subprotocol=false;raster_rate=20.0;raster_steps=50',
                        help='live_view settings besides the defaults, runs separated by ";" (name=value,...)')
    parser.add_argument('--out', type=Path, default=Path('results/live_view_bench.json'))
    args = parser.parse_args(argv)
    if args.pairs < 1:
        parser.error('--pairs must be >= 1')
    from snn_tools.run.demo import _raise_interrupt
    signal.signal(signal.SIGTERM, _raise_interrupt)  # a SIGTERM stops the node processes too
    variants = [{}] + [dict(_setting(item) for item in variant.split(','))
                       for variant in args.raster_variants.split(';') if variant.strip()]
    pairs, bandwidth = [], []
    load_before = load_average()
    with TemporaryDirectory(prefix='snn_live_bench_') as folder:
        for index in track(range(args.pairs), 'pairs', 'snn_live_bench'):
            order = ARMS[index % 3:] + ARMS[:index % 3]  # each arm first, second and third in turn
            runs = {arm: watched_run(Path(folder) / f'{index}_{arm}', arm != 'without', args.estimator, 'lockstep',
                                     args.duration, args.domain_id, **ARM_SETTINGS[arm]) for arm in order}
            pair = {**runs, 'order': list(order), 'load_average': load_average(),
                    'ratio': runs['with']['real_time_factor'] / runs['without']['real_time_factor'],
                    'ratio_sdk_only': runs['sdk_only']['real_time_factor'] / runs['without']['real_time_factor']}
            pairs.append(pair)
            print(f"set {index + 1}: real-time factor {runs['without']['real_time_factor']:.0f} without, "
                  f"{runs['sdk_only']['real_time_factor']:.0f} with the SDK alone and a foxglove.sdk.v1 client, "
                  f"{runs['with']['real_time_factor']:.0f} with the gateway and a client of each subprotocol "
                  f"(ratios {pair['ratio_sdk_only']:.2f}, {pair['ratio']:.2f}); the live view's CPU "
                  f"{runs['sdk_only']['live_view_cpu_share']} and {runs['with']['live_view_cpu_share']} of a core",
                  flush=True)
        for index, settings in enumerate(variants):
            alone = settings.get('legacy_subprotocol') is False  # the SDK alone: its own client only
            run = watched_run(Path(folder) / f'bandwidth_{index}', True, args.estimator, 'realtime',
                              args.bandwidth_duration, args.domain_id, args.bandwidth_rtf, settings,
                              subprotocols=(SDK_SUBPROTOCOL,) if alone else SUBPROTOCOLS)
            bandwidth.append({'settings': settings or 'defaults', 'real_time_factor': args.bandwidth_rtf,
                              'duration_s': args.bandwidth_duration, 'clients': run['clients'],
                              'live_view_cpu_share': run['live_view_cpu_share']})
            per_topic = run['clients'][SDK_SUBPROTOCOL]['per_topic']
            print(f"bandwidth ({settings or 'defaults'}): " + ', '.join(
                f"{topic} {v['bytes_per_s'] / 1000:.0f} kB/s" for topic, v in per_topic.items())
                + f"; the live view's CPU {run['live_view_cpu_share']} of a core", flush=True)

    def median(key, arm):
        return statistics.median(p[arm]['real_time_factor'] if arm else p[key] for p in pairs)
    ratios = [p['ratio'] for p in pairs]
    data = {'estimator': args.estimator, 'duration_s': args.duration, 'mode': 'lockstep', 'pairs': pairs,
            'median_without': median(None, 'without'), 'median_with': median(None, 'with'),
            'median_sdk_only': median(None, 'sdk_only'),
            'median_ratio': statistics.median(ratios), 'min_ratio': min(ratios), 'max_ratio': max(ratios),
            'median_ratio_sdk_only': median('ratio_sdk_only', None),
            'median_live_view_cpu_share': {arm: statistics.median(
                p[arm]['live_view_cpu_share'] for p in pairs if p[arm]['live_view_cpu_share'] is not None)
                for arm in ('sdk_only', 'with')},
            'date': time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime()),
            'arms': {'without': 'no live view', 'sdk_only': 'the SDK serving the port itself '
                     '(legacy_subprotocol false, as before) and one foxglove.sdk.v1 client',
                     'with': 'the gateway in front of the SDK and a client of each subprotocol'},
            'bandwidth': bandwidth,
            'cpus': os.cpu_count(), 'load_average_before': load_before, 'load_average_after': load_average(),
            'note': 'interleaved sets on a shared 2-core machine: compare the ratios'}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(data, indent=2) + '\n')
    print(f"real-time factor median {data['median_without']:.0f} without, {data['median_sdk_only']:.0f} with the "
          f"SDK alone, {data['median_with']:.0f} with both endpoints; ratio median {data['median_ratio']:.2f} "
          f"(min {data['min_ratio']:.2f}, max {data['max_ratio']:.2f}; SDK alone "
          f"{data['median_ratio_sdk_only']:.2f}) over {len(pairs)} sets -> {args.out}")
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
