"""``snn_neuromorphic``: the exported networks on neuromorphic terms.

For each filter it exports the constant-gain network to NIR, runs one closed-loop rendezvous
with our kernel (that network drives the LQR), replays its measurements and controls through
Brian2 built from the NIR file (snn_tools.neuromorphic.brian2_sim) and compares the two estimates; counts
the operations of every estimate from the run's spikes (snn_estimator.spiking.costs) and prices them
on published chips beside the CPU time measured here; compares the constant gain with the
time-varying one over a Monte Carlo. Writes ``<out>/neuromorphic.json``,
``<out>/neuromorphic.md`` and ``<out>/neuromorphic_costs.png`` (cost per estimate against N).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import nir
import numpy as np

from snn_estimator.filters.estimators import FILTER_KINDS, TWIN_OF, Estimator, make_estimator
from snn_estimator.sim.scenarios import rendezvous_scenario
from snn_estimator.sim.simulate import simulate
from snn_estimator.spiking.costs import CHIPS, FLOAT32_MAC_PJ, FLOAT32_MAC_SOURCE, CostModel, energy_pj
from snn_tools.experiments.tables import time_steps
from snn_tools.neuromorphic.brian2_sim import run_network
from snn_tools.neuromorphic.chip import run_all, synchronous_fixed_point, synchronous_markdown
from snn_tools.neuromorphic.local_rule import markdown as local_rule_markdown
from snn_tools.neuromorphic.local_rule import measure as measure_local_rule
from snn_tools.neuromorphic.nir_export import (
    NetworkArrays,
    constant_gain_estimator,
    network_arrays,
    network_graph,
)
from snn_tools.neuromorphic.reader_loop import markdown as norse_loop_markdown
from snn_tools.neuromorphic.recording import Recording, record_rendezvous, rmse  # noqa: F401 (the tables read them)
from snn_tools.progress import track

DEFAULT_FILTERS = ('snn_ekf', 'snn_emsif', 'snn_emsif_star', 'snn_emsif_weighted')
NEURON_COUNTS = tuple(range(50, 501, 50))
#: Brian2 sub-steps per 0.1 s sample: the greedy rule fires one spike per sub-step, so this
#: must exceed the spikes of any sample (at most ~130 on the rendezvous; a shortfall is counted
#: as saturated samples).
SUBSTEPS = 200
#: The continuous-time readings: (label, mode, rule, sub-steps, window) with window 'first' or
#: 'last' seconds of the run; 'last' starts from our network's state at that time.
READINGS = (
    ('continuous_greedy_first_10s', 'continuous', 'greedy', 1000, ('first', 10.0)),
    ('continuous_greedy_last_60s', 'continuous', 'greedy', 100, ('last', 60.0)),
    ('continuous_all_above_first_2s', 'continuous', 'all_above', 100, ('first', 2.0)),
)
#: Power assumed for the one busy CPU core when turning measured time into energy, W (not
#: measured: this container has no RAPL counters).
CPU_WATTS = 10.0


def reading_windows(scenario) -> list:
    """:data:`READINGS` as (label, mode, rule, sub-steps, first step, steps) for ``scenario``."""
    windows = []
    for label, mode, rule, substeps, (where, seconds) in READINGS:
        length = min(scenario.steps, round(seconds / scenario.dt))
        windows.append((label, mode, rule, substeps, 0 if where == 'first' else scenario.steps - length, length))
    return windows


class DenseNetwork:
    """The dense N x N formulation with held weights, in numpy, from the exported arrays: per
    step v = (1 - dt/tau) v + dt (Omega r + F_k z + F u), r decays, then the greedy rule with
    one Omega_f column per spike; x_hat = S D r. What a CPU does without our kernel's
    low-rank algebra (timed beside it)."""

    def __init__(self, net: NetworkArrays):
        self._net = net
        self._omega_f = net.omega_f
        self.v, self.r = net.initial_v.copy(), net.initial_r.copy()

    def step(self, z, u, dt: float) -> np.ndarray:
        net = self._net
        if dt != net.sample_period:
            raise ValueError(f'the network was exported for dt = {net.sample_period} s, got {dt}')
        self.v = self.v * (1.0 - dt / net.tau_v) + dt * (net.slow @ self.r + net.measurement @ z + net.control @ u)
        self.r *= 1.0 - dt / net.tau_r
        over = self.v - net.threshold
        best = int(np.argmax(over))
        while over[best] > 0.0:
            self.r[best] += net.train_jump[best]
            self.v += self._omega_f[:, best]
            over = self.v - net.threshold
            best = int(np.argmax(over))
        return net.decoder @ self.r


def independent_check(scenario, recording: Recording, net: NetworkArrays, substeps: int) -> dict:
    """Brian2 from the NIR file (``net``, as read back from it) over the recorded inputs against
    our estimate: the primary
    (sampled, greedy) comparison over the whole run and the continuous-time readings."""
    window = round(min(scenario.metric_window, scenario.duration) / scenario.dt)
    ours_rmse = rmse(recording.truth, recording.estimate, window)
    run = run_network(net, recording.zs, recording.us, mode='sampled', rule='greedy', substeps=substeps)
    theirs = rmse(recording.truth, run.estimate, window)
    record = {
        'independent_simulator': f'Brian2 {_version("brian2")} (numpy code generation) built from the NIR '
                                 f'file; mode sampled, greedy rule, {substeps} sub-steps per '
                                 f'{scenario.dt} s sample (dt = {run.brian_dt * 1e3:g} ms)',
        'independent_rmse_ratio': _ratio(np.linalg.norm(theirs[:3]), np.linalg.norm(ours_rmse[:3])),
        'independent_rmse_ratio_per_state': _round(theirs / ours_rmse),
        'independent_spike_ratio': _ratio(run.spikes_per_step.sum(), recording.raster.sum()),
        'independent_identical_spikes': bool(np.array_equal(run.raster, recording.raster)),
        'independent_max_estimate_difference': _round(np.abs(run.estimate - recording.estimate).max(axis=0)),
        'independent_saturated_samples': run.saturated_steps,
        'independent_wall_time_s': round(run.wall_time, 1),
        'rmse_ours': _round(ours_rmse), 'rmse_independent': _round(theirs),
        'readings': {},
    }
    for label, mode, rule, reading_substeps, start, length in reading_windows(scenario):
        v0, r0 = recording.snapshots[start]
        part = slice(start, start + length)
        reading = run_network(net, recording.zs[part], recording.us[part], mode=mode, rule=rule,
                              substeps=reading_substeps, initial_v=v0, initial_r=r0)
        truth, ours = recording.truth[start:start + length + 1], recording.estimate[start:start + length + 1]
        theirs, mine = rmse(truth, reading.estimate, length + 1), rmse(truth, ours, length + 1)
        record['readings'][label] = {
            'mode': mode, 'rule': rule, 'brian_dt_ms': reading.brian_dt * 1e3,
            'window_s': [round(start * scenario.dt, 3), round((start + length) * scenario.dt, 3)],
            'rmse_ratio': _ratio(np.linalg.norm(theirs[:3]), np.linalg.norm(mine[:3])),
            'rmse_ratio_per_state': _round(theirs / mine),
            'spike_ratio': _ratio(reading.spikes_per_step.sum(), recording.raster[part].sum()),
            'spikes': int(reading.spikes_per_step.sum()), 'spikes_ours': int(recording.raster[part].sum()),
            'mean_threshold_per_spike': _round([_mean_threshold(reading.raster, net.threshold),
                                                _mean_threshold(recording.raster[part], net.threshold)]),
            'wall_time_s': round(reading.wall_time, 1)}
    return record


def cost_record(estimator: Estimator, raster: np.ndarray, substeps: int) -> dict:
    """Operations and energy per estimate, averaged over the run's steps."""
    spikes = raster.sum(axis=1)
    model = CostModel.of(estimator)
    costs = model.step(spikes)
    time_varying = time_varying_model(model, estimator.kind)
    stepped_model = dataclasses.replace(model, ticks=substeps)
    stepped = stepped_model.step(spikes)
    return {
        'spikes_per_step': round(float(spikes.mean()), 3),
        'spike_fraction': round(float(spikes.mean() / estimator.neuron_count), 5),
        'synops_per_step': round(float(costs.synops.mean()), 1),
        'synops_per_spike': model.synops_per_spike, 'input_synops_per_step': model.input_synops,
        'neuron_updates_per_step': model.neuron_updates,
        'dense_macs_per_step': round(float(costs.dense_macs.mean()), 1),
        'nonspiking_macs_per_step': {'time_varying': time_varying.nonspiking_macs,
                                     'constant_gain': model.nonspiking_macs},
        'time_varying_host_macs_per_step': time_varying.host_macs_per_step,
        'energy_per_step_pj': {chip: round(float(energy_pj(costs, chip).mean()), 1) for chip in CHIPS},
        'float32_arithmetic_energy_per_step_pj': {
            'dense': round(float(costs.dense_macs.mean()) * FLOAT32_MAC_PJ, 1),
            'nonspiking_time_varying': round(time_varying.nonspiking_macs * FLOAT32_MAC_PJ, 1),
            'nonspiking_constant_gain': round(model.nonspiking_macs * FLOAT32_MAC_PJ, 1)},
        'time_stepped_chip': {
            'ticks_per_step': substeps, 'neuron_updates_per_step': stepped_model.neuron_updates,
            'energy_per_step_pj': {chip: round(float(energy_pj(stepped, chip).mean()), 1) for chip in CHIPS}},
    }


