"""snn_demo: the closed-loop rendezvous over ROS 2, each node its own process.

Starts the nodes of the pipeline description (scenario_nodes.registry: recorder, lqr_controller,
estimator, position_sensor and cw_plant, in that order) with the package's parameter file, runs
the scenario, stops the nodes cleanly (recorder last), then reads the bag back and writes
``runs/<name>/summary.json`` and the report. What ``make demo`` runs.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

import yaml

from scenario_nodes import registry
from scenario_nodes.parameter_tables import scenarios, sensor_suites
from snn_estimator.catalog import DEFAULT_FILTER
from snn_estimator.filters.estimators import FILTER_KINDS
from snn_tools.paths import DDS_PROFILE, DDS_PROFILE_VARIABLE, config_file

#: The module that runs every node of a run in one process (--single-process).
SINGLE_PROCESS = 'snn_tools.run.single_process'
#: The nodes that watch the loop and yield the CPU to it (see :func:`_child_setup`).
OBSERVERS = ('recorder', 'live_view')
#: The exchange that paces a lockstep run (estimate k -> control k -> estimate k+1).
LOOP_PAIR = ('estimator', 'lqr_controller')
#: Linux scheduling policies the node processes can run under (see :func:`_child_setup`).
SCHEDULING = ('batch', 'normal')
#: The policy by mode when none is asked for (docs/decisions.md, 39): lockstep runs for throughput,
#: realtime for latency.
SCHEDULING_BY_MODE = {'lockstep': 'batch', 'realtime': 'normal'}
BATCH, NORMAL = getattr(os, 'SCHED_BATCH', None), getattr(os, 'SCHED_OTHER', None)


def running_policy(pid: int) -> int | None:
    """The scheduling policy of process ``pid``; None where it cannot be read (not Linux, or
    the process has already exited)."""
    try:
        return os.sched_getscheduler(pid)
    except (AttributeError, OSError):
        return None


def cpu_plan(available=None, plant: str = 'cw') -> dict[str, set[int]]:
    """CPU affinity per node: the estimator and the controller share the last CPU, the plant,
    sensor and recorder get the others, so the pacing exchange wakes a process on the same CPU
    and nothing else runs there. {} (no pinning) with one CPU or no affinity support. On the
    2-core machines: real-time factor median 88 against 70 over 8 interleaved runs. With the
    Basilisk plant (twice the CW plant's CPU per step) the recorder may use every CPU: Basilisk
    / CW real-time factor 0.9 against 0.8 with it pinned (docs/performance.md)."""
    if not hasattr(os, 'sched_setaffinity'):
        return {}
    cpus = sorted(os.sched_getaffinity(0) if available is None else available)
    if len(cpus) < 2:
        return {}
    loop, rest = {cpus[-1]}, set(cpus[:-1])
    plan = {entry.name: loop if entry.name in LOOP_PAIR else rest for entry in registry.NODES}
    if plant == 'basilisk':
        plan['recorder'] = set(cpus)
    return plan


def _replace_file(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` by renaming a finished file over it: a node started a moment
    earlier may still be reading ``path`` (rcl reads its --params-file at init), and a write in
    place truncates it first, so on a loaded machine that node read an empty file and ran on the
    base parameters alone (seen: a controller with neither its guidance nor its weights)."""
    partial = path.with_name(path.name + '.partial')
    partial.write_text(text)
    os.replace(partial, path)


class Pipeline:
    """The node processes of one run, with their logs in ``<run>/logs``."""

    def __init__(self, run_dir: Path, params_file: Path, overrides: dict, env: dict, record: bool = True,
                 namespace: str = '', pin_cpus: bool = True, scheduling: str = 'batch', plant: str = 'cw',
                 live_view: bool = False, single_process: bool = False, sensor: str = 'position',
                 listeners: dict | None = None):
        if scheduling not in SCHEDULING:
            raise ValueError(f'scheduling {scheduling!r}: expected one of {SCHEDULING}')
        optional = [name for name, asked in (('recorder', record), ('live_view', live_view)) if asked]
        #: The nodes of the run in start order (scenario_nodes.registry.pipeline): a sensor suite's
        #: sensors each on their own topic, named after it.
        self.nodes = registry.pipeline(plant, optional, sensor)
        #: The plant's node name (cw_plant or basilisk_plant): the key of its process.
        self.plant = registry.plant_node(plant)
        self.plant_choice, self.sensor = plant, sensor
        #: Subscribers outside the pipeline: topic -> count (e.g. the latency bench's probe).
        self.listeners = dict(listeners or {})
        self.namespace = namespace
        #: Every node in one process and executor (snn_tools.run.single_process), keyed as the plant.
        self.single_process = single_process
        self.record = record
        self.cpus = cpu_plan(plant=plant) if pin_cpus and not single_process else {}
        self.batch = scheduling == 'batch'
        self.refused_batch: list[str] = []  # nodes the kernel would not run under SCHED_BATCH
        self.run_dir = run_dir
        self.params_file = params_file
        self.overrides = overrides
        self.env = env
        self.processes: dict[str, subprocess.Popen] = {}
        # Each node holds its input until its output reaches every subscriber of the run (the
        # plant its first state, the sensors 'truth', the controller 'estimate', the estimator its
        # measurements): DDS may match a subscriber's end first, and the recorder, which subscribes
        # to 'truth' last, would lose the start (docs/decisions.md, 33 and 41). An extra value
        # given for a count wins.
        for name, counts in registry.subscriber_counts(self.nodes, self.listeners).items():
            for key, value in counts.items():
                overrides.setdefault(name, {}).setdefault(key, value)
        (run_dir / 'logs').mkdir(parents=True, exist_ok=True)

    def command(self, name: str, module: str, node_name: str | None = None, remaps=()) -> list[str]:
        # Run-specific values go in a second parameter file: node-specific entries of the first
        # file would win over '-p' arguments, which rcl files under the /** wildcard.
        own = self.single_process_arguments() if module == SINGLE_PROCESS else []
        command = [sys.executable, '-m', module, *own, '--ros-args', '--params-file', str(self.params_file),
                   '--params-file', str(self.overrides_file)]
        if self.namespace:
            command += ['-r', f'__ns:={self.namespace}']
        if node_name and node_name != name:
            command += ['-r', f'__node:={node_name}']
        for remap in remaps:
            command += ['-r', remap]
        return command

    def single_process_arguments(self) -> list[str]:
        """The node set of this run as snn_tools.run.single_process takes it (the same counts)."""
        own = ['--plant', self.plant_choice, '--sensor', self.sensor]
        own += [] if self.record else ['--no-record']
        own += ['--live-view'] if any(node.name == 'live_view' for node in self.nodes) else []
        for topic, count in self.listeners.items():
            own += ['--listener', topic] * count
        return own

    @property
    def overrides_file(self) -> Path:
        return self.run_dir / 'overrides.yaml'

    def start(self) -> None:
        if self.single_process:
            self.start_node(self.plant, SINGLE_PROCESS, log_name='single_process')
        for node in self.nodes:
            if not self.single_process or node.entry.own_process:
                self.start_node(node.entry.name, node.entry.module, node_name=node.name, remaps=node.remaps)

    def start_node(self, name: str, module: str, overrides: dict | None = None, log_name: str | None = None,
                   node_name: str | None = None, remaps=()):
        """Start (or restart, e.g. a hot swap) one node; ``overrides`` update its parameters.
        ``node_name`` runs a second node of the same kind under another name (a standby
        estimator: the parameters of ``name`` with the overrides for ``node_name``)."""
        key = node_name or name
        if overrides:
            self.overrides.setdefault(key, {}).update(overrides)
        document = {f'/**/{n}': {'ros__parameters': values} for n, values in self.overrides.items()}
        _replace_file(self.overrides_file, yaml.dump(document, Dumper=_NoAliases, sort_keys=True))
        log = open(self.run_dir / 'logs' / f'{log_name or key}.log', 'w')
        self.processes[key] = subprocess.Popen(
            self.command(name, module, node_name, remaps), env=self.env, stdout=log, stderr=subprocess.STDOUT,
            start_new_session=True,
            preexec_fn=_child_setup(self.cpus.get(name), name in OBSERVERS, self.batch))
        if self.batch and running_policy(self.processes[key].pid) not in (BATCH, None):
            if not self.refused_batch:
                print(f'snn_demo: the kernel refused SCHED_BATCH for {key}; the nodes run under the '
                      'normal policy (slower lockstep)', file=sys.stderr)
            self.refused_batch.append(key)
        return self.processes[key]

    @property
    def scheduling(self) -> str:
        """The policy the nodes actually run under: 'batch' only if every one got it."""
        return 'batch' if self.batch and not self.refused_batch else 'normal'

    def failed(self) -> list[str]:
        """Nodes that exited although they should still run."""
        return [name for name, process in self.processes.items()
                if name != self.plant and process.poll() is not None]

    def stop(self, names, timeout: float = 10.0) -> dict:
        """SIGINT, then SIGTERM, then SIGKILL; returns exit codes."""
        codes = {}
        for name in names:
            process = self.processes.get(name)
            if process is not None and process.poll() is None:
                process.send_signal(signal.SIGINT)
        for name in names:
            process = self.processes.get(name)
            if process is None:
                continue
            try:
                codes[name] = process.wait(timeout)
            except subprocess.TimeoutExpired:
                process.terminate()
                try:
                    codes[name] = process.wait(5.0)
                except subprocess.TimeoutExpired:
                    process.kill()
                    codes[name] = process.wait()
        return codes

    def stop_all(self) -> dict:
        """Stop every node this pipeline started (extra ones included), the plant after the
        others and the recorder last, so it records their final diagnostics."""
        codes = self.stop([n for n in self.processes if n not in ('recorder', self.plant)])
        codes.update(self.stop([self.plant]))
        time.sleep(0.3)  # let the recorder take the final diagnostics
        codes.update(self.stop(['recorder']))
        return codes


def pipeline_env(domain_id: int | None = None) -> dict:
    env = dict(os.environ)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = env.get('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    if domain_id is not None:
        env['ROS_DOMAIN_ID'] = str(domain_id)
    elif 'ROS_DOMAIN_ID' not in env:
        env['ROS_DOMAIN_ID'] = str(random.randint(1, 100))
    env.setdefault('PYTHONUNBUFFERED', '1')
    env.setdefault(DDS_PROFILE_VARIABLE, str(config_file(DDS_PROFILE)))  # docs/decisions.md, 38
    return env


class _NoAliases(yaml.SafeDumper):
    """rcl's parameter-file parser refuses YAML aliases: a value shared by two nodes is written twice."""

    def ignore_aliases(self, data) -> bool:
        return True


def run_pipeline(run_dir: Path, estimator: str = DEFAULT_FILTER, mode: str = 'lockstep',
                 params_file: Path | None = None, duration: float | None = None,
                 real_time_factor: float | None = None, domain_id: int | None = None,
                 extra: dict | None = None, timeout: float | None = None,
                 storage: str = 'mcap', namespace: str = '', on_start=None, pin_cpus: bool = True,
                 scheduling: str | None = None, plant: str = 'cw', live_view: bool = False,
                 single_process: bool = False, sensor: str = 'position', listeners: dict | None = None,
                 scenario: str = 'rendezvous') -> dict:
    """Run the loop to completion; return {'exit_codes', 'wall_s', 'bag', 'scheduling' (the
    policy the nodes got, see :attr:`Pipeline.scheduling`)}. Raises RuntimeError
    when a node dies or the run does not finish in time (logs are in <run_dir>/logs).
    ``on_start(pipeline)``, if given, is called once the node processes are started.
    ``sensor``: position (Table 6) or a suite of scenario_nodes.parameter_tables.sensor_suites
    that ``scenario`` flies (scenario_nodes.registry.SCENARIOS; the approach: by_range, angles_far).
    ``scheduling``: batch | normal; None: by mode (SCHEDULING_BY_MODE). ``listeners``: subscribers
    besides the pipeline's, topic -> count (a probe), counted in each node's hold. ``scenario``:
    rendezvous (Table 6, the parameter file's) or one of scenario_nodes.parameter_tables.scenarios
    (approach: the CW plant node on the nonlinear truth, the position sensor, the sensors by
    range or the angles-only far suite, until contact or an abort; its duration, the scenario's
    limit, unless ``duration`` is given)."""
    scheduling = scheduling or SCHEDULING_BY_MODE.get(mode, 'normal')
    run_dir.mkdir(parents=True, exist_ok=True)
    params_file = params_file or config_file('rendezvous.yaml')
    plant_values = {'mode': mode, 'exit_when_done': True}
    if duration is not None:
        plant_values['duration'] = float(duration)
    if real_time_factor is not None:
        plant_values['real_time_factor'] = float(real_time_factor)
    if plant == 'basilisk':
        plant_values['cache_dir'] = str(run_dir / 'cache')  # nothing of the run outside its folder
    plant_name = registry.plant_node(plant)
    overrides = {plant_name: plant_values, 'estimator': {'filter_type': estimator},
                 'recorder': {'output': str(run_dir / 'bag'), 'storage': storage}}
    registry.check_scenario(scenario, plant, sensor)
    # as the files load: the scenario's over the parameter file, the sensor suite's over both
    if scenario != 'rendezvous':
        for name, values in scenarios()[scenario].items():
            overrides.setdefault(name, {}).update({k: v for k, v in values.items()
                                                   if not (name == plant_name and k in plant_values)})
    if sensor != 'position':
        for name, values in sensor_suites()[sensor].items():
            overrides.setdefault(plant_name if name == 'cw_plant' else name, {}).update(values)
    for name, values in (extra or {}).items():
        overrides.setdefault(name, {}).update(values)
    pipeline = Pipeline(run_dir, params_file, overrides, pipeline_env(domain_id), namespace=namespace,
                        pin_cpus=pin_cpus, scheduling=scheduling, plant=plant, live_view=live_view,
                        single_process=single_process, sensor=sensor, listeners=listeners)
    sim_duration = float(duration if duration is not None else overrides[plant_name].get('duration', 360.0))
    if timeout is None:
        timeout = 120.0 + (sim_duration / (real_time_factor or 1.0) if mode == 'realtime' else sim_duration)
    started = time.monotonic()
    pipeline.start()
    if on_start is not None:
        on_start(pipeline)
    try:
        plant_process = pipeline.processes[pipeline.plant]
        while plant_process.poll() is None:
            broken = pipeline.failed()
            if broken:
                raise RuntimeError(f'node(s) {broken} exited early; see {run_dir / "logs"}')
            if time.monotonic() - started > timeout:
                raise RuntimeError(f'the run did not finish within {timeout:.0f} s; see {run_dir / "logs"}')
            time.sleep(0.05)
        if plant_process.returncode != 0:
            raise RuntimeError(f'{pipeline.plant} exited with {plant_process.returncode}; see {run_dir / "logs"}')
        time.sleep(0.3)  # the estimator's last step and the controller's answer
    finally:
        codes = pipeline.stop_all()
    return {'exit_codes': codes, 'wall_s': time.monotonic() - started, 'bag': run_dir / 'bag',
            'scheduling': pipeline.scheduling}


def _child_setup(cpus: set[int] | None, lower_priority: bool, batch: bool = False):
    """What a node process does before it starts: take its CPUs (see :func:`cpu_plan`; threads
    it creates later inherit them and the scheduling policy); run under SCHED_BATCH with
    ``batch``, else SCHED_OTHER (not whatever the caller runs under); and, for the recorder,
    yield to the loop (nice 10: its KEEP_ALL reader queues hold what it has not written yet, and
    it drains them before closing).

    SCHED_BATCH (no privileges needed) keeps the kernel from preempting a running node each
    time it wakes a subscriber: the woken process runs when the CPU is free, so a node ends its
    callback (the estimator publishes three messages per step) instead of being switched out
    after every publish. Five processes on two CPUs otherwise spent about a third of their CPU
    time switching; CPU per step fell by about a third (docs/performance.md)."""
    def setup():
        if cpus:
            os.sched_setaffinity(0, cpus)
        if lower_priority:
            os.nice(10)
        policy = BATCH if batch else NORMAL
        if policy is not None:
            try:
                os.sched_setscheduler(0, policy, os.sched_param(0))
            except OSError:  # refused (some containers): Pipeline notices, says so and records it
                pass
    return setup


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


def sensor_lines(sensors: dict) -> list[str]:
    """One line per sensor of a summary (bag_tools.sensor_reports): its reports against its
    schedule, and its gaps, told apart into those the sensor says it did not publish and lost."""
    lines = []
    for topic, v in sensors.items():
        line = (f"{topic} {v['recorded']}/{v['expected']} reports ({v['measured']} measured, "
                f"{v['not_measured']} nothing measured; a sample every {v['period_s']:g} s)")
        if not v['gaps']:
            lines.append(line + ': no gap')
            continue
        shown = ', '.join(f'{a:g}' if a == b else f'{a:g}-{b:g}' for a, b in v['gaps'][:3])
        more = f' and {len(v["gaps"]) - 3} more' if len(v['gaps']) > 3 else ''
        lost = f"{v['lost']} lost" if v['lost'] else 'none lost'
        lines.append(line + f": {v['missing']} missing in {len(v['gaps'])} gap(s) at {shown} s{more} "
                     f"({v['not_published']} not published by the sensor, {lost})")
    return lines


def print_summary(summary: dict, run_dir: Path) -> None:
    rmse = summary['rmse_last_60s']
    print(f"\n{summary['estimator']}: {summary['sim_time_s']:.1f} s simulated in "
          f"{summary['wall_time_s']:.2f} s wall (real-time factor {summary['real_time_factor']:.0f}), "
          f"{summary['steps']} steps")
    print(f"  final range        {summary['final_range_m']:.4f} m")
    contact = summary.get('contact')
    if contact:  # docs/decisions.md, 49
        print(f"  within 1 m at {contact['t_s']:.1f} s: closing {contact['closing_speed_m_s']:.3f} m/s, "
              f"{contact['axis_offset_m']:.3f} m off the docking axis (LVLH x)")
    print('  RMSE last 60 s     ' + '  '.join(f'{k} {rmse[k]:.2e} m' for k in ('x', 'y', 'z')))
    print('                     ' + '  '.join(f'{k} {rmse[k]:.2e} m/s' for k in ('vx', 'vy', 'vz')))
    print(f"  spikes             {summary['spikes_total']} ({100 * summary['spike_fraction']:.2f}% of "
          f"N x steps, N = {summary['neurons']})")
    print(f"  control timeouts   {summary['control_timeouts']}    measurements rejected "
          f"{summary['measurements_rejected']}")
    counts = ', '.join(f"{k} {v['recorded']}/{v['published']}" for k, v in summary['messages'].items())
    print(f'  recorded/published {counts}')
    for i, line in enumerate(sensor_lines(summary.get('sensors', {}))):
        print(('  sensors            ' if i == 0 else ' ' * 21) + line)
    print(f'  files              {run_dir}/summary.json, {run_dir}/bag, {run_dir}/report.md')


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='snn_demo', description=__doc__.split('\n\n')[0])
    parser.add_argument('--estimator', default=DEFAULT_FILTER, choices=tuple(FILTER_KINDS),
                        help=f'filter_type of the estimator (default {DEFAULT_FILTER})')
    parser.add_argument('--mode', default='lockstep', choices=('lockstep', 'realtime'))
    parser.add_argument('--plant', default='cw', choices=tuple(registry.plants()),
                        help='truth: cw (the model the filters use) or basilisk (J2, thrust limits)')
    parser.add_argument('--sensor', default='position', choices=('position', *sensor_suites()),
                        help="position (Table 6's partial position) or a sensor suite (docs/sensors.md); "
                             'by_range (relative GPS, LIDAR, docking camera) or angles_far (far camera, LIDAR, '
                             'docking camera) with --scenario approach')
    parser.add_argument('--scenario', default='rendezvous', choices=list(registry.SCENARIOS),
                        help='rendezvous (Table 6, 360 s) or approach (5 km behind on V-bar to contact through the '
                             'holds, nonlinear truth and filter model, 1 s steps, until contact or abort)')
    parser.add_argument('--results', type=Path, help='approach: also write its results file here '
                        '(make demo SCENARIO=approach: results/approach_ros.json)')
    parser.add_argument('--params-file', type=Path, help='parameter file (default: config/rendezvous.yaml)')
    parser.add_argument('--duration', type=float, help='simulated seconds (default: from the file, 360)')
    parser.add_argument('--real-time-factor', type=float, help='realtime mode speed-up (default 1)')
    parser.add_argument('--name', help='run folder name (default: <estimator>_<mode>_<date-time>)')
    parser.add_argument('--runs-dir', type=Path, default=Path('runs'))
    parser.add_argument('--domain-id', type=int, help='ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID or random)')
    parser.add_argument('--storage', default='mcap', choices=('mcap', 'sqlite3'))
    parser.add_argument('--no-report', action='store_true', help='skip the figures')
    parser.add_argument('--cpu-affinity', default='auto', choices=('auto', 'off'),
                        help='auto: estimator and controller on one CPU, the other nodes on the rest')
    parser.add_argument('--scheduling', choices=SCHEDULING,
                        help='Linux policy of the node processes: batch (SCHED_BATCH, no wakeup '
                             'preemption: faster lockstep) or normal (SCHED_OTHER: a woken node '
                             'runs sooner, a lower latency tail in realtime); default: batch in '
                             'lockstep, normal in realtime')
    parser.add_argument('--live-view', action='store_true',
                        help='also start live_view: Foxglove at ws://localhost:8765, MarkerArray on markers')
    parser.add_argument('--cpu-wake-latency-us', type=int, metavar='US',
                        help='every node holds the kernel CPU latency request at US microseconds '
                             '(/dev/cpu_dma_latency, root only; 0: idle CPUs poll, the realtime p99 '
                             'of docs/performance.md; costs CPU time); sets SNN_CPU_WAKE_LATENCY_US')
    parser.add_argument('--single-process', action='store_true',
                        help='every node in one process and one executor (default: one process '
                             'per node); same results, see docs/performance.md')
    args = parser.parse_args(argv)
    if args.cpu_wake_latency_us is not None:
        if args.cpu_wake_latency_us < 0:
            parser.error('--cpu-wake-latency-us must be >= 0')
        os.environ['SNN_CPU_WAKE_LATENCY_US'] = str(args.cpu_wake_latency_us)  # the nodes inherit it
    sensor = '' if args.sensor == 'position' else f'_{args.sensor}'
    scenario = '' if args.scenario == 'rendezvous' else f'{args.scenario}_'
    name = args.name or (f"{scenario}{args.estimator}{sensor}_{args.mode}_"
                         f"{datetime.now().strftime('%Y%m%d-%H%M%S')}")
    run_dir = (args.runs_dir / name).resolve()
    if run_dir.exists():
        parser.error(f'{run_dir} exists; choose another --name')
    params_file = config_file(str(args.params_file)) if args.params_file else None
    print(f'snn_demo: {args.scenario}, {args.estimator} on {args.sensor} in {args.mode} mode -> {run_dir}')
    signal.signal(signal.SIGTERM, _raise_interrupt)  # so the nodes are stopped on SIGTERM too
    try:
        result = run_pipeline(run_dir, args.estimator, args.mode, params_file, args.duration,
                              args.real_time_factor, args.domain_id, storage=args.storage,
                              pin_cpus=args.cpu_affinity == 'auto', scheduling=args.scheduling,
                              plant=args.plant, live_view=args.live_view,
                              single_process=args.single_process, sensor=args.sensor, scenario=args.scenario)
    except (RuntimeError, ValueError) as error:
        print(f'snn_demo: {error}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print('snn_demo: interrupted; nodes stopped', file=sys.stderr)
        return 130
    from snn_tools.bags.data import read_bag, summarize
    run = read_bag(result['bag'])
    summary = summarize(run)
    summary['exit_codes'] = result['exit_codes']
    # how the processes ran: the real-time factor depends on it
    summary['scheduling'], summary['cpu_affinity'] = result['scheduling'], args.cpu_affinity
    summary['single_process'] = args.single_process
    (run_dir / 'summary.json').write_text(json.dumps(summary, indent=2) + '\n')
    if not args.no_report:
        from snn_tools.bags.report import write_report
        write_report([run_dir], run_dir)
    print_summary(summary, run_dir)
    if args.scenario == 'approach':
        from snn_tools.bags.approach import ros_lines, ros_results
        approach = ros_results(run, wall_time=result['wall_s'])
        approach.update(estimator=args.estimator, mode=args.mode, run=os.path.relpath(run_dir))
        for path in [run_dir / 'approach.json'] + ([args.results] if args.results else []):
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(approach, indent=1) + '\n')
        print('\n'.join(ros_lines(approach)))
        print(f"  results            {run_dir / 'approach.json'}" + (f', {args.results}' if args.results else ''))
        return 0 if approach['success'] else 3
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
