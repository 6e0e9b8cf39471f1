"""snn_loop_bench: how fast the closed loop runs over ROS 2 on this machine, and where the CPU goes.

Runs the lockstep demo pipeline (recorder included, no figures) ``--runs`` times and prints, per
run, the real-time factor and the CPU time each node's process used per step. The CPU is read
from /proc (Linux) over the middle 60 % of the plant's stepping (its diagnostics say when the
stepping ended and how long it took), so start-up and shut-down are left out; steps in that
window are counted at the run's mean rate. Reading /proc every 50 ms
costs the machine a little itself. The figures of docs/performance.md come from this tool.

In the same invocation it measures the loop's transport floor (issue 25): a two-process rclpy
round trip with the pipeline's executor, QoS and raw CDR (:mod:`snn_tools.bench.round_trip`), and
reports each run's real-time factor as ``fraction_of_floor`` = factor / (dt / RTT): a lockstep
step costs at least one round trip (estimate k -> control k -> estimate k+1). What a step costs
is counted per run:

* ``deliveries_per_step``: per topic, messages per step (the nodes' published counters, /clock
  one per step) times the subscriptions matched to it, taken from the ROS graph while the loop
  steps (a separate census process, which subscribes to nothing);
* ``wakeups_per_step``: voluntary context switches per step of each node's process, all its
  threads (/proc/<pid>/task/*/status over the same window): every time a thread slept and was
  woken (an executor callback, a DDS receive thread, a timer). The executor callbacks alone are
  one per delivery (EventsExecutor runs one subscription callback per sample) plus the timers;
* ``critical_path_hops``: 2 (estimate k -> controller -> control k -> estimator -> estimate
  k+1: with provisional steps, the default, the estimator steps with the controller's u_k and
  the plant's report of the control it applied only confirms the step; the plant -> sensor ->
  estimator path runs one step ahead, in parallel: z_k was there before u_k's report in 98 % of
  the steps, timed by a probe on every loop topic). Without provisional steps it is 3 (the
  estimator waits for applied_control): a step then costs at least 1.5 round trips.

``--single-process`` runs every node in one process and one executor
(:mod:`snn_tools.run.single_process`) instead of one process per node.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from tempfile import TemporaryDirectory

from scenario_nodes.topics import APPLIED_CONTROL, CLOCK, DIAGNOSTICS, PIPELINE_TOPICS
from snn_estimator.catalog import DEFAULT_FILTER
from snn_estimator.filters.estimators import FILTER_KINDS
from snn_tools.progress import track
from snn_tools.run.demo import SCHEDULING, Pipeline, pipeline_env, run_pipeline

#: Part of the stepping interval, at each end, left out of the CPU window.
WINDOW_MARGIN = 0.2
SAMPLE_PERIOD = 0.05


#: Deliveries on the path that paces a lockstep step: estimate -> control -> estimate, since
#: provisional steps (the estimator steps with the controller's u_k at once; the plant's report
#: of the applied control only confirms it). Waiting for that report (``provisional_steps:
#: false``) makes it 3: estimate -> control -> applied_control -> estimate.
CRITICAL_PATH_HOPS = 2
#: The sampler reads the context switches of every thread every this many samples.
SWITCH_EVERY = 10


def voluntary_switches(pid: int) -> int | None:
    """Voluntary context switches of all threads of a process (each one: a thread slept and
    was woken), or None if it is gone or the system has no /proc."""
    total = 0
    try:
        tasks = os.listdir(f'/proc/{pid}/task')
    except OSError:
        return None
    for task in tasks:
        try:
            with open(f'/proc/{pid}/task/{task}/status') as status:
                for line in status:
                    if line.startswith('voluntary_ctxt_switches'):
                        total += int(line.split()[1])
                        break
        except OSError:
            continue  # a thread that ended meanwhile
    return total


def deliveries_per_step(published_per_step: dict[str, float], subscribers: dict[str, int]) -> dict:
    """Deliveries per step by topic: messages per step x matched subscriptions, and the total."""
    per_topic = {topic: published_per_step[topic] * subscribers.get(topic, 0) for topic in published_per_step}
    return {'by_topic': per_topic, 'total': sum(per_topic.values())}


def fraction_of_floor(real_time_factor: float, dt: float, rtt_us: float) -> float:
    """The real-time factor as a part of dt / RTT (see :func:`snn_tools.bench.round_trip.floor_factor`)."""
    from snn_tools.bench.round_trip import floor_factor
    return real_time_factor / floor_factor(dt, rtt_us)


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
        self.switches: list[tuple[float, dict[str, int]]] = []  # (unix time, switches by node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def _run(self) -> None:
        count = 0
        while not self._stop.is_set():
            now = time.time()
            cpu, switches = {}, {}
            for name, process in list(self.pipeline.processes.items()):
                seconds = process_cpu_seconds(process.pid) if process.poll() is None else None
                if seconds is not None:
                    cpu[name] = seconds
                if count % SWITCH_EVERY == 0 and seconds is not None:
                    woken = voluntary_switches(process.pid)
                    if woken is not None:
                        switches[name] = woken
            self.samples.append((now, cpu))
            if switches:
                self.switches.append((now, switches))
            count += 1
            self._stop.wait(self.period)

    def cpu_per_step(self, stepping_end: float, stepping_wall_s: float,
                     steps: int) -> dict[str, float] | None:
        """Milliseconds of CPU per step for each node over the middle of the stepping interval
        (which ended at unix time ``stepping_end`` and lasted ``stepping_wall_s``); None when
        there are too few samples (a run shorter than a few sampling periods, or no /proc)."""
        per_step = _per_step(self.samples, stepping_end, stepping_wall_s, steps, minimum=3)
        return None if per_step is None else {name: 1e3 * value for name, value in per_step.items()}

    def wakeups_per_step(self, stepping_end: float, stepping_wall_s: float,
                         steps: int) -> dict[str, float] | None:
        """Voluntary context switches per step for each node over the same window (None when
        there are fewer than two readings in it)."""
        return _per_step(self.switches, stepping_end, stepping_wall_s, steps, minimum=2)


def _per_step(samples, stepping_end: float, stepping_wall_s: float, steps: int, minimum: int):
    """Increase per step of cumulative per-node counters over the middle of the stepping."""
    if stepping_end <= 0 or stepping_wall_s <= 0 or steps <= 0:
        return None
    start = stepping_end - stepping_wall_s
    begin = start + WINDOW_MARGIN * stepping_wall_s
    end = start + (1.0 - WINDOW_MARGIN) * stepping_wall_s
    inside = [(t, values) for t, values in samples if begin <= t <= end]
    if len(inside) < minimum:
        return None
    (t0, first), (t1, last) = inside[0], inside[-1]
    window_steps = steps * (t1 - t0) / stepping_wall_s
    if window_steps <= 0:
        return None
    return {name: (last[name] - first[name]) / window_steps for name in last if name in first}


#: Topics whose matched subscriptions the census counts (absolute names, no namespace).
CENSUS_TOPICS = tuple('/' + t for t in PIPELINE_TOPICS) + ('/' + APPLIED_CONTROL, CLOCK)
#: The longest the census watches the graph (seconds); bench_run stops it when the run ends.
CENSUS_MAX_SECONDS = 3600.0
#: What rmw reports for an endpoint discovered before its participant's node names arrived.
UNKNOWN_NODE = '_NODE_NAME_UNKNOWN_'


def census_main(seconds: float) -> int:
    """(the census process) Print, as JSON, how many nodes subscribed to each of CENSUS_TOPICS
    while it watched the graph: until its standard input closes (the run ended) or ``seconds``
    passed. It counts the nodes seen over the whole watch, not at once (a short lockstep run's
    nodes may come and go within it), by name, and leaves out endpoints whose node is not known
    yet (rmw names them _NODE_NAME_UNKNOWN_ until the participant's node list arrives: counted,
    one node would count twice)."""
    import rclpy
    rclpy.init(args=[])
    node = rclpy.create_node('snn_loop_census')
    seen: dict[str, set] = {topic: set() for topic in CENSUS_TOPICS}
    ended = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), ended.set()), daemon=True).start()
    print('ready', flush=True)
    deadline = time.monotonic() + seconds
    try:
        while time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
            for topic in CENSUS_TOPICS:
                seen[topic].update((info.node_namespace, info.node_name)
                                   for info in node.get_subscriptions_info_by_topic(topic)
                                   if info.node_name not in (node.get_name(), UNKNOWN_NODE))
            if ended.is_set():
                break
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    print(json.dumps({topic: len(nodes) for topic, nodes in seen.items()}))
    return 0


class Census:
    """Runs the census process in the pipeline's ROS domain, started before the nodes so that it
    discovers each one as it comes up; ``result()`` ends the watch and returns the counts."""

    def __init__(self, env: dict, seconds: float = CENSUS_MAX_SECONDS):
        self._process = subprocess.Popen(
            [sys.executable, '-m', 'snn_tools.bench.loop', '--census', str(seconds)], env=env,
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        self._process.stdout.readline()  # 'ready': its participant is up

    def result(self) -> dict[str, int] | None:
        try:
            out, _ = self._process.communicate(timeout=30)  # closes its stdin: the run ended
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.communicate()
            return None
        try:
            return {topic.lstrip('/'): n for topic, n in json.loads(out.splitlines()[-1]).items()}
        except (ValueError, IndexError):
            return None


def published_per_step(summary: dict, run) -> dict[str, float]:
    """Messages per step by topic: the nodes' published counters, /clock and applied_control
    one per step (the plant publishes both each step; neither is recorded), the diagnostics as
    recorded."""
    steps = summary['steps']
    counts = {topic: values['published'] / steps for topic, values in summary['messages'].items()}
    counts[CLOCK.lstrip('/')] = counts[APPLIED_CONTROL] = 1.0
    counts[DIAGNOSTICS] = run.counts.get('/' + DIAGNOSTICS, 0) / steps
    return counts


def bench_run(run_dir: Path, estimator: str, duration: float, pin_cpus: bool = True,
              scheduling: str = 'batch', plant: str = 'cw', domain_id: int | None = None,
              single_process: bool = False) -> dict:
    """One lockstep run; returns its real-time factor, CPU, wake-ups and deliveries per step."""
    from snn_tools.bags.data import read_bag, summarize

    samplers = []

    def watch(pipeline: Pipeline) -> None:
        samplers.append(CpuSampler(pipeline))
        samplers[-1].start()

    env = pipeline_env(domain_id)  # the domain the pipeline will use, for the census beside it
    census = Census(env)
    try:
        result = run_pipeline(run_dir, estimator, 'lockstep', duration=duration, on_start=watch,
                              pin_cpus=pin_cpus, scheduling=scheduling, plant=plant,
                              domain_id=int(env['ROS_DOMAIN_ID']), single_process=single_process)
    finally:
        for sampler in samplers:
            sampler.stop()
        subscribers = census.result()
    run = read_bag(result['bag'])
    summary = summarize(run)
    stepping_end = float(run.last_diagnostics(f'{plant}_plant').get('finished_unix_time', 0.0))
    window = (stepping_end, summary['wall_time_s'], summary['steps'])
    cpu = samplers[0].cpu_per_step(*window)
    wakeups = samplers[0].wakeups_per_step(*window)
    deliveries = (deliveries_per_step(published_per_step(summary, run), subscribers)
                  if subscribers and summary['steps'] else None)
    return {'real_time_factor': summary['real_time_factor'], 'steps': summary['steps'],
            'scheduling': result['scheduling'], 'single_process': single_process,
            'dt_s': summary['sim_time_s'] / summary['steps'] if summary['steps'] else None,
            'wall_time_s': summary['wall_time_s'], 'final_range_m': summary['final_range_m'],
            'cpu_ms_per_step': cpu, 'wakeups_per_step': wakeups,
            'subscribers': subscribers, 'deliveries_per_step': deliveries,
            'critical_path_hops': CRITICAL_PATH_HOPS}


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
    parser.add_argument('--single-process', action='store_true',
                        help="as snn_demo's: every node in one process and one executor")
    parser.add_argument('--rtt-samples', type=int, default=2000,
                        help='round trips timed for the transport floor (default 2000; 0: skip)')
    parser.add_argument('--domain-id', type=int, help='ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID or random)')
    parser.add_argument('--census', type=float, help=argparse.SUPPRESS)  # (internal) the graph census
    args = parser.parse_args(argv)
    if args.census is not None:
        return census_main(args.census)
    if args.runs < 1 or args.duration <= 0 or args.rtt_samples < 0:
        parser.error('--runs must be >= 1, --duration > 0 and --rtt-samples >= 0')
    layout = 'one process' if args.single_process else 'one process per node'
    print(f'snn_loop_bench: {args.runs} lockstep runs of {args.duration:.0f} s with {args.estimator} '
          f'and the {args.plant} plant, {layout}, '
          f'{os.cpu_count()} CPUs, scheduling {args.scheduling}, CPU affinity {args.cpu_affinity}')
    rtt = None
    if args.rtt_samples:
        from snn_tools.bench.round_trip import measure_round_trip
        try:
            rtt = measure_round_trip(args.rtt_samples, args.domain_id, args.cpu_affinity == 'auto',
                                     args.scheduling)
        except RuntimeError as error:
            print(f'snn_loop_bench: round trip failed: {error}', file=sys.stderr)
            return 1
        print(f"round trip (two rclpy processes, the loop pair's executor, QoS, CDR): median "
              f"{rtt['median_us']:.0f} us, p90 {rtt['p90_us']:.0f}, p99 {rtt['p99_us']:.0f} "
              f"over {rtt['samples']}", flush=True)
    runs = []
    with TemporaryDirectory(prefix='snn_loop_bench_') as folder:
        for index in track(range(args.runs), 'runs', 'snn_loop_bench'):  # progress on a terminal
            try:
                run = bench_run(Path(folder) / f'run_{index}', args.estimator, args.duration,
                                args.cpu_affinity == 'auto', args.scheduling, args.plant,
                                args.domain_id, args.single_process)
            except RuntimeError as error:
                print(f'snn_loop_bench: run {index + 1} failed: {error}', file=sys.stderr)
                return 1
            if rtt and run['dt_s']:
                run['fraction_of_floor'] = fraction_of_floor(run['real_time_factor'], run['dt_s'],
                                                             rtt['median_us'])
            runs.append(run)
            cpu = run['cpu_ms_per_step']
            split = ('  '.join(f'{name} {ms:.2f}' for name, ms in sorted(cpu.items()))
                     + f'  | total {sum(cpu.values()):.2f}') if cpu else 'n/a'
            line = f"run {index + 1}: real-time factor {run['real_time_factor']:5.1f}"
            if 'fraction_of_floor' in run:
                line += f" ({100 * run['fraction_of_floor']:.0f} % of the floor)"
            print(f'{line}  CPU ms/step: {split}', flush=True)
            wakeups, deliveries = run['wakeups_per_step'], run['deliveries_per_step']
            if deliveries:
                clock = deliveries['by_topic'].get(CLOCK.lstrip('/'), 0.0)
                print(f"       deliveries/step {deliveries['total']:.1f} ({clock:.0f} of them /clock), "
                      f"critical path {CRITICAL_PATH_HOPS} hops", flush=True)
            if wakeups:
                print('       wake-ups/step (voluntary context switches, all threads): '
                      + '  '.join(f'{name} {n:.1f}' for name, n in sorted(wakeups.items()))
                      + f'  | total {sum(wakeups.values()):.1f}', flush=True)
    factors = [run['real_time_factor'] for run in runs]
    print(f'real-time factor: median {statistics.median(factors):.1f}, '
          f'min {min(factors):.1f}, max {max(factors):.1f} over {len(factors)} runs')
    fractions = [run['fraction_of_floor'] for run in runs if 'fraction_of_floor' in run]
    summary = {}
    if fractions:
        floor = runs[0]['real_time_factor'] / fractions[0]
        summary = {'floor_real_time_factor': floor, 'fraction_of_floor': statistics.median(fractions)}
        print(f'floor dt / RTT = {floor:.0f}: the loop reaches {100 * statistics.median(fractions):.0f} % '
              'of it (median over the runs)')
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({'estimator': args.estimator, 'plant': args.plant,
                                        'duration_s': args.duration,
                                        'cpus': os.cpu_count(),
                                        'cpu_affinity': args.cpu_affinity,
                                        'single_process': args.single_process,
                                        'load_average_1min': os.getloadavg()[0],
                                        'round_trip': rtt, **summary,
                                        'runs': runs}, indent=2) + '\n')
        print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