def time_varying_model(model: CostModel, kind: str) -> CostModel:
    """The cost model of ``kind`` with the paper's time-varying gain and its own covariance law."""
    return dataclasses.replace(model, constant_gain=False, covariance_law=FILTER_KINDS[kind].covariance)


def cpu_record(kind: str, config, scenario, recording: Recording, net: NetworkArrays, watts: float) -> dict:
    """Median wall time per step over the recorded inputs: our compiled kernel (constant and
    time-varying gain), the dense numpy network from the exported arrays, the non-spiking twin."""
    model, dt = scenario.model, scenario.dt
    zs, us = recording.zs, recording.us
    constant = config.replace(gain_schedule='steady_state')

    def best_of(make, passes=3):
        time_steps(make(), zs[:50], us[:50], dt)  # compile, warm caches
        return min(time_steps(make(), zs, us, dt) for _ in range(passes))

    record = {
        'compiled_us_per_step': best_of(lambda: make_estimator(kind, constant, model)),
        'compiled_time_varying_us_per_step': best_of(lambda: make_estimator(kind, config, model)),
        'dense_us_per_step': best_of(lambda: DenseNetwork(net), passes=1),
        'nonspiking_us_per_step': best_of(lambda: make_estimator(TWIN_OF[kind], config, model)),
    }
    record = {key: round(value, 2) for key, value in record.items()}
    dense = DenseNetwork(net)
    deviation = max(float(np.abs(dense.step(z, u, dt) - x).max())
                    for z, u, x in zip(zs, us, recording.estimate[1:], strict=True))
    record.update({
        'dense_max_estimate_difference': float(f'{deviation:.3g}'),
        'assumed_watts': watts, 'compiled_energy_per_step_pj': round(record['compiled_us_per_step'] * watts * 1e6, 0),
        'dense_energy_per_step_pj': round(record['dense_us_per_step'] * watts * 1e6, 0),
        'platform': f'{platform.processor() or platform.machine()}, Python {platform.python_version()}'})
    return record


