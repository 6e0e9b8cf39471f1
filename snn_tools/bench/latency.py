"""snn_latency_bench: wall-clock latency from a measurement to its estimate and to its control, in realtime mode.

Runs the demo pipeline (every node its own process, recorder included, the demo's CPU plan and
its realtime scheduling, the normal policy; ``10x_batch``: SCHED_BATCH) in realtime mode,
where the plant steps on a wall-clock timer and the sensor
publishes one measurement per step: 10 Hz at ``1x`` and 100 Hz at ``10x`` (the plant's
``real_time_factor``). A probe process subscribes to ``measurement``, ``estimate`` and ``control``
(raw CDR, best effort, the pipeline's executor) and takes each message's receive time at the
entry of its callback on CLOCK_MONOTONIC (``time.monotonic_ns``). Every clock read is in the probe,
one process on one host, so no clocks are compared across processes and no offset is needed;
the header stamps (simulated time) only pair the messages: the estimate that used z_k is
stamped t_k + time_step (x_hat_{k+1}, snn_estimator.runners.filter_runner), and the control answering it
carries the same stamp. Latency = receive(estimate or control) - receive(measurement), so the
probe's own delivery cost, the same on both ends, cancels to first order.

Per case the tool reports p50 / p99 / max in milliseconds over ``--samples`` measurements
(default 10,000; a 10x case then takes ~2 minutes, a 1x case ~17), plus the largest latency
during the first second of stepping (start-up: the filter's first steps, caches) against the
rest. The default cases name the causes of the tail by switching them off one at a time:
``1x_awake`` and ``10x_awake`` keep idle CPUs polling (every node holds the kernel's CPU latency
request at 0 us, SNN_CPU_WAKE_LATENCY_US=0; a halted vCPU wakes through its host), and at 10x
``10x_gc_frozen`` runs every node with the garbage collector frozen and disabled after start-up
(SNN_GC=freeze, see scenario_nodes.runtime.tune_process), ``10x_gc_unfrozen`` with the collector
as Python sets it (SNN_GC=none; the default freezes only the start-up's objects), ``10x_log_warn`` with the nodes'
loggers at WARN (SNN_LOG_LEVEL), ``10x_unpinned`` without the demo's CPU plan (``1x_unpinned`` on
request); ``10x_wait`` (and ``1x_wait``, not run by default) runs the
estimator with ``provisional_steps: false``, waiting for the plant's report of the applied control
as before provisional steps (one step of latency by design), the reference within the same run.
An estimate published again under its stamp (a correction, snn_estimator.runners.provisional) counts
from its first arrival, and the copies are counted (``estimates_again``). Results: stdout and
``--out`` (JSON: case -> path -> p50_ms, p99_ms, max_ms, ...).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import shutil
import signal
import struct
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from tempfile import mkdtemp

import numpy as np

from snn_estimator.catalog import DEFAULT_FILTER
from snn_estimator.filters.estimators import FILTER_KINDS

#: case -> (plant real_time_factor, extra environment of every node, node parameters changed,
#: run_pipeline options)
CASES = {
    '1x': (1.0, {}, {}, {}),
    '10x': (10.0, {}, {}, {}),
    '10x_gc_frozen': (10.0, {'SNN_GC': 'freeze'}, {}, {}),
    # the collector as Python sets it: a full collection traverses the start-up's objects too (the
    # default freezes them, decisions.md 42)
    '10x_gc_unfrozen': (10.0, {'SNN_GC': 'none'}, {}, {}),
    '10x_log_warn': (10.0, {'SNN_LOG_LEVEL': 'warn'}, {}, {}),
    # the estimator waiting for the plant's applied_control report (the design before provisional steps)
    '1x_wait': (1.0, {}, {'estimator': {'provisional_steps': False}}, {}),
    '10x_wait': (10.0, {}, {'estimator': {'provisional_steps': False}}, {}),
    # no CPU plan: every node may run on either CPU (the demo pins them for lockstep throughput)
    '1x_unpinned': (1.0, {}, {}, {'pin_cpus': False}),
    '10x_unpinned': (10.0, {}, {}, {'pin_cpus': False}),
    # SCHED_BATCH, the lockstep policy (realtime runs the normal one, decision 39): no wakeup
    # preemption, so a woken controller waits for the estimator's callback to end on their CPU
    '1x_batch': (1.0, {}, {}, {'scheduling': 'batch'}),
    '10x_batch': (10.0, {}, {}, {'scheduling': 'batch'}),
    # idle CPUs kept polling (the kernel's CPU latency request held at 0 us by every node): a
    # halted vCPU of a virtual machine wakes through its host (docs/performance.md)
    '1x_awake': (1.0, {'SNN_CPU_WAKE_LATENCY_US': '0'}, {}, {}),
    '10x_awake': (10.0, {'SNN_CPU_WAKE_LATENCY_US': '0'}, {}, {}),
}
DEFAULT_CASES = ('1x', '1x_awake', '10x', '10x_awake', '10x_batch', '10x_gc_frozen', '10x_gc_unfrozen', '10x_log_warn',
                 '10x_unpinned', '10x_wait')
#: Paths measured: name -> topic whose receive time ends it (each starts at the measurement).
PATHS = {'measurement_to_estimate': 'estimate', 'measurement_to_control': 'control'}
PROBE_TOPICS = ('measurement', 'estimate', 'control')
#: Samples at the start of stepping reported apart (the first second at 10 Hz... 10x: 0.1 s).
START_SAMPLES = 10
_STAMP = struct.Struct('<iI')  # header.stamp after the 4-byte CDR encapsulation header


def percentile(sorted_values: np.ndarray, q: float) -> float:
    """The q-th percentile (0-100) of ascending values, interpolated linearly between the two
    nearest ranks (numpy's default 'linear' method): rank q/100 * (n - 1)."""
    n = len(sorted_values)
    if n == 0:
        raise ValueError('percentile of no samples')
    if not 0.0 <= q <= 100.0:
        raise ValueError(f'percentile q = {q}: expected 0-100')
    rank = q / 100.0 * (n - 1)
    low = int(math.floor(rank))
    high = min(low + 1, n - 1)
    return float(sorted_values[low] + (rank - low) * (sorted_values[high] - sorted_values[low]))


def summary(latencies_ms) -> dict:
    """p50 / p99 / max (and mean, count) of latencies in milliseconds; the start-up samples
    (the first START_SAMPLES) and the rest are also given their own max."""
    values = np.asarray(latencies_ms, dtype=float)
    if values.size == 0:
        raise ValueError('no latency samples: did the pipeline step? (see the run logs)')
    ordered = np.sort(values)
    return {'p50_ms': percentile(ordered, 50.0), 'p99_ms': percentile(ordered, 99.0),
            'max_ms': float(ordered[-1]), 'mean_ms': float(values.mean()), 'samples': int(values.size),
            'start_max_ms': float(values[:START_SAMPLES].max()),
            'steady_max_ms': float(values[START_SAMPLES:].max()) if values.size > START_SAMPLES else None}


def path_figures(latencies_ms: np.ndarray, expected: int) -> dict:
    """The summary of one path's latencies, with how many of the ``expected`` measurements had
    no answer; a path without any answer is reported (samples 0), not raised."""
    if len(latencies_ms) == 0:
        return {'samples': 0, 'unanswered': int(expected)}
    return {**summary(latencies_ms), 'unanswered': max(int(expected) - len(latencies_ms), 0)}


def format_line(case: str, path: str, figures: dict) -> str:
    """One printed line per case and path; a path with no answers (every control refused as
    stale under load, say) or too few for a steady part says so instead of a number."""
    head = f'{case:<14} {path:<24}'
    if figures['samples'] == 0:
        return f"{head} no answers to {figures['unanswered']} measurements"
    steady = figures['steady_max_ms']
    after = f'{steady:.2f}' if steady is not None else 'n/a'
    missing = f", {figures['unanswered']} unanswered" if figures['unanswered'] else ''
    return (f"{head} p50 {figures['p50_ms']:6.2f} ms  p99 {figures['p99_ms']:6.2f}  "
            f"max {figures['max_ms']:7.2f}  (start {figures['start_max_ms']:.2f}, after {after})  "
            f"n {figures['samples']}{missing}")


def match_latencies(source: dict[int, int], target: dict[int, int], offset_ns: int) -> np.ndarray:
    """Milliseconds from each source message (stamp -> receive ns) to the target message
    stamped ``offset_ns`` later, in stamp order; source messages without one are skipped."""
    pairs = [(target[stamp + offset_ns] - received) for stamp, received in sorted(source.items())
             if stamp + offset_ns in target]
    return np.asarray(pairs, dtype=float) * 1e-6


def first_arrivals(rows: np.ndarray) -> dict[int, int]:
    """Stamp -> receive time of its first message, from (stamp, receive ns) rows in arrival
    order (a corrected estimate or a resend comes again under its stamp)."""
    first = {}
    for stamp, received in rows.tolist():
        first.setdefault(stamp, received)
    return first


def stamp_ns(data: bytes) -> int:
    """The header stamp of a CDR message with a std_msgs/Header first (nanoseconds)."""
    sec, nanosec = _STAMP.unpack_from(data, 4)
    return sec * 1_000_000_000 + nanosec


# ------------------------------------------------------------------------------------ probe
def probe_main(out: Path) -> int:
    """(the probe process) Record (stamp, receive time) per topic until SIGINT/SIGTERM, then
    write them to ``out`` (npz: one (n, 2) int64 array per topic)."""
    from geometry_msgs.msg import AccelStamped, PointStamped
    from nav_msgs.msg import Odometry
    from rclpy.node import Node

    from scenario_nodes import qos
    from scenario_nodes.runtime import ProcessHooks, run_node

    types = {'measurement': PointStamped, 'estimate': Odometry, 'control': AccelStamped}

    class Probe(ProcessHooks, Node):
        def __init__(self):
            super().__init__('latency_probe')
            events = qos.QosEvents(self)
            self.received = {topic: [] for topic in PROBE_TOPICS}
            for topic in PROBE_TOPICS:
                qos.subscription(self, events, types[topic], topic, self._on(self.received[topic]),
                                 qos.INPUT_QOS)

        @staticmethod
        def _on(store):
            clock = time.monotonic_ns

            def callback(data: bytes) -> None:
                store.append((clock(), data))  # decode after the run: nothing more in the callback
            return callback

        def close(self) -> None:
            arrays = {topic: np.array([(stamp_ns(data), t) for t, data in rows], dtype=np.int64).reshape(-1, 2)
                      for topic, rows in self.received.items()}
            np.savez(out, **arrays)

    return run_node(Probe, [], 'latency_probe')


#: node -> diagnostics keys a case reports from its bag: what the loop did while it was timed
#: (an estimate waits for the plant's report when the controller's u_k is not there: one step late)
PIPELINE_COUNTS = {
    'cw_plant': ('late_controls', 'control_timeouts'),
    'lqr_controller': ('controls_published', 'estimates_rejected', 'safe_mode_steps'),
    'estimator': ('steps', 'provisional_steps', 'provisional_corrected', 'controls_missing',
                  'measurements_rejected'),
}


def pipeline_counts(bag_dir: Path) -> dict:
    """The nodes' own counters at the end of a case (their last diagnostics in its bag), with
    ``steps_waiting_for_report``: estimator steps not taken provisionally, each answered a step
    late. Empty when the bag cannot be read (the latencies stand without it)."""
    from snn_tools.bags.data import read_bag
    try:
        run = read_bag(bag_dir)
    except Exception as error:  # noqa: BLE001 - a diagnostic: never lose the latencies to it
        print(f'snn_latency_bench: no pipeline counts from {bag_dir}: {error}', file=sys.stderr)
        return {}
    counts = {}
    for node, keys in PIPELINE_COUNTS.items():
        last = run.last_diagnostics(node)
        for key in keys:
            if key in last:
                counts[f'{node}.{key}'] = int(float(last[key]))
    if 'estimator.steps' in counts and 'estimator.provisional_steps' in counts:
        counts['steps_waiting_for_report'] = counts['estimator.steps'] - counts['estimator.provisional_steps']
    return counts


@contextmanager
def environment(values: dict):
    """os.environ with ``values`` set (the pipeline's node processes inherit it)."""
    saved = {key: os.environ.get(key) for key in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def run_case(run_dir: Path, case: str, samples: int, estimator: str, domain_id: int,
             time_step: float = 0.1) -> dict:
    """One realtime run with the probe; returns the case's figures."""
    from snn_tools.run.demo import pipeline_env, run_pipeline
    factor, env, parameters, options = CASES[case]
    run_dir.mkdir(parents=True, exist_ok=True)
    probe_file = run_dir / 'probe.npz'
    with environment(env):
        probe = subprocess.Popen([sys.executable, '-m', 'snn_tools.bench.latency', '--probe', str(probe_file)],
                                 env=pipeline_env(domain_id), stdout=subprocess.DEVNULL,
                                 stderr=open(run_dir / 'probe.log', 'w'), start_new_session=True)
        try:
            time.sleep(2.0)  # the probe's subscriptions are up before the first measurement
            duration = (samples + START_SAMPLES + 5) * time_step
            # the probe is one more subscriber of measurement, estimate and control: each publisher
            # waits for it too, so it cannot stand in for a node (decisions.md 33 and 41)
            run_pipeline(run_dir, estimator, 'realtime', duration=duration, real_time_factor=factor,
                         domain_id=domain_id, extra=parameters, listeners=dict.fromkeys(PROBE_TOPICS, 1),
                         **options)
        finally:
            probe.send_signal(signal.SIGINT)
            try:
                probe.wait(20.0)
            except subprocess.TimeoutExpired:
                probe.kill()
                probe.wait()
    if not probe_file.exists():
        raise RuntimeError(f'the latency probe wrote nothing; see {run_dir / "probe.log"}')
    recorded = np.load(probe_file)
    received = {topic: first_arrivals(recorded[topic]) for topic in PROBE_TOPICS}
    offset = int(round(time_step * 1e9))
    figures = {'real_time_factor': factor, 'environment': env, 'parameters': parameters, 'pipeline': options,
               'measurements': len(received['measurement']),
               'estimates_again': int(len(recorded['estimate']) - len(received['estimate']))}
    for path, topic in PATHS.items():
        latencies = match_latencies(received['measurement'], received[topic], offset)[:samples]
        figures[path] = path_figures(latencies, min(samples, len(received['measurement'])))
    figures['pipeline_counts'] = pipeline_counts(run_dir / 'bag')
    return figures


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='snn_latency_bench', description=__doc__.split('\n\n')[0])
    parser.add_argument('--samples', type=int, default=10_000,
                        help='measurements per case (default 10000: ~17 min at 1x, ~2 min at 10x)')
    parser.add_argument('--cases', nargs='+', default=list(DEFAULT_CASES), choices=tuple(CASES),
                        help=f'cases to run (default: {" ".join(DEFAULT_CASES)})')
    parser.add_argument('--estimator', default=DEFAULT_FILTER, choices=tuple(FILTER_KINDS))
    parser.add_argument('--out', type=Path, help='also write the figures as JSON here')
    parser.add_argument('--domain-id', type=int, help='ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID or random)')
    parser.add_argument('--history', type=Path,
                        help='also keep a copy of the JSON in this folder, named by the start time (UTC), '
                             'so that runs compared later each have their file')
    parser.add_argument('--keep-runs', action='store_true',
                        help="keep every case's folder (bag, node logs, probe.npz; kept anyway when a case fails)")
    parser.add_argument('--probe', type=Path, help=argparse.SUPPRESS)  # (internal) the probe process
    args = parser.parse_args(argv)
    if args.probe is not None:
        return probe_main(args.probe)
    if args.samples < 2 * START_SAMPLES:
        parser.error(f'--samples must be >= {2 * START_SAMPLES}')
    domain = args.domain_id
    if domain is None:
        domain = int(os.environ.get('ROS_DOMAIN_ID') or random.randint(1, 100))
    print(f'snn_latency_bench: {args.estimator}, realtime, {args.samples} measurements per case, '
          f'{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}, ROS domain {domain}')
    results, failures = {}, {}
    started = time.strftime('%Y%m%dT%H%MZ', time.gmtime())
    folder = Path(mkdtemp(prefix='snn_latency_bench_'))
    for index, case in enumerate(args.cases):
        run_dir = folder / f'{index:02d}_{case}'  # a case named twice runs twice, each in its own folder
        try:
            figures = run_case(run_dir, case, args.samples, args.estimator, domain)
        except (RuntimeError, ValueError) as error:
            print(f'snn_latency_bench: case {case} failed: {error}', file=sys.stderr)
            failures[f'{index:02d}_{case}'] = str(error)
            continue
        results[case if case not in results else f'{case}_{index:02d}'] = figures
        for path in PATHS:
            print(format_line(case, path, figures[path]), flush=True)
        waiting = figures.get('pipeline_counts', {}).get('steps_waiting_for_report', 0)
        if waiting > 2:  # the first step and the last one wait by design
            print(f'{case:<14} {waiting} estimator steps waited for the plant\'s report (the controller\'s '
                  f'u_k was not there): each answered a step late', flush=True)
    if failures:
        print(f'snn_latency_bench: {len(failures)} case(s) failed; their logs are kept in {folder}', file=sys.stderr)
    elif args.keep_runs:
        print(f'snn_latency_bench: the runs are kept in {folder}')
    else:
        shutil.rmtree(folder, ignore_errors=True)
    report = {'estimator': args.estimator, 'samples': args.samples, 'cpus': os.cpu_count(),
              'load_average_1min': os.getloadavg()[0], 'started_utc': started, 'cases': results}
    if failures:
        report['failed_cases'] = failures
    for out in (args.out, args.history / f'latency_{started}.json' if args.history else None):
        if out and results:
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(report, indent=2) + '\n')
            print(f'wrote {out}' + (' (the finished cases only)' if failures else ''))
    return 1 if failures else 0


if __name__ == '__main__':
    raise SystemExit(main())
