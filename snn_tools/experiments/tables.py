"""The paper's experiments and ours in one command: Monte-Carlo tables, figures and REPORT.md.

``snn_experiments [--experiment NAME ...] [--runs 100] [--workers 2 | --scheduler ADDR] [--out results]``

Every Monte-Carlo table is a campaign (snn_tools.campaign.run): one spec per table under
config/campaigns/, run on Dask like any user's sweep, its cells kept under
``<out>/campaigns/<name>/`` (so an interrupted ``make experiments`` resumes). The rows are then
written as ``<out>/<experiment>.json`` and ``<out>/REPORT.md`` with our numbers beside the
paper's. Two readings of the paper's "average RMSE" are reported for every table:

* ``rmse``: ordinary RMSE over the final window, sqrt(mean over runs and time of e^2);
* ``mean_error``: the time average over the window of |mean over runs of e(t)|, which
  cancels zero-mean noise and is the only reading that reaches the paper's mm-level numbers.

Figures (one run's tracking, RMSE against time) come from a direct simulation of
``FIGURE_RUNS`` runs of the same scenarios and go to ``<out>/figures/`` (committed with the
report, within :data:`FIGURE_BUDGET_BYTES`); the runtime table (Table 5), Fig. 2's transient
metrics and the rendezvous neuron loss are computed directly on the core.
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

from snn_estimator.config import silenced_neurons
from snn_estimator.filters.estimators import TWIN_OF, make_estimator
from snn_estimator.sim.scenarios import far_range_scenario, rendezvous_scenario, van_der_pol_scenario
from snn_estimator.sim.simulate import simulate
from snn_tools.campaign.cells import run_cell
from snn_tools.campaign.run import CampaignProgress, dask_client, run_campaign
from snn_tools.campaign.spec import load_spec, validate
from snn_tools.experiments.paper_metrics import median_metrics
from snn_tools.progress import track

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
    # Sec. 3.1, the text on Fig. 2(c): error of x1 (read off the text, not a table)
    'vdp_transients': {'figure': 2, 'x1': {
        'msif': {'enter_3sigma_s': 2.0, 'zero_crossing_s': 2.5, 'overshoot': 0.2, 'settle_s': 5.0},
        'kalman': {'enter_3sigma_s': 2.0, 'overshoot': 1.8, 'settle_s': 15.0}},
        'note': 'EMSIF/SNN-EMSIF enter the bound at 2 s, cross zero at 2.5 s, overshoot ~0.2, settle by '
                '5 s; EKF/SNN-EKF enter at the same time, overshoot ~1.8, stay outside the bound until '
                '10 s and settle after 15 s (x2: "almost the same")'},
}
#: Experiment -> the campaign spec of its table (config/campaigns/<name>.yaml), in report order.
TABLES = ('vdp_nominal', 'vdp_process_noise', 'vdp_measurement_noise', 'vdp_neurons', 'vdp_silencing',
          'rendezvous', 'rendezvous_printed_cw', 'spike_rules', 'rendezvous_dispersed', 'rendezvous_plants',
          'far_range', 'constant_gain')
#: Computed directly on the core (no campaign): Fig. 2's metrics, neuron loss mid-run, Table 5.
DIRECT = ('vdp_transients', 'rendezvous_silencing', 'runtime')
EXPERIMENTS = TABLES + DIRECT
RUNTIME_COUNTS = (50, 100, 300, 500)
#: Runs stepped together when timing the network's own cost per run and step (Table 5).
RUNTIME_BATCH = 100
#: Runs behind each figure, Fig. 2's metrics and the Fig. 6 coding error (the tables use the spec's runs).
FIGURE_RUNS = 20
#: The committed figures (results/figures/) stay below this total.
FIGURE_BUDGET_BYTES = 4_000_000
FIGURE_DPI = 72
#: How a grid value away from the spec's first one is written after the filter (kind@label).
LABELS = {('preset', 'as_published'): 'as_published', ('measurement_noise_units', 'per_sample'): 'per_sample_R',
          ('plant', 'basilisk'): 'basilisk', ('gain_schedule', 'steady_state'): 'steady_state',
          ('initial_state_dispersion', True): 'dispersed', ('truth_noise', 'held_sample'): 'held_noise',
          ('network_drive', 'nonlinear'): 'f_drive'}
#: The Van der Pol readings (docs/decisions.md, 4 and 13): truth noise x R_hat units x network drive.
READINGS = [dict(truth_noise=t, measurement_noise_units=r, network_drive=d)
            for t in ('spectral_density', 'held_sample') for r in ('spectral_density', 'per_sample')
            for d in ('linearized', 'nonlinear')]
#: The zero-gain row of Table 7: an EKF that all but ignores its measurements (R_hat x 1e9).
ZERO_GAIN = {'measurement_noise_scale': 5e9}


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
        if row.get('peak_thrust_max') is not None:
            out['peak_thrust_m_s2'] = {'median': row['peak_thrust_median'], 'max': row['peak_thrust_max']}
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
    if name in ('rendezvous', 'rendezvous_dispersed'):  # Table 7's setup needs no measurements
        fixed = {**{key: values[0] for key, values in spec.grid.items()}, **spec.settings}
        data['filters']['ekf@zero_gain'] = record(run_cell(spec.scenario, 'ekf', {**fixed, **ZERO_GAIN},
                                                           spec.runs, spec.seed, spec.runs_per_task), states)
    if name == 'vdp_neurons':
        data['coding_error'] = coding_error_sweep(spec.grid)
    if name == 'vdp_silencing':
        data['ratios'] = silencing_ratios(data['filters'])
    return data


def coding_error_sweep(grid: dict) -> dict:
    """Fig. 6's missing trend: what the network adds to its twin, the RMSE of x_snn - x_twin over
    the last 10 s (same seeds, so the same truth and measurements), against N, from
    FIGURE_RUNS runs per point; and the spiking filter's own delta_x beside it."""
    sweep = {'neurons': list(grid['neuron_count']), 'runs': FIGURE_RUNS}
    for preset in grid.get('preset', ['default']):
        for truth_noise in grid.get('truth_noise', ['spectral_density']):
            base = van_der_pol_scenario(preset)
            base = dataclasses.replace(base, truth_noise=truth_noise)
            for kind in ('snn_ekf', 'snn_emsif'):
                twin = simulate(base, TWIN_OF[kind], runs=FIGURE_RUNS)
                label = _coding_label(kind, preset, truth_noise)
                series = sweep.setdefault(label, {'coding_rmse_norm': [], 'twin_rmse_norm': []})
                window = twin.window()
                for neurons in grid['neuron_count']:
                    scenario = dataclasses.replace(base, estimator=base.estimator.replace(neuron_count=neurons))
                    spiking = simulate(scenario, kind, runs=FIGURE_RUNS)
                    gap = spiking.estimate[:, window] - twin.estimate[:, window]
                    series['coding_rmse_norm'].append(float(np.linalg.norm(np.sqrt(np.mean(gap ** 2, axis=(0, 1))))))
                    series['twin_rmse_norm'].append(float(np.linalg.norm(twin.rmse())))
    return sweep