def gain_schedule_comparison(kind: str, runs: int, duration: float) -> dict:
    """RMSE per state of the constant-gain network over the time-varying one, ``runs`` runs of
    ``duration`` s, with and without a dispersed initial estimate."""
    record = {}
    for label, dispersion in (('dispersed', True), ('undispersed', False)):
        scenario = dataclasses.replace(rendezvous_scenario(initial_state_dispersion=dispersion), duration=duration)
        varying = simulate(scenario, kind, runs=runs).rmse()
        constant = simulate(scenario, kind, runs=runs,
                            config=scenario.estimator.replace(gain_schedule='steady_state')).rmse()
        record[label] = {'rmse_ratio_per_state': _round(constant / varying), 'rmse_constant': _round(constant),
                         'rmse_time_varying': _round(varying), 'runs': runs}
    return record


def neuron_sweep(kind: str, scenario, counts, watts: float) -> dict:
    """Operations and energy per estimate against N (one closed-loop run per N)."""
    rows = []
    for neurons in track(counts, 'networks', 'neuron sweep'):
        config = scenario.estimator.replace(neuron_count=int(neurons))
        estimator = constant_gain_estimator(kind, config, scenario.model)
        recording = record_rendezvous(scenario, estimator)
        spikes = recording.raster.sum(axis=1)
        model = CostModel.of(estimator)
        costs, varying = model.step(spikes), time_varying_model(model, kind)
        time_steps(constant_gain_estimator(kind, config, scenario.model), recording.zs[:50],
                   recording.us[:50], scenario.dt)  # compile, warm caches
        compiled = time_steps(constant_gain_estimator(kind, config, scenario.model), recording.zs,
                              recording.us, scenario.dt)
        rows.append({'neurons': int(neurons), 'spikes_per_step': float(spikes.mean()),
                     'synops_per_step': float(costs.synops.mean()),
                     'dense_macs_per_step': float(costs.dense_macs.mean()),
                     'dense_time_varying_macs_per_step': float(varying.step(spikes).dense_macs.mean()),
                     'nonspiking_macs_per_step': model.nonspiking_macs,
                     'nonspiking_time_varying_macs_per_step': varying.nonspiking_macs,
                     'energy_per_step_pj': {chip: float(energy_pj(costs, chip).mean()) for chip in CHIPS},
                     'cpu_energy_per_step_pj': compiled * watts * 1e6})
    return {'filter': kind, 'rows': rows}


