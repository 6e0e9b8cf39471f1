"""snn_loop_bench: how fast the closed loop runs over ROS 2 on this machine, and where the CPU goes.

Runs the lockstep demo pipeline (recorder included, no figures) ``--runs`` times and prints, per
run, the real-time factor and the CPU time each node's process used per step. The CPU is read
from /proc (Linux) over the middle 60 % of the plant's stepping (its diagnostics say when the
stepping ended and how long it took), so start-up and shut-down are left out; steps in that
window are counted at the run's mean rate. Reading /proc every 50 ms
costs the machine a little itself. The figures of docs/performance.md come from this tool.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import threading
import time
from pathlib import Path
from tempfile import TemporaryDirectory

from scenario_nodes.parameters import DEFAULT_FILTER
from snn_estimator.estimators import FILTER_KINDS

from .demo import SCHEDULING, Pipeline, run_pipeline
from .progress import track

#: Part of the stepping interval, at each end, left out of the CPU window.
WINDOW_MARGIN = 0.2
SAMPLE_PERIOD = 0.05


def process_cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of a process (all its threads), or None if it is gone or the
    system has no /proc."""
    try:
        with open(f'/proc/{pid}/stat') as stat:
            text = stat.read()
    except OSError:
        return None
    fields = text[text.rindex(')') + 2:].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


class CpuSampler:
    """Samples the CPU seconds of a pipeline's node processes every ``period`` seconds."""

    def __init__(self, pipeline: Pipeline, period: float = SAMPLE_PERIOD):
        self.pipeline = pipeline
        self.period = period
        self.samples: list[tuple[float, dict[str, float]]] = []  # (unix time, cpu by node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def _run(self) -> None:
        while not self._stop.is_set():
            now = time.time()
            cpu = {}
            for name, process in list(self.pipeline.processes.items()):
                seconds = process_cpu_seconds(process.pid) if process.poll() is None else None
                if seconds is not None:
                    cpu[name] = seconds
            self.samples.append((now, cpu))
            self._stop.wait(self.period)

    def cpu_per_step(self, stepping_end: float, stepping_wall_s: float,
                     steps: int) -> dict[str, float] | None:
        """Milliseconds of CPU per step for each node over the middle of the stepping interval
        (which ended at unix time ``stepping_end`` and lasted ``stepping_wall_s``); None when
        there are too few samples (a run shorter than a few sampling periods, or no /proc)."""
        if stepping_end <= 0 or stepping_wall_s <= 0 or steps <= 0:
            return None
        start = stepping_end - stepping_wall_s
        begin = start + WINDOW_MARGIN * stepping_wall_s
        end = start + (1.0 - WINDOW_MARGIN) * stepping_wall_s
        inside = [(t, cpu) for t, cpu in self.samples if begin <= t <= end]
        if len(inside) < 3:
            return None
        (t0, first), (t1, last) = inside[0], inside[-1]
        window_steps = steps * (t1 - t0) / stepping_wall_s
        if window_steps <= 0:
            return None
        return {name: 1e3 * (last[name] - first[name]) / window_steps
                for name in last if name in first}


def bench_run(run_dir: Path, estimator: str, duration: float, pin_cpus: bool = True,
              scheduling: str = 'batch', plant: str = 'cw') -> dict:
    """One lockstep run; returns its real-time factor and CPU per step by node."""
    from .bag_tools import read_bag, summarize

    samplers = []

    def watch(pipeline: Pipeline) -> None:
        samplers.append(CpuSampler(pipeline))
        samplers[-1].start()

    try:
        result = run_pipeline(run_dir, estimator, 'lockstep', duration=duration, on_start=watch,
                              pin_cpus=pin_cpus, scheduling=scheduling, plant=plant)
    finally:
        for sampler in samplers:
            sampler.stop()
    run = read_bag(result['bag'])
    summary = summarize(run)
    stepping_end = float(run.last_diagnostics(f'{plant}_plant').get('finished_unix_time', 0.0))
    cpu = samplers[0].cpu_per_step(stepping_end, summary['wall_time_s'], summary['steps'])
    return {'real_time_factor': summary['real_time_factor'], 'steps': summary['steps'],
            'scheduling': result['scheduling'],
            'wall_time_s': summary['wall_time_s'], 'final_range_m': summary['final_range_m'],
            'cpu_ms_per_step': cpu}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='snn_loop_bench', description=__doc__.split('\n\n')[0])
    parser.add_argument('--estimator', default=DEFAULT_FILTER, choices=tuple(FILTER_KINDS))
    parser.add_argument('--plant', default='cw', choices=('cw', 'basilisk'), help='truth plant (default cw)')
    parser.add_argument('--runs', type=int, default=5, help='lockstep runs (default 5)')
    parser.add_argument('--duration', type=float, default=720.0,
                        help='simulated seconds per run (default 720: long enough for a CPU window)')
    parser.add_argument('--out', type=Path, help='also write the figures as JSON here')
    parser.add_argument('--cpu-affinity', default='auto', choices=('auto', 'off'),
                        help="as snn_demo's (auto: estimator and controller on one CPU)")
    parser.add_argument('--scheduling', default='batch', choices=SCHEDULING,
                        help="as snn_demo's (batch: SCHED_BATCH, no wakeup preemption)")
    args = parser.parse_args(argv)
    if args.runs < 1 or args.duration <= 0:
        parser.error('--runs must be >= 1 and --duration > 0')
    print(f'snn_loop_bench: {args.runs} lockstep runs of {args.duration:.0f} s with {args.estimator} '
          f'and the {args.plant} plant, '
          f'{os.cpu_count()} CPUs, scheduling {args.scheduling}, CPU affinity {args.cpu_affinity}')
    runs = []
    with TemporaryDirectory(prefix='snn_loop_bench_') as folder:
        for index in track(range(args.runs), 'runs', 'snn_loop_bench'):  # progress on a terminal
            try:
                run = bench_run(Path(folder) / f'run_{index}', args.estimator, args.duration,
                                args.cpu_affinity == 'auto', args.scheduling, args.plant)
            except RuntimeError as error:
                print(f'snn_loop_bench: run {index + 1} failed: {error}', file=sys.stderr)
                return 1
            runs.append(run)
            cpu = run['cpu_ms_per_step']
            split = ('  '.join(f'{name} {ms:.2f}' for name, ms in sorted(cpu.items()))
                     + f'  | total {sum(cpu.values()):.2f}') if cpu else 'n/a'
            print(f"run {index + 1}: real-time factor {run['real_time_factor']:5.1f}  "
                  f'CPU ms/step: {split}', flush=True)
    factors = [run['real_time_factor'] for run in runs]
    print(f'real-time factor: median {statistics.median(factors):.1f}, '
          f'min {min(factors):.1f}, max {max(factors):.1f} over {len(factors)} runs')
    if args.out:
        args.out.write_text(json.dumps({'estimator': args.estimator, 'plant': args.plant,
                                        'duration_s': args.duration,
                                        'cpus': os.cpu_count(),
                                        'cpu_affinity': args.cpu_affinity,
                                        'runs': runs}, indent=2) + '\n')
        print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