def _coding_label(kind: str, preset: str, truth_noise: str) -> str:
    labels = (['as_published'] if preset == 'as_published' else []) + (
        ['held_noise'] if truth_noise == 'held_sample' else [])
    return kind + ('@' + ','.join(labels) if labels else '')


def silencing_ratios(filters: dict) -> dict:
    """Ordinary RMSE with a fraction of the neurons silenced / intact, per filter, reading and
    state (the intact row is the one without ``silenced_fraction`` in its key)."""
    ratios = {}
    for key, rec in filters.items():
        kind, _, labels = key.partition('@')
        parts = labels.split(',') if labels else []
        fraction = [p for p in parts if p.startswith('silenced_fraction=')]
        if not fraction:
            continue
        rest = [p for p in parts if not p.startswith('silenced_fraction=')]
        intact = filters.get(kind + ('@' + ','.join(rest) if rest else ''))
        if intact:
            ratios[key] = {s: rec['rmse'][s] / intact['rmse'][s] for s in rec['rmse']}
    return ratios


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


def figure_folder(out: Path) -> Path:
    """Where the report's figures go: a tracked folder beside REPORT.md."""
    return out / 'figures'


def draw(name: str, out: Path) -> dict:
    """Figures of one table from FIGURE_RUNS runs per filter; extra numbers for the JSON."""
    from snn_tools import figures
    figures.DPI = FIGURE_DPI
    folder = figure_folder(out)
    extra = {}
    if name == 'vdp_neurons':
        figures.neuron_sweep(json.loads((out / f'{name}.json').read_text()), folder / 'vdp_neurons.png')
        return extra
    if name not in FIGURE_SCENARIOS:
        return extra
    factory, kinds, title = FIGURE_SCENARIOS[name]
    scenario = factory()
    results = {kind: simulate(scenario, kind, runs=FIGURE_RUNS) for kind in kinds}
    states = scenario.model.state_names
    figures.rmse_histories(results, states, folder / f'{name}_rmse.png',
                           f'{title}: RMSE over {FIGURE_RUNS} runs')
    if name in ('vdp_nominal', 'rendezvous', 'rendezvous_dispersed', 'far_range'):
        figures.tracking(results, states, folder / f'{name}_tracking.png',
                         f'{title}, one run: estimates and errors with 3-sigma bounds')
    if name == 'vdp_nominal':
        single = simulate(van_der_pol_scenario(), 'snn_emsif', runs=1)
        figures.raster(single, folder / 'vdp_spike_raster.png', 'SNN-EMSIF spike raster, Van der Pol, one run (Fig. 7)')
        extra = {'single_run_spikes': int(single.spikes_per_step.sum()),
                 'single_run_spike_fraction': single.spike_fraction}
    return extra