def plot_sweep(sweep: dict, path: Path) -> None:
    """Operations (left) and energy (right) per estimate against N."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    rows = sweep['rows']
    neurons = [row['neurons'] for row in rows]
    fig, (ops, energy) = plt.subplots(1, 2, figsize=(12, 5.6))
    ops.plot(neurons, [r['synops_per_step'] for r in rows], 'o-', label='spiking: synaptic ops (event-driven)')
    ops.plot(neurons, [r['dense_macs_per_step'] for r in rows], 's-', label='dense N x N MACs, constant K')
    ops.plot(neurons, [r['dense_time_varying_macs_per_step'] for r in rows], 's--',
             label='dense N x N MACs, K and weights recomputed')
    ops.plot(neurons, [r['nonspiking_time_varying_macs_per_step'] for r in rows], '^--',
             label='non-spiking filter MACs (K, P updated)')
    ops.plot(neurons, [r['nonspiking_macs_per_step'] for r in rows], '^-', label='non-spiking filter MACs, constant K')
    ops.set(xlabel='neurons N', ylabel='operations per estimate', yscale='log',
            title=f'{sweep["filter"]}, constant gain: operations per 0.1 s estimate')
    for chip, spec in CHIPS.items():
        energy.plot(neurons, [r['energy_per_step_pj'][chip] * 1e-6 for r in rows], 'o-', label=spec.label)
    energy.plot(neurons, [r['cpu_energy_per_step_pj'] * 1e-6 for r in rows], 'k--',
                label=f'CPU, compiled kernel (measured time x {CPU_WATTS:g} W assumed)')
    for key, style, label in (('dense_macs_per_step', 'k:', 'dense N x N MACs'),
                              ('nonspiking_time_varying_macs_per_step', 'r:', 'non-spiking filter MACs')):
        energy.plot(neurons, [r[key] * FLOAT32_MAC_PJ * 1e-6 for r in rows], style,
                    label=f'{label} x {FLOAT32_MAC_PJ:g} pJ (float32 arithmetic only)')
    energy.set(xlabel='neurons N', ylabel='energy per estimate, uJ', yscale='log',
               title='energy per estimate (no static power)')
    for axis in (ops, energy):
        axis.grid(True, which='both', alpha=0.3)
        axis.legend(fontsize=7, loc='upper center', bbox_to_anchor=(0.5, -0.16), ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def markdown(data: dict) -> str:
    """The results/neuromorphic.md section."""
    lines = ['## Neuromorphic: NIR export, an independent simulator, cost per estimate', '',
             (f'Generated by `snn_neuromorphic` ({data["scenario"]}). Networks with the steady-state '
              'gain (constant weights) exported by `snn_export` to NIR and read back by Brian2.'), '',
             '### Independent simulator (Brian2 from the NIR file) against our kernel', '',
             '| filter | RMSE ratio (pos.) | spike ratio | identical spikes | max diff x (m) | Brian2 run (s) |',
             '|---|---|---|---|---|---|']
    for kind, item in data['filters'].items():
        lines.append(f'| {kind} | {item["independent_rmse_ratio"]} | {item["independent_spike_ratio"]} | '
                     f'{item["independent_identical_spikes"]} | '
                     f'{max(item["independent_max_estimate_difference"][:3]):.2g} | '
                     f'{item["independent_wall_time_s"]} |')
    first = next(iter(data['filters'].values()))
    lines += ['', (f'Setting: {first["independent_simulator"]}. The drive of each sample is applied at '
                   'its start and the spikes resolved by a threshold function that lets only the neuron '
                   "with the largest overshoot fire per Brian2 step (the package's greedy rule)."), '',
              'Other readings of the same graph (ratios Brian2 / ours over the window):', '',
              ('| filter | reading | Brian2 dt (ms) | window (s) | RMSE ratio (pos.) | spikes (Brian2 / ours) '
               '| run (s) |'),
              '|---|---|---|---|---|---|---|']
    for kind, item in data['filters'].items():
        for label, reading in item['readings'].items():
            lines.append(f'| {kind} | {label} | {reading["brian_dt_ms"]:g} | {reading["window_s"]} | '
                         f'{reading["rmse_ratio"]} | {reading["spikes"]} / {reading["spikes_ours"]} | '
                         f'{reading["wall_time_s"]} |')
    first_reading = next(iter(first['readings'].values()))
    brian_t, ours_t = first_reading['mean_threshold_per_spike']
    lines += ['', ('Only the sampled reading reproduces the package\'s network. Read as a continuous-time '
               'network (inputs held, fine dt, one spike per Brian2 step) the same weights fire more spikes '
               'while the state moves fast: the first neuron to cross is one with a small threshold '
               f'(mean T_i of a spike {brian_t:.3g} against {ours_t:.3g} in our run, first filter, first '
               'window), whose spike moves the estimate less, where the greedy rule after a whole sample picks '
               'the largest overshoot. Brian2\'s own threshold (every neuron above fires in the same step, as '
               'on a synchronous chip) overshoots and runs away (the all_above rows).')]
    lines += ['', '### Cost per estimate (one 0.1 s step, mean over the run)', '',
              '| filter | spikes | synaptic ops | neuron updates | dense MACs | non-spiking MACs (K varies / fixed) | '
              + ' | '.join(f'{CHIPS[c].label} (nJ)' for c in CHIPS) + ' | CPU compiled (us) | CPU dense (us) |',
              '|---|---|---|---|---|---|' + '---|' * len(CHIPS) + '---|---|']
    for kind, item in data['filters'].items():
        macs = item['nonspiking_macs_per_step']
        energies = ' | '.join(f'{item["energy_per_step_pj"][c] / 1e3:.3g}' for c in CHIPS)
        lines.append(f'| {kind} | {item["spikes_per_step"]} | {item["synops_per_step"]:.0f} | '
                     f'{item["neuron_updates_per_step"]} | {item["dense_macs_per_step"]:.0f} | '
                     f'{macs["time_varying"]} / {macs["constant_gain"]} | {energies} | '
                     f'{item["cpu"]["compiled_us_per_step"]} | {item["cpu"]["dense_us_per_step"]} |')
    arithmetic = []
    for kind, item in data['filters'].items():
        energies = item['float32_arithmetic_energy_per_step_pj']
        arithmetic.append(f'{kind}: dense {energies["dense"] / 1e3:.3g} nJ, non-spiking filter '
                          f'{energies["nonspiking_time_varying"] / 1e3:.3g} nJ')
    lines += ['', f'Float32 arithmetic alone ({FLOAT32_MAC_PJ:g} pJ per MAC, no memory access): '
              + '; '.join(arithmetic) + '.',
              '', '![cost per estimate against N](neuromorphic_costs.png)', '',
              '### Constant gain against the time-varying gain (RMSE ratio per state)', '',
              '| filter | start | ' + ' | '.join(data['states']) + ' |', '|---|---|' + '---|' * len(data['states'])]
    for kind, item in data['filters'].items():
        for label, row in item['constant_vs_time_varying'].items():
            lines.append(f'| {kind} | {label} | ' + ' | '.join(f'{v:.3g}' for v in row['rmse_ratio_per_state']) + ' |')
    lines += ['', ('Ratio of RMSE over the last 60 s, constant gain / time-varying gain, same kind, '
                   f'{first["constant_vs_time_varying"]["dispersed"]["runs"]} runs each. With Q_hat = 0.9e-12 '
                   'the steady-state Kalman gain is tiny, so a constant-gain SNN-EKF that starts away from '
                   'the truth (dispersed) barely corrects its initial error; the (M)SIF gains depend on P only '
                   'through diag(C P C^T + R_hat), which R_hat dominates, so holding them changes little.')]
    lines += ['', '### Sources and assumptions', '']
    lines += [f'- {spec.label}: {spec.source}; {spec.note}.' for spec in CHIPS.values()]
    lines += [f'- Float32 MAC: {FLOAT32_MAC_SOURCE}; arithmetic only.']
    lines += [f'- {text}' for text in data['assumptions'].values()]
    if 'chip' in data:  # the chip's arithmetic, schedule, spiking LQR (snn_tools.neuromorphic.chip)
        from snn_tools.neuromorphic.chip import markdown as chip_markdown
        lines += chip_markdown(data['chip'])
    if 'local_rule' in data:  # the synchronous rule (snn_tools.neuromorphic.local_rule)
        lines += local_rule_markdown(data['local_rule'])
    if 'chip_synchronous' in data:  # the synchronous rule in fixed point (snn_tools.neuromorphic.chip)
        lines += synchronous_markdown(data['chip_synchronous'])
    if 'norse_loop' in data:  # Norse in the closed loop (make norse-loop, snn_tools.neuromorphic.norse_loop)
        lines += norse_loop_markdown(data['norse_loop'])
    return '\n'.join(lines) + '\n'


def run_filter(kind: str, scenario, args, workdir: Path) -> dict:
    """Every figure of ``kind``."""
    estimator = constant_gain_estimator(kind, scenario.estimator, scenario.model)
    nir_path = workdir / f'{kind}.nir'
    nir.write(nir_path, network_graph(estimator, scenario.dt))
    net = network_arrays(nir.read(nir_path))
    starts = {start for *_, start, _ in reading_windows(scenario)}
    recording = record_rendezvous(scenario, estimator, snapshot_steps=starts)
    record = independent_check(scenario, recording, net, args.substeps)
    record.update(cost_record(estimator, recording.raster, args.substeps))
    record['cpu'] = cpu_record(kind, scenario.estimator, scenario, recording, net, args.cpu_watts)
    record['constant_vs_time_varying'] = gain_schedule_comparison(kind, args.runs, scenario.duration)
    record['sources'] = SOURCES
    return record


SOURCES = {
    'independent_*': 'Brian2 network built from the .nir file (snn_tools.neuromorphic.brian2_sim) over the z_k, '
                     'u_k of one closed-loop rendezvous driven by our constant-gain network (seed 0); RMSE against the '
                     'truth over the last 60 s, ratios Brian2 / ours',
    'synops_per_step': 'counted from that run\'s spikes: spikes x (2N - 1 + n) + N (m + nu) '
                       '(snn_estimator.spiking.costs)',
    'neuron_updates_per_step': '2N + n state updates per estimate (membranes, slow currents, readout)',
    'dense_macs_per_step': "the paper's N x N algebra per step with held weights (snn_estimator.spiking.costs)",
    'nonspiking_macs_per_step': 'the loops of kernels.estimator_step for n = 6, m = 3, nu = 3 '
                                '(snn_estimator.spiking.costs)',
    'energy_per_step_pj': 'operations x published per-operation energy (snn_estimator.spiking.costs.CHIPS); '
                          'no static power',
    'cpu': 'median time.perf_counter per step over the replay, best of 3; energy = time x assumed_watts',
    'constant_vs_time_varying': 'simulate(rendezvous_scenario(initial_state_dispersion=...), kind, runs) with '
                                'gain_schedule steady_state over time_varying; rmse() over the last 60 s',
}


def _mean_threshold(raster: np.ndarray, threshold: np.ndarray) -> float:
    """Mean T_i = ||D_i||^2 / 2 over the spikes of ``raster`` (steps, N): how large a step in
    the decoded estimate the firing neurons make."""
    counts = raster.sum(axis=0)
    return float(counts @ threshold / max(counts.sum(), 1))


def _round(values) -> list:
    return [float(f'{v:.4g}') for v in np.asarray(values, dtype=float)]


def _ratio(a, b) -> float:
    return round(float(a) / float(b), 4) if b else float('nan')


def _version(package: str) -> str:
    from importlib.metadata import version
    return version(package)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='snn_neuromorphic', description=__doc__.split('\n\n')[0])
    parser.add_argument('--out', type=Path, default=Path('results'), help='output folder')
    parser.add_argument('--filters', nargs='+', default=list(DEFAULT_FILTERS),
                        choices=[k for k, spec in FILTER_KINDS.items() if spec.spiking])
    parser.add_argument('--runs', type=int, default=100, help='Monte-Carlo runs per gain schedule')
    parser.add_argument('--substeps', type=int, default=SUBSTEPS, help='Brian2 sub-steps per sample')
    parser.add_argument('--duration', type=float, default=None, help='s of rendezvous (default: 360)')
    parser.add_argument('--neuron-counts', type=int, nargs='+', default=list(NEURON_COUNTS))
    parser.add_argument('--cpu-watts', type=float, default=CPU_WATTS,
                        help='power assumed for the busy CPU core, W (energy = measured time x this)')
    parser.add_argument('--chip-spec', default='config/campaigns/chip_bits.yaml',
                        help='campaign spec of the fixed-point bit-width sweep')
    parser.add_argument('--chip-runs', type=int, default=None, help='runs per bit-width cell (default: the spec)')
    parser.add_argument('--schedule-runs', type=int, default=100, help='Monte-Carlo runs per weight schedule')
    parser.add_argument('--controller-runs', type=int, default=20, help='runs per controller comparison')
    parser.add_argument('--emulator-seconds', type=float, default=60.0,
                        help='s of the Brian2 re-run of the integer network')
    parser.add_argument('--no-chip', action='store_true', help='skip the chip section (snn_tools.neuromorphic.chip)')
    parser.add_argument('--chip-only', action='store_true',
                        help='compute the chip section alone and add it to the existing <out>/neuromorphic.json')
    parser.add_argument('--local-rule-only', action='store_true',
                        help='compute the synchronous spike rule section alone (make spike-rules) and add it to '
                             'the existing <out>/neuromorphic.json')
    parser.add_argument('--local-rule-runs', type=int, nargs=2, default=[100, 100], metavar=('POSITION', 'LIDAR'),
                        help='runs of the synchronous rule section per scenario (LIDAR 0: position only)')
    parser.add_argument('--markdown-only', action='store_true',
                        help='rewrite <out>/neuromorphic.md from <out>/neuromorphic.json, measuring nothing')
    parser.add_argument('--chip-synchronous-only', action='store_true',
                        help='compute the fixed-point synchronous network section alone (make chip-synchronous) and '
                             'add it to the existing <out>/neuromorphic.json')
    parser.add_argument('--chip-synchronous-runs', type=int, default=20,
                        help='runs per row of the fixed-point synchronous network section')
    args = parser.parse_args(argv)
    if args.markdown_only:
        (args.out / 'neuromorphic.md').write_text(markdown(json.loads((args.out / 'neuromorphic.json').read_text())))
        return 0
    if args.chip_synchronous_only:
        return _chip_synchronous_only(args)
    if args.chip_only:
        return _chip_only(args)
    if args.local_rule_only:
        return _local_rule_only(args)
    if args.runs < 1 or args.substeps < 1:
        parser.error('--runs and --substeps must be >= 1')
    scenario = rendezvous_scenario()
    if args.duration is not None:
        scenario = dataclasses.replace(scenario, duration=args.duration)
    args.out.mkdir(parents=True, exist_ok=True)
    data = {'scenario': f'rendezvous, {scenario.duration:g} s at dt = {scenario.dt} s, seed 0, N = '
                        f'{scenario.estimator.neuron_count}',
            'states': list(scenario.model.state_names), 'filters': {},
            'assumptions': {
                'static': 'Static and leakage power are not per-operation and are left out (TrueNorth\'s '
                          '26 pJ is all-in and includes them at its operating point).',
                'cpu': f'CPU energy = measured time per step x {args.cpu_watts:g} W assumed for one busy core '
                       '(not measured: no power counters in this container).',
                'ticks': 'Neuron updates count one update per estimate (the spikes of a sample resolved in '
                         'place); a chip that resolves one spike per time step needs at least as many ticks as '
                         'spikes per sample: time_stepped_chip gives the updates and energy at the Brian2 '
                         'sub-step count.'}}
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix='snn_neuromorphic_') as workdir:
        for kind in track(args.filters, 'filters', 'snn_neuromorphic'):  # progress on a terminal
            data['filters'][kind] = run_filter(kind, scenario, args, Path(workdir))
            item = data['filters'][kind]
            print(f'{kind}: Brian2/ours RMSE {item["independent_rmse_ratio"]}, spikes '
                  f'{item["independent_spike_ratio"]}; {item["synops_per_step"]:.0f} synops, '
                  f'{item["dense_macs_per_step"]:.0f} dense MACs per step', flush=True)
    sweep = neuron_sweep(args.filters[0], scenario, args.neuron_counts, args.cpu_watts)
    data['neuron_sweep'] = sweep
    if not args.no_chip:
        first = data['filters'].get('snn_ekf') or next(iter(data['filters'].values()))
        data['chip'] = run_all(args, first['energy_per_step_pj']['loihi'])
        print(f'chip section: {data["chip"]["wall_time_s"]} s', flush=True)
    data['local_rule'] = _measure_local_rule(args)
    if not args.no_chip:
        data['chip_synchronous'] = synchronous_fixed_point(args.chip_synchronous_runs)
    data['wall_time_s'] = round(time.perf_counter() - started, 1)
    plot_sweep(sweep, args.out / 'neuromorphic_costs.png')
    previous = args.out / 'neuromorphic.json'
    if previous.exists():  # make norse-loop's measurement: it needs Norse, which this run does not run
        norse_loop = json.loads(previous.read_text()).get('norse_loop')
        if norse_loop is not None:
            data['norse_loop'] = norse_loop
    (args.out / 'neuromorphic.json').write_text(json.dumps(data, indent=2) + '\n')
    (args.out / 'neuromorphic.md').write_text(markdown(data))
    print(f'wrote {args.out / "neuromorphic.json"}, neuromorphic.md, neuromorphic_costs.png '
          f'({data["wall_time_s"]} s)')
    return 0


def _measure_local_rule(args) -> dict:
    position, lidar = args.local_rule_runs
    if position < 1 or lidar < 0:
        raise SystemExit('--local-rule-runs: position runs >= 1, LIDAR runs >= 0')
    return measure_local_rule({'position': position, **({'lidar': lidar} if lidar else {})},
                              report=lambda line: print(line, flush=True))


def _local_rule_only(args) -> int:
    """The synchronous rule's section over the existing results (the rest as the last full run wrote it)."""
    path = args.out / 'neuromorphic.json'
    data = json.loads(path.read_text())
    data['local_rule'] = _measure_local_rule(args)
    path.write_text(json.dumps(data, indent=2) + '\n')
    (args.out / 'neuromorphic.md').write_text(markdown(data))
    print(f'wrote the local rule section into {path} and neuromorphic.md ({data["local_rule"]["wall_time_s"]} s)')
    return 0


