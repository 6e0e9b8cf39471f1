"""The paper's experiments in one command: Monte-Carlo tables, figures and REPORT.md.

``snn_experiments [--experiment NAME ...] [--runs 100] [--out results]`` writes
``<out>/<experiment>.json``, PNG figures and ``<out>/REPORT.md`` with our numbers beside the
paper's. Two readings of the paper's "average RMSE" are reported for every table:

* ``rmse``: ordinary RMSE over the final window, sqrt(mean over runs and time of e^2);
* ``mean_error``: the time average over the window of |mean over runs of e(t)|, which
  cancels zero-mean noise and is the only reading that reaches the paper's mm-level numbers.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from snn_estimator.estimators import make_estimator
from snn_estimator.simulation import SimulationResult, rendezvous_scenario, simulate, van_der_pol_scenario

VDP_STATES = ('x1', 'x2')
CW_STATES = ('x', 'y', 'z', 'vx', 'vy', 'vz')
#: Filters in every Monte-Carlo table, default preset first, then the literal network.
TABLE_FILTERS = ('ekf', 'emsif', 'snn_ekf', 'snn_emsif', 'esif', 'snn_emsif_star')
AS_PUBLISHED_FILTERS = ('ekf', 'emsif', 'snn_ekf', 'snn_emsif')
#: Rows with R_hat read as a per-sample variance (Eq. 5-6 then use R_hat dt; README, Decisions).
PER_SAMPLE_FILTERS = ('ekf', 'emsif', 'snn_ekf', 'snn_emsif')
NEURON_COUNTS = tuple(range(50, 501, 50))
RUNTIME_COUNTS = (50, 100, 300)

#: Numbers printed in the paper (Tables 2-5, 7; Sec. 3.1.2 for Fig. 7).
PAPER = {
    'vdp_nominal': {'table': 2, 'rmse': {
        'ekf': {'x1': 0.0166, 'x2': 0.0144}, 'emsif': {'x1': 0.0016, 'x2': 0.0020},
        'snn_ekf': {'x1': 0.0310, 'x2': 0.0338}, 'snn_emsif': {'x1': 0.0043, 'x2': 0.0046}}},
    'vdp_process_noise': {'table': 3, 'rmse': {
        'ekf': {'x1': 0.6785, 'x2': 0.6093}, 'emsif': {'x1': 0.0016, 'x2': 0.0022},
        'snn_ekf': {'x1': 0.6511, 'x2': 0.6100}, 'snn_emsif': {'x1': 0.0031, 'x2': 0.0036}}},
    'vdp_measurement_noise': {'table': 4, 'rmse': {
        'ekf': {'x1': 1.4599, 'x2': 1.3204}, 'emsif': {'x1': 0.0015, 'x2': 0.0019},
        'snn_ekf': {'x1': 1.5529, 'x2': 1.4307}, 'snn_emsif': {'x1': 0.0037, 'x2': 0.0051}}},
    'runtime': {'table': 5, 'ms_per_step': {
        'snn_ekf': {'50': 0.214, '100': 0.300, '300': 0.875},
        'snn_emsif': {'50': 0.219, '100': 0.320, '300': 0.890},
        'snn_emsif_star': {'50': 0.175, '100': 0.285, '300': 0.850}},
        'platform': 'MATLAB 2020b, Intel Core i7-6700HQ'},
    'rendezvous': {'table': 7, 'rmse': {
        'snn_ekf': {'x': 0.0157, 'y': 0.0501, 'z': 0.0342,
                    'vx': 1.5169e-04, 'vy': 5.4087e-04, 'vz': 3.9759e-04},
        'snn_emsif': {'x': 0.0013, 'y': 0.0012, 'z': 0.0013,
                      'vx': 9.2758e-05, 'vy': 1.4348e-04, 'vz': 9.8731e-05}}},
    'spikes': {'figure': 7, 'filter': 'snn_emsif', 'neurons': 100, 'steps': 2000,
               'spikes': 34342, 'fraction': 0.17},
}

VDP_CASES = {
    'vdp_nominal': {},
    'vdp_process_noise': {'process_noise_scale': 0.1},      # Q_hat = 0.1 Q
    'vdp_measurement_noise': {'measurement_noise_scale': 10.0},  # R_hat = 10 R
}
EXPERIMENTS = ('vdp_nominal', 'vdp_process_noise', 'vdp_measurement_noise', 'vdp_neurons',
               'rendezvous', 'rendezvous_printed_cw', 'spike_rules', 'runtime')
SPIKE_RULE_RUNS = 20


class Progress:
    """A one-line progress bar on stderr (silent when quiet)."""

    def __init__(self, quiet: bool = False):
        self.quiet = quiet
        self.interactive = sys.stderr.isatty()  # a log file gets one line per item instead
        self.label = ''
        self.total = 1
        self._last = -1

    def start(self, label: str, total: int):
        self.label, self.total, self._last = label, max(total, 1), -1
        self.update(0)

    def update(self, done: int):
        if self.quiet:
            return
        percent = int(100 * done / self.total)
        if not self.interactive:
            if percent >= 100 and self._last < 100:
                self._last = 100
                sys.stderr.write(f'  {self.label}: done\n')
            return
        if percent != self._last:
            self._last = percent
            bar = '#' * (percent // 4)
            sys.stderr.write(f'\r  {self.label:<44} [{bar:<25}] {percent:3d}%')
            if percent >= 100:
                sys.stderr.write('\n')
            sys.stderr.flush()


def summarise(result: SimulationResult, states) -> dict:
    """The JSON record of one filter: both readings, spike fraction, extras."""
    record = {
        'rmse': dict(zip(states, map(float, result.rmse()))),
        'mean_error': dict(zip(states, map(float, result.mean_error()))),
        'spike_fraction': result.spike_fraction,
        'wall_time_s': round(result.wall_time, 3),
    }
    if result.scenario.name == 'rendezvous':
        record['final_range_m'] = {'median': float(np.median(result.final_range())),
                                   'max': float(result.final_range().max())}
    if result.capped_steps:
        record['capped_steps'] = int(result.capped_steps)
    return record


def run_table(scenario_factory, changes: dict, runs: int, progress: Progress, label: str):
    """All filters of one table; returns (records, results kept for figures)."""
    records, results = {}, {}
    groups = (('default', TABLE_FILTERS, {}), ('as_published', AS_PUBLISHED_FILTERS, {}),
              ('per_sample_R', PER_SAMPLE_FILTERS, {'measurement_noise_units': 'per_sample'}))
    for label_suffix, kinds, units in groups:
        preset = 'as_published' if label_suffix == 'as_published' else 'default'
        scenario = scenario_factory(preset, **units, **changes)
        for kind in kinds:
            key = kind if label_suffix == 'default' else f'{kind}@{label_suffix}'
            progress.start(f'{label}: {key}', scenario.steps)
            result = simulate(scenario, kind, runs=runs, on_step=progress.update)
            progress.update(scenario.steps)
            states = CW_STATES if scenario.name == 'rendezvous' else VDP_STATES
            records[key] = summarise(result, states)
            if label_suffix == 'default':
                results[kind] = result
    return records, results


def _vdp_factory(preset, **changes):
    return van_der_pol_scenario(preset, **changes)


def _rendezvous_factory(preset, **changes):
    return rendezvous_scenario(preset, **changes)


def _printed_cw_factory(preset, **changes):
    return rendezvous_scenario(preset, cw_model='as_published', **changes)


def experiment_vdp_table(name: str, runs: int, out: Path, progress: Progress) -> dict:
    records, results = run_table(_vdp_factory, VDP_CASES[name], runs, progress, name)
    from . import figures
    figures.rmse_histories(results, VDP_STATES, out / f'{name}_rmse.png',
                           f'Van der Pol, {name.split("_", 1)[1].replace("_", " ")}: RMSE over {runs} runs')
    if name == 'vdp_nominal':
        figures.tracking(results, VDP_STATES, out / 'vdp_nominal_tracking.png',
                         'Van der Pol, one run: estimates and errors with 3-sigma bounds (Fig. 2)')
        single = simulate(van_der_pol_scenario(), 'snn_emsif', runs=1)
        figures.raster(single, out / 'vdp_spike_raster.png',
                       'SNN-EMSIF spike raster, Van der Pol, one run (Fig. 7)')
        records['snn_emsif']['single_run_spikes'] = int(single.spikes_per_step.sum())
        records['snn_emsif']['single_run_spike_fraction'] = single.spike_fraction
    return {'experiment': name, 'runs': runs, 'filters': records, 'paper': PAPER[name]}


def experiment_vdp_neurons(runs: int, out: Path, progress: Progress) -> dict:
    """Fig. 6: delta_x = sqrt(d_x1^2 + d_x2^2) (Eq. 29) over the last 10 s versus N."""
    sweep = {'neurons': list(NEURON_COUNTS)}
    records = {}
    for preset in ('default', 'as_published'):
        for kind in ('snn_ekf', 'snn_emsif'):
            key = kind if preset == 'default' else f'{kind}@as_published'
            series = {'rmse_norm': [], 'mean_error_norm': [], 'spike_fraction': []}
            for neurons in NEURON_COUNTS:
                scenario = van_der_pol_scenario(preset, neuron_count=neurons)
                progress.start(f'vdp_neurons: {key} N={neurons}', scenario.steps)
                result = simulate(scenario, kind, runs=runs, on_step=progress.update)
                progress.update(scenario.steps)
                series['rmse_norm'].append(float(np.linalg.norm(result.rmse())))
                series['mean_error_norm'].append(float(np.linalg.norm(result.mean_error())))
                series['spike_fraction'].append(result.spike_fraction)
                if neurons == 100:
                    records[key] = summarise(result, VDP_STATES)
            sweep[key] = series
    from . import figures
    figures.neuron_sweep(sweep, out / 'vdp_neurons.png')
    return {'experiment': 'vdp_neurons', 'runs': runs, 'filters': records, 'sweep': sweep,
            'paper': {'figure': 6, 'note': 'plotted only; no numbers printed'}}


def experiment_rendezvous(name: str, runs: int, out: Path, progress: Progress) -> dict:
    factory = _rendezvous_factory if name == 'rendezvous' else _printed_cw_factory
    records, results = run_table(factory, {}, runs, progress, name)
    from . import figures
    figures.tracking(results, CW_STATES, out / f'{name}_tracking.png',
                     'Rendezvous, one run: estimates and errors with 3-sigma bounds (Fig. 9-10)')
    figures.rmse_histories(results, CW_STATES, out / f'{name}_rmse.png',
                           f'Rendezvous: RMSE over {runs} runs (Fig. 11)')
    paper = PAPER['rendezvous'] if name == 'rendezvous' else {
        'note': 'not in the paper: filters and LQR use the CW matrix printed as Eq. 41, truth is standard CW'}
    return {'experiment': name, 'runs': runs, 'filters': records, 'paper': paper}


def experiment_spike_rules(runs: int, out: Path, progress: Progress) -> dict:
    """SNN-EMSIF on the rendezvous with each spike rule, scaled and literal network (not in the
    paper, which does not say how simultaneous threshold crossings are resolved)."""
    runs = min(runs, SPIKE_RULE_RUNS)
    records = {}
    for preset in ('default', 'as_published'):
        scenario = rendezvous_scenario(preset)
        for rule in ('greedy', 'one_per_step', 'all_above'):
            key = rule if preset == 'default' else f'{rule}@as_published'
            progress.start(f'spike_rules: {key}', scenario.steps)
            config = scenario.estimator.replace(spike_rule=rule)
            result = simulate(scenario, 'snn_emsif', runs=runs, config=config, on_step=progress.update)
            progress.update(scenario.steps)
            records[key] = summarise(result, CW_STATES)
    return {'experiment': 'spike_rules', 'runs': runs, 'filters': records,
            'paper': {'note': 'not in the paper'}}


def time_steps(estimator, zs, us, dt) -> float:
    """Median wall time of one ``step`` in microseconds over a recorded input sequence."""
    samples = np.empty(len(zs))
    clock = time.perf_counter
    for k in range(len(zs)):
        start = clock()
        estimator.step(zs[k], us[k], dt)
        samples[k] = clock() - start
    return float(np.median(samples) * 1e6)


def experiment_runtime(runs: int, out: Path, progress: Progress) -> dict:
    """Table 5: us per step of one filter instance on the Van der Pol problem (N = 50, 100, 300)."""
    scenario = van_der_pol_scenario()
    truth = simulate(scenario, 'emsif', runs=1)
    rng = np.random.default_rng(0)
    zs = truth.truth[0, :-1, :1] + math.sqrt(0.1) * rng.standard_normal((scenario.steps, 1))
    us = np.zeros((scenario.steps, 1))
    records = {}
    progress.start('runtime', len(RUNTIME_COUNTS))
    for index, neurons in enumerate(RUNTIME_COUNTS):
        for kind in ('snn_ekf', 'snn_emsif', 'snn_emsif_star', 'ekf', 'emsif'):
            config = scenario.estimator.replace(neuron_count=neurons)
            estimator = make_estimator(kind, config, scenario.model)
            time_steps(estimator, zs[:50], us[:50], scenario.dt)  # compile and warm up
            best = math.inf
            for _ in range(3):
                estimator.reset()
                best = min(best, time_steps(estimator, zs, us, scenario.dt))
            records.setdefault(kind, {'us_per_step': {}})['us_per_step'][str(neurons)] = round(best, 2)
        progress.update(index + 1)
    return {'experiment': 'runtime', 'runs': 1, 'filters': records, 'paper': PAPER['runtime'],
            'note': 'median over the 2000 steps of one Van der Pol run, best of 3 repetitions'}


def run(name: str, runs: int, out: Path, progress: Progress) -> dict:
    if name in VDP_CASES:
        return experiment_vdp_table(name, runs, out, progress)
    if name == 'vdp_neurons':
        return experiment_vdp_neurons(runs, out, progress)
    if name in ('rendezvous', 'rendezvous_printed_cw'):
        return experiment_rendezvous(name, runs, out, progress)
    if name == 'runtime':
        return experiment_runtime(runs, out, progress)
    if name == 'spike_rules':
        return experiment_spike_rules(runs, out, progress)
    raise ValueError(f'unknown experiment {name!r}; choose from {", ".join(EXPERIMENTS)}')


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog='snn_experiments', description="Run the paper's experiments; write JSON, PNG and REPORT.md.")
    parser.add_argument('--experiment', '-e', action='append', choices=EXPERIMENTS,
                        help='experiment to run (repeatable; default: all)')
    parser.add_argument('--runs', type=int, default=100, help='Monte-Carlo runs (default 100)')
    parser.add_argument('--out', type=Path, default=Path('results'), help='output folder')
    parser.add_argument('--quiet', action='store_true', help='no progress bar')
    args = parser.parse_args(argv)
    if args.runs < 1:
        parser.error('--runs must be >= 1')
    args.out.mkdir(parents=True, exist_ok=True)
    progress = Progress(args.quiet)
    for name in args.experiment or EXPERIMENTS:
        started = time.perf_counter()
        data = run(name, args.runs, args.out, progress)
        data['wall_time_s'] = round(time.perf_counter() - started, 1)
        (args.out / f'{name}.json').write_text(json.dumps(data, indent=2) + '\n')
        print(f'{name}: {args.out / (name + ".json")} ({data["wall_time_s"]} s)')
    from .report_md import write_report
    report = write_report(args.out)
    print(f'report: {report}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