def figure_budget(out: Path) -> dict:
    """Total size of the committed figures against FIGURE_BUDGET_BYTES."""
    sizes = {path.name: path.stat().st_size for path in sorted(figure_folder(out).glob('*.png'))}
    total = sum(sizes.values())
    if total > FIGURE_BUDGET_BYTES:
        print(f'warning: figures take {total / 1e6:.1f} MB, above the {FIGURE_BUDGET_BYTES / 1e6:.0f} MB budget')
    return {'files': len(sizes), 'bytes': total, 'budget_bytes': FIGURE_BUDGET_BYTES}


# ---------------------------------------------------------------- computed directly on the core
def experiment_vdp_transients() -> dict:
    """Fig. 2's claims (Sec. 3.1) in numbers: per reading and filter, the medians over
    FIGURE_RUNS runs of when the error enters +-3 sigma, first crosses zero, how far it
    overshoots and when it settles (snn_tools.experiments.paper_metrics), for x1 and x2."""
    readings = {}
    for reading in READINGS:
        label = reading_label(reading)
        scenario = van_der_pol_scenario(measurement_noise_units=reading['measurement_noise_units'],
                                        network_drive=reading['network_drive'])
        scenario = dataclasses.replace(scenario, truth_noise=reading['truth_noise'])
        rows = {}
        for kind in ('ekf', 'emsif', 'snn_ekf', 'snn_emsif'):
            result = simulate(scenario, kind, runs=FIGURE_RUNS)
            rows[kind] = {state: median_metrics(result, i) for i, state in enumerate(scenario.model.state_names)}
        readings[label] = {'settings': reading, 'filters': rows}
    return {'experiment': 'vdp_transients', 'runs': FIGURE_RUNS, 'readings': readings,
            'paper': PAPER['vdp_transients'],
            'note': 'medians over the runs; settle = |e| stays below 5 % of |e(0)| (0.1 for x1 and x2)'}


def reading_label(reading: dict) -> str:
    """'Q dt truth, R_hat density, A(x)x drive' and the like, for tables."""
    return ', '.join(('Q dt truth' if reading['truth_noise'] == 'spectral_density' else 'Q dt^2 truth',
                      'R_hat density' if reading['measurement_noise_units'] == 'spectral_density'
                      else 'R_hat per sample',
                      'A(x)x drive' if reading['network_drive'] == 'linearized' else 'f(x) drive'))


def experiment_rendezvous_silencing(runs: int | None) -> dict:
    """Neuron loss in the rendezvous (Decision 12): 50 % of the neurons silenced at t = 100 s,
    the same runs (seeds) with and without; ordinary RMSE over the last 60 s per state."""
    runs = runs or 100
    scenario = rendezvous_scenario()
    at_step = int(round(100.0 / scenario.dt))
    neurons = scenario.estimator.neuron_count
    dead = silenced_neurons(neurons, 0, 0.5)
    out = {}
    for kind in ('snn_ekf', 'snn_emsif'):
        intact = simulate(scenario, kind, runs=runs)
        silenced = simulate(scenario, kind, runs=runs, events={at_step: lambda estimator: estimator.silence(dead)})
        states = scenario.model.state_names
        out[kind] = {'rmse_intact': dict(zip(states, intact.rmse().tolist())),
                     'rmse_silenced': dict(zip(states, silenced.rmse().tolist())),
                     'ratio': dict(zip(states, (silenced.rmse() / intact.rmse()).tolist())),
                     'final_range_median_m': {'intact': float(np.median(intact.final_range())),
                                              'silenced': float(np.median(silenced.final_range()))},
                     'peak_thrust_m_s2': float(np.abs(intact.control).max())}
    return {'experiment': 'rendezvous_silencing', 'runs': runs, 'silenced': len(dead), 'neurons': neurons,
            'at_s': 100.0, 'filters': out, 'paper': {'note': 'the paper silences neurons in the Van der Pol '
                                                              'Monte Carlo only (Sec. 3.1.2), without figures'}}