def _chip_synchronous_only(args) -> int:
    """The fixed-point synchronous network's section over the existing results."""
    if args.chip_synchronous_runs < 1:
        raise SystemExit('--chip-synchronous-runs must be >= 1')
    path = args.out / 'neuromorphic.json'
    data = json.loads(path.read_text())
    started = time.perf_counter()
    data['chip_synchronous'] = synchronous_fixed_point(args.chip_synchronous_runs)
    data['chip_synchronous']['wall_time_s'] = round(time.perf_counter() - started, 1)
    path.write_text(json.dumps(data, indent=2) + '\n')
    (args.out / 'neuromorphic.md').write_text(markdown(data))
    print(f'wrote the fixed-point synchronous section into {path} and neuromorphic.md '
          f'({data["chip_synchronous"]["wall_time_s"]} s)')
    return 0


def _chip_only(args) -> int:
    """The chip section over the existing results (the rest as the last full run wrote it)."""
    path = args.out / 'neuromorphic.json'
    data = json.loads(path.read_text())
    first = data['filters'].get('snn_ekf') or next(iter(data['filters'].values()))
    data['chip'] = run_all(args, first['energy_per_step_pj']['loihi'])
    path.write_text(json.dumps(data, indent=2) + '\n')
    (args.out / 'neuromorphic.md').write_text(markdown(data))
    print(f'wrote the chip section into {path} and neuromorphic.md ({data["chip"]["wall_time_s"]} s)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
