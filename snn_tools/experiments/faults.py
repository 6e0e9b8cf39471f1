"""snn_faults: the fault matrix. Each node of the loop (plant, sensor, controller, estimator,
recorder) is killed (SIGKILL, restarted after ``--outage`` wall s) or stopped (SIGSTOP, SIGCONT
after ``--outage`` s) at ``--at`` simulated s of a realtime run at ``--real-time-factor``; per
cell: the final range, crashes, NaN in the bag, which peers reported the outage, safe-mode
steps, what the report of the bag says. What ``make faults`` runs.

``python -m snn_tools.experiments.faults [--cells controller:kill,sensor:stop] [--out results/faults.json]``
writes the JSON, a markdown table beside it (``faults.md``) and the table into
docs/robustness.md between its fault-matrix markers. The machine it runs on matters (realtime
x10 on a loaded machine is late): the JSON records the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import time
from pathlib import Path

import numpy as np

from scenario_nodes import registry
from snn_tools.bags.data import read_bag, summarize
from snn_tools.paths import SOURCE_ROOT, config_file, replace_between_markers
from snn_tools.run.demo import Pipeline, pipeline_env

#: Matrix rows: the node a fault hits -> its process name in the pipeline.
TARGETS = {'plant': 'cw_plant', 'sensor': 'position_sensor', 'controller': 'lqr_controller',
           'estimator': 'estimator', 'recorder': 'recorder'}
FAULTS = ('kill', 'stop')
#: The truth cannot come back mid-flight: a restarted plant starts the scenario again.
COMES_BACK = {'plant': False, 'sensor': True, 'controller': True, 'estimator': True, 'recorder': True}
#: The peers that must notice each node's outage: (status name, diagnostics key).
WATCHERS = {'plant': [('position_sensor', 'peer.truth')],
            'sensor': [('estimator', 'peer.measurement'), ('lqr_controller', 'peer.measurement')],
            'controller': [('cw_plant', 'peer.control'), ('estimator', 'peer.control')],
            'estimator': [('lqr_controller', 'peer.estimate')],
            'recorder': []}
#: What each node publishes: where the bag shows when it was back (None: nothing of its own).
OUTPUTS = {'plant': 'truth', 'sensor': 'measurement', 'controller': 'control', 'estimator': 'estimate',
           'recorder': None}
FINAL_RANGE_LIMIT = 0.1  # m
#: Simulated s per run: a 10 s wall outage at x10 is 100 s simulated, a restart under load
#: 5-15 s of wall time more (50-150 s simulated), the drift meanwhile ~10 m, and the LQR
#: (slowest closed-loop pole 0.04 1/s, with overshoot) needs ~2 minutes to close in from there.
DURATION = 480.0
ROBUSTNESS_DOC = SOURCE_ROOT / 'docs' / 'robustness.md'
BEGIN, END = '<!-- fault matrix: begin (python -m snn_tools.experiments.faults) -->', '<!-- fault matrix: end -->'


def all_cells() -> list[tuple[str, str]]:
    return [(node, fault) for node in TARGETS for fault in FAULTS]


def parse_cells(text: str | None) -> list[tuple[str, str]]:
    """'controller:kill,sensor:stop' -> [('controller', 'kill'), ...]; None: every cell."""
    if not text:
        return all_cells()
    cells = []
    for item in text.split(','):
        node, _, fault = item.strip().partition(':')
        if node not in TARGETS or fault not in FAULTS:
            raise ValueError(f"cell {item!r}: expected <{'|'.join(TARGETS)}>:<{'|'.join(FAULTS)}>")
        cells.append((node, fault))
    return cells


def _wait_for_start(run_dir: Path, timeout: float) -> float:
    """Wall time the plant started the scenario (its log says so)."""
    log = run_dir / 'logs' / 'cw_plant.log'
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if log.exists() and 'starting the scenario' in log.read_text():
            return time.monotonic()
        time.sleep(0.05)
    raise RuntimeError(f'the scenario did not start within {timeout:.0f} s; see {run_dir / "logs"}')


def inject(pipeline: Pipeline, node: str, fault: str, outage: float) -> None:
    """The fault: kill -9 and start again after ``outage`` s, or SIGSTOP for ``outage`` s."""
    name = TARGETS[node]
    process = pipeline.processes[name]
    if fault == 'stop':
        os.kill(process.pid, signal.SIGSTOP)
        time.sleep(outage)
        os.kill(process.pid, signal.SIGCONT)
        return
    process.send_signal(signal.SIGKILL)
    process.wait(10)
    time.sleep(outage)
    overrides = {'output': str(pipeline.run_dir / 'bag_restarted')} if node == 'recorder' else None
    pipeline.start_node(name, registry.node(name).module, overrides, log_name=f'{name}_restarted')


def run_cell(node: str, fault: str, out: Path, domain_id: int, duration: float, at: float, outage: float,
             real_time_factor: float) -> dict:
    """One cell of the matrix: its run folder under ``out`` and its result."""
    run_dir = out / f'{node}_{fault}'
    overrides = {'cw_plant': {'mode': 'realtime', 'real_time_factor': real_time_factor, 'duration': duration,
                              'exit_when_done': True},
                 'recorder': {'output': str(run_dir / 'bag')}}
    pipeline = Pipeline(run_dir, config_file(), overrides, pipeline_env(domain_id))
    started = time.monotonic()
    crashed = []
    try:
        pipeline.start()
        begun = _wait_for_start(run_dir, 120.0)
        time.sleep(max(0.0, at / real_time_factor - (time.monotonic() - begun)))
        inject(pipeline, node, fault, outage)
        deadline = time.monotonic() + 120.0 + 2 * duration / real_time_factor
        while pipeline.processes['cw_plant'].poll() is None and time.monotonic() < deadline:
            crashed = sorted(set(crashed) | {n for n in pipeline.failed()})
            time.sleep(0.1)
        time.sleep(0.5)
    finally:
        codes = pipeline.stop_all()
    crashed = sorted(set(crashed) | {n for n, code in codes.items() if code not in (0, None)})
    return evaluate(node, fault, run_dir, crashed, time.monotonic() - started, at)


def outage(run, node: str, at: float) -> tuple[float | None, float | None]:
    """(first stamp back, simulated s without the node's output) of the longest gap in its
    topic that ends after ``at`` - 5 s; (None, None) when it has no topic of its own or no gap
    (a stopped node that published every stamp once it went on)."""
    topic = OUTPUTS[node]
    if topic is None:
        return None, None
    t = np.unique(getattr(run, f'{topic}_t'))
    gaps = np.where(t[1:] > at - 5.0, np.diff(t), 0.0)
    if not len(gaps) or gaps.max() < 0.25:  # no gap: it caught up on every stamp (or has none)
        return None, None
    i = int(np.argmax(gaps))
    return float(t[i + 1]), float(gaps[i])


def peers_reported(run, watchers) -> dict:
    """Whether each watcher's diagnostics showed the peer WARN or ERROR at some point."""
    return {f'{name}:{key}': any(values.get(key) in ('WARN', 'ERROR') for _, values in run.diagnostics.get(name, ()))
            for name, key in watchers}


def evaluate(node: str, fault: str, run_dir: Path, crashed: list, wall: float, at: float = 100.0) -> dict:
    """The cell's result from its bag (the restarted recorder's bag when the recorder was killed)."""
    bag = run_dir / ('bag_restarted' if node == 'recorder' and fault == 'kill' else 'bag')
    comes_back = fault == 'stop' or COMES_BACK[node]  # a stopped plant resumes its flight
    result = {'node': node, 'fault': fault, 'run': str(run_dir), 'wall_s': round(wall, 1), 'crashed': crashed,
              'comes_back': comes_back}
    try:
        run = read_bag(bag)
    except Exception as error:  # a bag that cannot be read is the cell's result, not a crash of the tool
        result.update(error=f'{type(error).__name__}: {error}', passed=False)
        return result
    summary = summarize(run)
    finite = all(np.all(np.isfinite(a)) for a in (run.truth, run.estimate, run.control, run.estimate_variance))
    controller = run.last_diagnostics('lqr_controller')
    estimator = run.last_diagnostics('estimator')
    plant = run.last_diagnostics('cw_plant')
    back, gap = outage(run, node, at)
    result.update(
        back_at_s=back, outage_s=gap,
        final_range_m=summary['final_range_m'], steps=summary['steps'], nan_free=bool(finite),
        peers=peers_reported(run, WATCHERS[node]),
        safe_mode_steps=int(float(controller.get('safe_mode_steps', 0))),
        expired_control_steps=int(float(plant.get('expired_control_steps', 0))),
        control_timeouts=summary['control_timeouts'],
        reinitialisations=int(float(estimator.get('reinitialisations', 0))),
        reset_storms=int(float(estimator.get('reset_storms', 0))),
        restarts=summary['restarts'], recording_complete=summary['recording_complete'],
        gaps={k: len(v) for k, v in summary['gaps'].items()}, spike_fraction=summary['spike_fraction'])
    from snn_tools.bags.report import write_report
    try:
        write_report([bag], run_dir / 'report')
        result['report'] = str(run_dir / 'report' / 'report.md')
    except Exception as error:  # the report must read any bag: a failure here is a finding
        result['report_error'] = f'{type(error).__name__}: {error}'
    range_ok = not comes_back or summary['final_range_m'] < FINAL_RANGE_LIMIT
    result['passed'] = bool(not crashed and finite and range_ok and all(result['peers'].values())
                            and 'report_error' not in result)
    return result


def markdown(results: list[dict], meta: dict) -> str:
    lines = [f"Realtime x{meta['real_time_factor']:g}, {meta['duration']:g} s simulated, the fault at "
             f"{meta['at']:g} s, {meta['outage']:g} s wall outage (kill: then restarted; stop: then SIGCONT); "
             f"load average {meta['load_average']} on {meta['cpus']} CPUs (a shared machine: timings vary), "
             f"commit {meta.get('commit', 'unknown')}.", '',
             '| node | fault | final range [m] | back at [s] (outage) | crashed | NaN-free | peers reported | '
             'safe-mode steps | zero-thrust steps (expired) | re-inits | report | passed |',
             '|---|---|---|---|---|---|---|---|---|---|---|---|']
    for r in results:
        if 'error' in r:
            crashed = ', '.join(r['crashed']) or 'none'
            lines.append(f"| {r['node']} | {r['fault']} | - | - | {crashed} | - | - | - | - | - | {r['error']} | no |")
            continue
        peers = ', '.join(k.split(':')[0] for k, v in r['peers'].items() if v) or ('-' if not r['peers'] else 'none')
        final = f"{r['final_range_m']:.4f}" + ('' if r['comes_back'] else ' (scenario restarted)')
        back = ('-' if r.get('back_at_s') is None else f"{r['back_at_s']:.1f} ({r['outage_s']:.1f} s)")
        lines.append(
            f"| {r['node']} | {r['fault']} | {final} | {back} | {', '.join(r['crashed']) or 'none'} | "
            f"{'yes' if r['nan_free'] else 'NO'} | {peers} | {r['safe_mode_steps']} | {r['expired_control_steps']} | "
            f"{r['reinitialisations']} | {'read' if 'report' in r else r.get('report_error', '-')} | "
            f"{'yes' if r['passed'] else 'no'} |")
    return '\n'.join(lines) + '\n'


def write_results(results: list[dict], meta: dict, out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({'meta': meta, 'cells': results}, indent=2) + '\n')
    table = markdown(results, meta)
    out.with_suffix('.md').write_text(table)
    if out.resolve().parent == ROBUSTNESS_DOC.parents[1] / 'results':
        replace_between_markers(ROBUSTNESS_DOC, BEGIN, END, table)


def _commit() -> str:
    import subprocess
    try:
        return subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], cwd=Path(__file__).parent, text=True,
                              capture_output=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return 'unknown'


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='snn_faults', description=__doc__.split('\n\n')[0])
    parser.add_argument('--cells', help="e.g. 'controller:kill,sensor:stop' (default: all ten)")
    parser.add_argument('--out', type=Path, default=Path('results/faults.json'))
    parser.add_argument('--runs', type=Path, default=Path('runs/faults'), help='run folders (bags, logs, reports)')
    parser.add_argument('--duration', type=float, default=DURATION, help='simulated s per run')
    parser.add_argument('--at', type=float, default=100.0, help='simulated s at which the fault hits')
    parser.add_argument('--outage', type=float, default=10.0, help='wall s the node stays dead or stopped')
    parser.add_argument('--real-time-factor', type=float, default=10.0)
    parser.add_argument('--domain-id', type=int, default=None,
                        help='ROS_DOMAIN_ID of the runs (default: the environment)')
    args = parser.parse_args(argv)
    try:
        cells = parse_cells(args.cells)
    except ValueError as error:
        parser.error(str(error))
    domain = args.domain_id if args.domain_id is not None else int(os.environ.get('ROS_DOMAIN_ID', '0'))
    meta = {'real_time_factor': args.real_time_factor, 'duration': args.duration, 'at': args.at,
            'outage': args.outage, 'cpus': os.cpu_count(), 'load_average': round(os.getloadavg()[0], 1),
            'commit': _commit()}
    results = []
    for node, fault in cells:
        print(f'snn_faults: {node} {fault} ...', flush=True)
        result = run_cell(node, fault, args.runs, domain, args.duration, args.at, args.outage, args.real_time_factor)
        print(f"  final range {result.get('final_range_m', float('nan')):.4f} m, passed {result['passed']}", flush=True)
        results.append(result)
        write_results(results, meta, args.out)  # after each cell: a long run leaves what it did
    print(f'snn_faults: {args.out}, {args.out.with_suffix(".md")}')
    return 0 if all(r['passed'] for r in results) else 1


if __name__ == '__main__':
    raise SystemExit(main())