def time_steps(estimator, zs, us, dt) -> float:
    """Median wall time of one ``step`` in microseconds over a recorded input sequence."""
    samples = np.empty(len(zs))
    clock = time.perf_counter
    for k in range(len(zs)):
        start = clock()
        estimator.step(zs[k], us[k], dt)
        samples[k] = clock() - start
    return float(np.median(samples) * 1e6)


def time_batched(estimator, zs, us, dt, runs) -> float:
    """Median wall time of one batched ``step`` per run, in microseconds."""
    zb = np.repeat(zs[:, None, :], runs, axis=1)
    ub = np.repeat(us[:, None, :], runs, axis=1)
    return time_steps(estimator, zb, ub, dt) / runs


def experiment_runtime() -> dict:
    """Table 5: us per step on the Van der Pol problem against N. Two readings: one call for one
    filter instance (what a node pays: dominated by the per-call overhead), and the cost per run
    of a batch of RUNTIME_BATCH runs stepped in one call (the network's own work, which grows
    with N); the network's cost is the spiking filter's batched figure minus its twin's."""
    scenario = van_der_pol_scenario()
    truth = simulate(scenario, 'emsif', runs=1)
    rng = np.random.default_rng(0)
    zs = truth.truth[0, :-1, :1] + math.sqrt(0.1) * rng.standard_normal((scenario.steps, 1))
    us = np.zeros((scenario.steps, 1))
    records = {}
    for neurons in RUNTIME_COUNTS:
        for kind in ('snn_ekf', 'snn_emsif', 'snn_emsif_star', 'ekf', 'emsif', 'esif'):
            config = scenario.estimator.replace(neuron_count=neurons)
            record_ = records.setdefault(kind, {'us_per_step': {}, 'us_per_run_step_batched': {}})
            estimator = make_estimator(kind, config, scenario.model)
            time_steps(estimator, zs[:50], us[:50], scenario.dt)  # compile and warm up
            best = math.inf
            for _ in range(3):
                estimator.reset()
                best = min(best, time_steps(estimator, zs, us, scenario.dt))
            record_['us_per_step'][str(neurons)] = round(best, 2)
            batch = make_estimator(kind, config, scenario.model, runs=RUNTIME_BATCH)
            time_batched(batch, zs[:20], us[:20], scenario.dt, RUNTIME_BATCH)
            best = math.inf
            for _ in range(2):
                batch.reset()
                best = min(best, time_batched(batch, zs[:500], us[:500], scenario.dt, RUNTIME_BATCH))
            record_['us_per_run_step_batched'][str(neurons)] = round(best, 3)
    for kind in ('snn_ekf', 'snn_emsif', 'snn_emsif_star'):
        twin = records[TWIN_OF[kind]]
        records[kind]['network_us_per_run_step'] = {
            n: round(v - twin['us_per_run_step_batched'][n], 3)
            for n, v in records[kind]['us_per_run_step_batched'].items()}
    return {'experiment': 'runtime', 'runs': 1, 'batch': RUNTIME_BATCH, 'filters': records, 'paper': PAPER['runtime'],
            'note': 'single call: median over the 2000 steps of one Van der Pol run, best of 3; batched: '
                    f'median per run over 500 steps of {RUNTIME_BATCH} runs in one call, best of 2 '
                    '(network = spiking minus its non-spiking twin, both batched)'}


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
        elif name == 'vdp_transients':
            _write(args.out, name, experiment_vdp_transients())
        elif name == 'rendezvous_silencing':
            _write(args.out, name, experiment_rendezvous_silencing(args.runs))
        elif name in tables:
            extra = draw(name, args.out)
            if extra:
                data = json.loads((args.out / f'{name}.json').read_text())
                data['filters']['snn_emsif'].update(extra)
                _write(args.out, name, data)
    budget = figure_budget(args.out)
    print(f"figures: {budget['files']} files, {budget['bytes'] / 1e6:.2f} MB "
          f"(budget {budget['budget_bytes'] / 1e6:.0f} MB) in {figure_folder(args.out)}")
    from snn_tools.experiments.report import write_report
    print(f'report: {write_report(args.out)}')
    from snn_tools.campaign.page import write_experiments_page  # i27: one interactive page of every table
    print(f'interactive page: {write_experiments_page(args.out, tables)}')
    return 0


def _write(out: Path, name: str, data: dict) -> None:
    path = out / f'{name}.json'
    path.write_text(json.dumps(data, indent=2) + '\n')
    print(f'{name}: {path}' + (f" ({data['wall_time_s']} s)" if 'wall_time_s' in data else ''))


if __name__ == '__main__':
    sys.exit(main())
