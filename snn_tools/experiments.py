"""The paper's experiments and ours in one command: Monte-Carlo tables, figures and REPORT.md.

``snn_experiments [--experiment NAME ...] [--runs 100] [--workers 2 | --scheduler ADDR] [--out results]``

Every Monte-Carlo table is a campaign (snn_tools.campaign): one spec per table under
config/campaigns/, run on Dask like any user's sweep, its cells kept under
``<out>/campaigns/<name>/`` (so an interrupted ``make experiments`` resumes). The rows are then
written as ``<out>/<experiment>.json`` and ``<out>/REPORT.md`` with our numbers beside the
paper's. Two readings of the paper's "average RMSE" are reported for every table:

* ``rmse``: ordinary RMSE over the final window, sqrt(mean over runs and time of e^2);
* ``mean_error``: the time average over the window of |mean over runs of e(t)|, which
  cancels zero-mean noise and is the only reading that reaches the paper's mm-level numbers.

Figures (one run's tracking, RMSE against time) come from a direct simulation of
``FIGURE_RUNS`` runs of the same scenarios; the runtime table (Table 5) is timed directly.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from snn_estimator.estimators import make_estimator
from snn_estimator.simulation import far_range_scenario, rendezvous_scenario, simulate, van_der_pol_scenario

from .campaign import CampaignProgress, dask_client, load_spec, run_campaign, validate
from .progress import track

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
#: Experiment -> the campaign spec of its table (config/campaigns/<name>.yaml), in report order.
TABLES = ('vdp_nominal', 'vdp_process_noise', 'vdp_measurement_noise', 'vdp_neurons', 'rendezvous',
          'rendezvous_printed_cw', 'spike_rules', 'rendezvous_dispersed', 'rendezvous_plants', 'far_range',
          'constant_gain')
EXPERIMENTS = TABLES + ('runtime',)
RUNTIME_COUNTS = (50, 100, 300)
#: Runs behind each figure (the tables use the spec's runs).
FIGURE_RUNS = 20
#: How a grid value away from the spec's first one is written after the filter (kind@label).
LABELS = {('preset', 'as_published'): 'as_published', ('measurement_noise_units', 'per_sample'): 'per_sample_R',
          ('plant', 'basilisk'): 'basilisk', ('gain_schedule', 'steady_state'): 'steady_state',
          ('initial_state_dispersion', True): 'dispersed'}


def row_key(row: dict, grid: dict, skip=()) -> str:
    """``kind`` for the spec's first grid point, ``kind@label`` for the others, e.g.
    ``snn_emsif@as_published,per_sample_R`` or ``ekf@basilisk,process_noise_scale=10000``."""
    labels = []
    for name, values in grid.items():
        if name in skip or row[name] == values[0]:
            continue
        labels.append(LABELS.get((name, row[name]), f'{name}={row[name]:g}' if isinstance(row[name], float)
                                 else f'{name}={row[name]}'))
    return row['filter'] + ('@' + ','.join(labels) if labels else '')


def record(row: dict, states) -> dict:
    """The JSON record of one table row: both readings, spike fraction and, where measured,
    final range, delta-v, saturation and the covariance checks."""
    out = {'rmse': {s: row[f'rmse_{s}'] for s in states},
           'mean_error': {s: row[f'mean_error_{s}'] for s in states},
           'spike_fraction': row.get('spike_fraction'), 'wall_time_s': round(row['wall_time_s'], 3)}
    if row.get('final_range_median') is not None:
        out['final_range_m'] = {'median': row['final_range_median'], 'max': row['final_range_max']}
        out['delta_v_m_s'] = row['delta_v_mean']
        out['saturated_steps'] = row['saturated_steps_mean']
    if row.get('nees_verdict'):
        out['consistency'] = {name: {'average': row[f'{name}_average'], 'fraction_inside':
                                     row[f'{name}_fraction_inside'], 'verdict': row[f'{name}_verdict']}
                              for name in ('nees', 'nis')}
    if row.get('capped_steps'):
        out['capped_steps'] = int(row['capped_steps'])
    return out


def run_table(name: str, runs: int | None, out: Path, client, quiet: bool) -> dict:
    """The campaign of one table, then its JSON (figures are drawn by :func:`draw`)."""
    spec = load_spec(f'campaigns/{name}.yaml')
    if runs is not None:
        spec = dataclasses.replace(spec, runs=runs, runs_per_task=min(spec.runs_per_task, runs))
    validate(spec)
    progress = CampaignProgress(quiet=quiet)
    progress.say(f'{name}: {len(spec.cells())} cells x {spec.runs} runs')
    outcome = run_campaign(spec, out / 'campaigns' / name, client, progress)
    states = [key[len('rmse_'):] for key in outcome.rows[0] if key.startswith('rmse_')]
    data = {'experiment': name, 'runs': spec.runs, 'description': spec.description.strip(),
            'spec': f'config/campaigns/{name}.yaml', 'paper': PAPER.get(name, {'note': 'not in the paper'})}
    if name == 'vdp_neurons':
        data['sweep'] = neuron_sweep(outcome.rows, spec.grid)
        rows = [row for row in outcome.rows if row['neuron_count'] == 100]
        data['filters'] = {row_key(row, spec.grid, skip=('neuron_count',)): record(row, states) for row in rows}
    elif name == 'spike_rules':  # one filter: rows named by their rule, as the paper's text names them
        data['filters'] = {row_key(row, spec.grid, skip=('spike_rule',)).replace(row['filter'], row['spike_rule'], 1):
                           record(row, states) for row in outcome.rows}
    else:
        data['filters'] = {row_key(row, spec.grid): record(row, states) for row in outcome.rows}
    return data


def neuron_sweep(rows: list[dict], grid: dict) -> dict:
    """Fig. 6: delta_x = sqrt(d_x1^2 + d_x2^2) (Eq. 29) over the last 10 s against N."""
    sweep = {'neurons': list(grid['neuron_count'])}
    for row in rows:
        key = row_key(row, grid, skip=('neuron_count',))
        series = sweep.setdefault(key, {'rmse_norm': [], 'mean_error_norm': [], 'spike_fraction': []})
        series['rmse_norm'].append(math.hypot(row['rmse_x1'], row['rmse_x2']))
        series['mean_error_norm'].append(math.hypot(row['mean_error_x1'], row['mean_error_x2']))
        series['spike_fraction'].append(row['spike_fraction'])
    return sweep


#: Experiment -> (scenario of its figures, filters drawn, title); the others have no figure.
FIGURE_SCENARIOS = {
    'vdp_nominal': (lambda: van_der_pol_scenario(), ('ekf', 'emsif', 'snn_ekf', 'snn_emsif'),
                    'Van der Pol, nominal'),
    'vdp_process_noise': (lambda: van_der_pol_scenario(process_noise_scale=0.1),
                          ('ekf', 'emsif', 'snn_ekf', 'snn_emsif'), 'Van der Pol, Q_hat = 0.1 Q'),
    'vdp_measurement_noise': (lambda: van_der_pol_scenario(measurement_noise_scale=10.0),
                              ('ekf', 'emsif', 'snn_ekf', 'snn_emsif'), 'Van der Pol, R_hat = 10 R'),
    'rendezvous': (lambda: rendezvous_scenario(), ('ekf', 'emsif', 'snn_ekf', 'snn_emsif'), 'Rendezvous'),
    'rendezvous_printed_cw': (lambda: rendezvous_scenario(cw_model='as_published'),
                              ('ekf', 'emsif', 'snn_ekf', 'snn_emsif'), 'Rendezvous, printed CW'),
    'rendezvous_dispersed': (lambda: rendezvous_scenario(initial_state_dispersion=True),
                             ('ekf', 'emsif', 'emsif_weighted', 'snn_ekf', 'snn_emsif', 'snn_emsif_weighted'),
                             'Rendezvous from a dispersed start'),
    'rendezvous_plants': (lambda: rendezvous_scenario(plant='basilisk', initial_state_dispersion=True),
                          ('ekf', 'emsif_weighted', 'snn_ekf', 'snn_emsif_weighted'),
                          'Rendezvous, Basilisk truth (J2), dispersed start'),
    'far_range': (lambda: far_range_scenario(), ('ekf', 'emsif', 'emsif_weighted', 'snn_ekf', 'snn_emsif_weighted'),
                  'Far-range V-bar approach, Basilisk truth (J2)'),
}


def draw(name: str, out: Path) -> dict:
    """Figures of one table from FIGURE_RUNS runs per filter; extra numbers for the JSON."""
    from . import figures
    extra = {}
    if name == 'vdp_neurons':
        figures.neuron_sweep(json.loads((out / f'{name}.json').read_text())['sweep'], out / 'vdp_neurons.png')
        return extra
    if name not in FIGURE_SCENARIOS:
        return extra
    factory, kinds, title = FIGURE_SCENARIOS[name]
    scenario = factory()
    results = {kind: simulate(scenario, kind, runs=FIGURE_RUNS) for kind in kinds}
    states = scenario.model.state_names
    figures.rmse_histories(results, states, out / f'{name}_rmse.png',
                           f'{title}: RMSE over {FIGURE_RUNS} runs')
    if name in ('vdp_nominal', 'rendezvous', 'rendezvous_dispersed', 'far_range'):
        figures.tracking(results, states, out / f'{name}_tracking.png',
                         f'{title}, one run: estimates and errors with 3-sigma bounds')
    if name == 'vdp_nominal':
        single = simulate(van_der_pol_scenario(), 'snn_emsif', runs=1)
        figures.raster(single, out / 'vdp_spike_raster.png', 'SNN-EMSIF spike raster, Van der Pol, one run (Fig. 7)')
        extra = {'single_run_spikes': int(single.spikes_per_step.sum()),
                 'single_run_spike_fraction': single.spike_fraction}
    return extra


def time_steps(estimator, zs, us, dt) -> float:
    """Median wall time of one ``step`` in microseconds over a recorded input sequence."""
    samples = np.empty(len(zs))
    clock = time.perf_counter
    for k in range(len(zs)):
        start = clock()
        estimator.step(zs[k], us[k], dt)
        samples[k] = clock() - start
    return float(np.median(samples) * 1e6)


def experiment_runtime() -> dict:
    """Table 5: us per step of one filter instance on the Van der Pol problem (N = 50, 100, 300)."""
    scenario = van_der_pol_scenario()
    truth = simulate(scenario, 'emsif', runs=1)
    rng = np.random.default_rng(0)
    zs = truth.truth[0, :-1, :1] + math.sqrt(0.1) * rng.standard_normal((scenario.steps, 1))
    us = np.zeros((scenario.steps, 1))
    records = {}
    for neurons in RUNTIME_COUNTS:
        for kind in ('snn_ekf', 'snn_emsif', 'snn_emsif_star', 'ekf', 'emsif'):
            config = scenario.estimator.replace(neuron_count=neurons)
            estimator = make_estimator(kind, config, scenario.model)
            time_steps(estimator, zs[:50], us[:50], scenario.dt)  # compile and warm up
            best = math.inf
            for _ in range(3):
                estimator.reset()
                best = min(best, time_steps(estimator, zs, us, scenario.dt))
            records.setdefault(kind, {'us_per_step': {}})['us_per_step'][str(neurons)] = round(best, 2)
    return {'experiment': 'runtime', 'runs': 1, 'filters': records, 'paper': PAPER['runtime'],
            'note': 'median over the 2000 steps of one Van der Pol run, best of 3 repetitions'}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog='snn_experiments', description="Run the paper's experiments and ours; write JSON, PNG and REPORT.md.")
    parser.add_argument('--experiment', '-e', action='append', choices=EXPERIMENTS,
                        help='experiment to run (repeatable; default: all)')
    parser.add_argument('--runs', type=int, help="Monte-Carlo runs per cell (default: each spec's, 100)")
    parser.add_argument('--workers', type=int, default=2, help='local Dask workers (default 2)')
    parser.add_argument('--scheduler', help='address of a running dask scheduler instead of local workers')
    parser.add_argument('--out', type=Path, default=Path('results'), help='output folder')
    parser.add_argument('--quiet', action='store_true', help='no progress bar')
    args = parser.parse_args(argv)
    if args.runs is not None and args.runs < 1:
        parser.error('--runs must be >= 1')
    args.out.mkdir(parents=True, exist_ok=True)
    names = args.experiment or list(EXPERIMENTS)
    tables = [name for name in names if name in TABLES]
    if tables:
        with dask_client(args.workers, args.scheduler) as client:
            for name in tables:
                started = time.perf_counter()
                data = run_table(name, args.runs, args.out, client, args.quiet)
                data['wall_time_s'] = round(time.perf_counter() - started, 1)
                _write(args.out, name, data)
    for name in track(names, 'experiments', 'figures'):  # i27: progress on a terminal
        if name == 'runtime':
            _write(args.out, name, experiment_runtime())
        elif name in tables:
            extra = draw(name, args.out)
            if extra:
                data = json.loads((args.out / f'{name}.json').read_text())
                data['filters']['snn_emsif'].update(extra)
                _write(args.out, name, data)
    from .report_md import write_report
    print(f'report: {write_report(args.out)}')
    from .campaign_page import write_experiments_page  # i27: one interactive page of every table
    print(f'interactive page: {write_experiments_page(args.out, tables)}')
    return 0


def _write(out: Path, name: str, data: dict) -> None:
    path = out / f'{name}.json'
    path.write_text(json.dumps(data, indent=2) + '\n')
    print(f'{name}: {path}' + (f" ({data['wall_time_s']} s)" if 'wall_time_s' in data else ''))


if __name__ == '__main__':
    sys.exit(main())
