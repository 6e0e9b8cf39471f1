"""The chip part of ``snn_neuromorphic``: fixed point against float per bit width (the
chip_bits campaign's cells), Brian2 from the chip network's NIR file against the integer
network, the gain schedule from the dispersed Monte Carlo, the spiking LQR beside the LQR, and
the energy per estimate from the fixed-point network's own operation counts."""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

import nir
import numpy as np

from snn_estimator.filters.estimators import make_estimator
from snn_estimator.sim.scenarios import rendezvous_scenario
from snn_estimator.sim.simulate import simulate
from snn_estimator.spiking.costs import CHIPS, CostModel, energy_pj
from snn_tools.campaign.cells import run_cell
from snn_tools.campaign.spec import load_spec
from snn_tools.neuromorphic.brian2_sim import run_network
from snn_tools.neuromorphic.nir_export import network_arrays, network_graph
from snn_tools.neuromorphic.recording import record_rendezvous, rmse

SCHEDULE = {'gain_schedule': 'switched', 'schedule_times': (1.0, 10.0, 100.0)}
#: Switch times tried for the number of weight sets (1 = the steady-state gain alone).
SCHEDULES = ((), (10.0, 100.0), (1.0, 10.0, 100.0))
SCHEDULE_FILTERS = ('snn_ekf', 'snn_emsif_weighted')
POSITION = ('rmse_x', 'rmse_y', 'rmse_z')


def _position(row: dict) -> float:
    return float(np.linalg.norm([row[k] for k in POSITION]))


def bit_sweep(spec_path: str, runs: int | None) -> dict:
    """Every cell of the chip_bits spec and, per filter, the same settings in float64."""
    spec = load_spec(spec_path)
    runs = runs or spec.runs
    rows, reference = [], {}
    for cell in spec.cells():
        if cell.filter not in reference:
            settings = dict(cell.settings, precision='float64')
            settings.pop('weight_bits'), settings.pop('membrane_bits')
            reference[cell.filter] = run_cell(spec.scenario, cell.filter, settings, runs, spec.seed)
        row = run_cell(spec.scenario, cell.filter, cell.settings, runs, spec.seed)
        float_row = reference[cell.filter]
        rows.append({'filter': cell.filter, 'weight_bits': cell.settings['weight_bits'],
                     'membrane_bits': cell.settings['membrane_bits'],
                     'rmse_position_m': _position(row), 'rmse_position_float_m': _position(float_row),
                     'rmse_ratio_position': _position(row) / _position(float_row),
                     'rmse_ratio_velocity': float(np.linalg.norm([row[f'rmse_v{a}'] for a in 'xyz'])
                                                  / np.linalg.norm([float_row[f'rmse_v{a}'] for a in 'xyz'])),
                     'final_range_max_m': row['final_range_max'],
                     'final_range_max_float_m': float_row['final_range_max'],
                     'spike_fraction': row['spike_fraction'], 'capped_steps': row['capped_steps']})
    return {'spec': spec_path, 'runs': runs, 'settings': {k: v for k, v in spec.settings.items()}, 'rows': rows}


def emulator_check(seconds: float, substeps: int) -> dict:
    """Brian2 built from the NIR file of the Loihi-format SNN-EKF (steady-state gain: NIR
    holds one weight set) over ``seconds`` of a closed loop the integer network drives."""
    scenario = dataclasses.replace(rendezvous_scenario(), duration=seconds)
    config = scenario.estimator.replace(gain_schedule='steady_state', precision='loihi')
    estimator = make_estimator('snn_ekf', config, scenario.model)
    estimator.prepare(scenario.dt)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / 'chip.nir'
        nir.write(path, network_graph(estimator, scenario.dt))
        net = network_arrays(nir.read(path))
    recording = record_rendezvous(scenario, estimator)
    run = run_network(net, recording.zs, recording.us, mode='sampled', rule='greedy', substeps=substeps)
    window = round(min(scenario.metric_window, seconds / 2) / scenario.dt)
    ours, theirs = rmse(recording.truth, recording.estimate, window), rmse(recording.truth, run.estimate, window)
    return {'filter': 'snn_ekf', 'precision': 'loihi (8/24/12)', 'seconds': seconds, 'substeps': substeps,
            'rmse_ratio_position': float(np.linalg.norm(theirs[:3]) / np.linalg.norm(ours[:3])),
            'spikes_independent': int(run.spikes_per_step.sum()), 'spikes_ours': int(recording.raster.sum()),
            'max_difference_position_m': float(np.abs(run.estimate - recording.estimate)[:, :3].max()),
            'saturated_samples': run.saturated_steps, 'wall_time_s': round(run.wall_time, 1)}


def schedule_study(runs: int) -> dict:
    """Final range and RMSE from the dispersed Monte Carlo per number of weight sets, in
    Loihi's formats, beside the time-varying float filter."""
    scenario = rendezvous_scenario(initial_state_dispersion=True)
    out = {}
    for kind in SCHEDULE_FILTERS:
        varying = simulate(scenario, kind, runs=runs)
        rows = [{'weight_sets': 'time-varying (float)', 'switch_times_s': None,
                 'rmse_position_m': float(np.linalg.norm(varying.rmse()[:3])),
                 'final_range_max_m': float(varying.final_range().max()),
                 'final_range_median_m': float(np.median(varying.final_range()))}]
        for times in SCHEDULES:
            config = scenario.estimator.replace(precision='loihi', gain_schedule='switched', schedule_times=times)
            result = simulate(scenario, kind, runs=runs, config=config)
            rows.append({'weight_sets': len(times) + 1, 'switch_times_s': list(times),
                         'rmse_position_m': float(np.linalg.norm(result.rmse()[:3])),
                         'final_range_max_m': float(result.final_range().max()),
                         'final_range_median_m': float(np.median(result.final_range())),
                         'runs_below_0.1m': int((result.final_range() < 0.1).sum())})
        out[kind] = rows
    return {'runs': runs, 'filters': out}


def controller_study(runs: int) -> dict:
    """lqr against snn_lqr, and the whole loop spiking (spiking estimator, in Loihi's formats
    with the 4-set schedule, and spiking controller), dispersed start."""
    scenario = rendezvous_scenario(initial_state_dispersion=True)
    chip_config = scenario.estimator.replace(precision='loihi', **SCHEDULE)
    cases = (('ekf', 'lqr', None), ('ekf', 'snn_lqr', None), ('snn_ekf', 'lqr', None),
             ('snn_ekf', 'snn_lqr', None), ('snn_ekf', 'lqr', chip_config), ('snn_ekf', 'snn_lqr', chip_config))
    rows = []
    for kind, controller, config in cases:
        result = simulate(scenario, kind, runs=runs, config=config, controller=controller)
        spikes = result.spikes_per_step
        controller_spikes = result.extra['controller_spikes']
        rows.append({'estimator': kind + (' (loihi, 4 sets)' if config is not None else ''), 'controller': controller,
                     'final_range_max_m': float(result.final_range().max()),
                     'final_range_median_m': float(np.median(result.final_range())),
                     'delta_v_mean_m_s': float(result.delta_v().mean()),
                     'peak_thrust_m_s2': float(np.abs(result.control).max()),
                     'estimator_spikes_per_step': None if spikes is None else float(spikes.mean()),
                     'controller_spikes_per_step': (None if controller_spikes is None
                                                    else float(controller_spikes.mean() / scenario.steps))})
    return {'runs': runs, 'controller_neurons': 100, 'controller_leak': 0.001, 'rows': rows}


def chip_energy(float_energy: dict) -> dict:
    """Energy per estimate of the Loihi-format SNN-EKF from its own operation counts (graded
    synaptic operations and spikes counted by the kernel over a 360 s rendezvous), beside the
    float network's estimate (today's count, snn_estimator.spiking.costs)."""
    scenario = rendezvous_scenario()
    config = scenario.estimator.replace(gain_schedule='steady_state', precision='loihi')
    estimator = make_estimator('snn_ekf', config, scenario.model)
    recording = record_rendezvous(scenario, estimator)
    network = estimator.chip
    steps = scenario.steps
    n, neurons = scenario.model.n_state, estimator.neuron_count
    spikes = recording.raster.sum() / steps
    synops = network.synops / steps
    # per tick: N membranes (v = D^T e), n coding-error and n readout compartments, n state compartments
    updates = neurons + 3 * n
    chip = CHIPS['loihi']
    energy = synops * chip.synop_pj + updates * chip.neuron_update_pj + spikes * chip.spike_pj
    float_model = CostModel.of(make_estimator('snn_ekf', scenario.estimator.replace(gain_schedule='steady_state'),
                                              scenario.model))
    float_costs = float_model.step(spikes)
    return {'filter': 'snn_ekf', 'precision': 'loihi (8/24/12), steady-state gain',
            'spikes_per_step': float(spikes), 'synops_per_step': float(synops),
            'compartment_updates_per_step': updates, 'energy_per_step_pj': float(energy),
            'float_network_synops_per_step_same_spikes': float(float_costs.synops),
            'float_network_energy_per_step_pj_same_spikes': float(energy_pj(float_costs, 'loihi')),
            'float_network_energy_per_step_pj_own_run': float_energy,
            'source': chip.source,
            'note': ('synaptic operations of the factored network: each tick and after each spike the n-vector '
                     'e reaches every neuron (N n graded operations), each spike reaches e and the readout '
                     '(2 n); priced at Loihi\'s 23.6 pJ per synaptic operation, which Davies et al. give for '
                     'binary spikes: graded messages (Loihi 2) cost more per operation and no per-operation '
                     'figure is published; compartment updates at 52 pJ, spikes at the active-update '
                     'difference plus routing')}


#: The synchronous network's windows: the tables' metric (the last 60 s of the 360 s rendezvous)
#: and the approach (60-120 s), where the SNN-EKF's small late gain corrects little.
SYNCHRONOUS_WINDOWS = {'last 60 s of 360 s': 360.0, 'approach, 60-120 s': 120.0}
SYNCHRONOUS_FILTERS = ('snn_ekf', 'snn_emsif_weighted')
#: Issue 40: the fixed-point network with the local rule within this of float at 8-bit weights.
SYNCHRONOUS_GOAL = 1.1


def exact_coupling_scale(scenario) -> tuple:
    """The scenario's state scale with the velocity scales moved (by < 2^0.5) so that dt s_v / s_p,
    the kinematic coupling of the network's A in scaled units, is a power of two: exact in any
    weight mantissa (docs/decisions.md, 65)."""
    scale = np.asarray(scenario.estimator.state_scale, dtype=float)
    position, velocity = scale[:3], scale[3:]
    exponent = np.round(np.log2(velocity * scenario.dt / position))
    return tuple(position) + tuple(position * 2.0 ** exponent / scenario.dt)


def synchronous_fixed_point(runs: int, weight_bits: int = 8) -> dict:
    """The Eq. 15 network in Loihi's formats under the synchronous rule
    (snn_estimator.spiking.chip_synchronous) against the same network in float64, both with the
    4-set schedule, dispersed start, the same seeds: position RMSE per kind, window and state scale."""
    rows = []
    for window, duration in SYNCHRONOUS_WINDOWS.items():
        scenario = dataclasses.replace(rendezvous_scenario(initial_state_dispersion=True), duration=duration)
        scales = {'package (1 cm, 0.1 mm/s)': scenario.estimator.state_scale,
                  'dt s_v / s_p a power of two': exact_coupling_scale(scenario)}
        for kind in SYNCHRONOUS_FILTERS:
            for label, scale in scales.items():
                config = scenario.estimator.replace(spike_rule='synchronous', state_scale=scale, **SCHEDULE)
                started = time.perf_counter()
                float_run = simulate(scenario, kind, runs=runs, config=config, trajectories=False)
                fixed_config = config.replace(precision='loihi', weight_bits=weight_bits)
                fixed = simulate(scenario, kind, runs=runs, trajectories=False, config=fixed_config)
                rows.append({'filter': kind, 'window': window, 'state_scale': label,
                             'velocity_scale_m_s': float(scale[3]), 'weight_bits': weight_bits,
                             'chip_velocity_unit_m_s': _chip_velocity_unit(scenario, kind, fixed_config),
                             'rmse_position_m': _position_rmse(fixed),
                             'rmse_position_float_m': _position_rmse(float_run),
                             'rmse_ratio_position': _position_rmse(fixed) / _position_rmse(float_run),
                             'spikes_per_step': _spikes_per_step(fixed),
                             'spikes_per_step_float': _spikes_per_step(float_run),
                             'diverged': int(fixed.diverged.sum()), 'diverged_float': int(float_run.diverged.sum()),
                             'capped_steps': int(fixed.capped_steps),
                             'wall_s': round(time.perf_counter() - started, 1)})
                row = rows[-1]
                print(f"chip synchronous {kind} {window} {label}: {row['rmse_ratio_position']:.3f}x float "
                      f"({row['wall_s']} s)", flush=True)
    settings = rendezvous_scenario().estimator
    return {'runs': runs, 'weight_bits': weight_bits, 'goal_ratio': SYNCHRONOUS_GOAL, 'rows': rows,
            'rule': {'ticks_per_sample': settings.ticks_per_sample, 'firing_slots': settings.firing_slots,
                     'threshold_widening': settings.threshold_widening,
                     'refractory_ticks': settings.refractory_ticks}}


def _chip_velocity_unit(scenario, kind: str, config) -> float:
    """The velocity unit the integer chip chose for itself (m/s per unit; docs/decisions.md, 66)."""
    estimator = make_estimator(kind, config, scenario.model)
    estimator.prepare(scenario.dt)
    return float(estimator.chip.unit[3])


def _position_rmse(result) -> float:
    return float(np.linalg.norm(result.rmse()[:3]))


def _spikes_per_step(result) -> float:
    kept = ~result.diverged
    return float(result.sums.spikes[kept].mean() / result.sums.steps)


def synchronous_markdown(data: dict) -> list[str]:
    """The synchronous fixed-point section of results/neuromorphic.md."""
    rule = data['rule']
    lines = ['', '## The local rule on the chip: the Eq. 15 network in Loihi\'s formats (issue 40)', '',
             ('Generated by `make chip-synchronous` (`snn_tools.neuromorphic.chip.synchronous_fixed_point`). '
              'The network itself (snn_estimator/spiking/chip_synchronous.py): N integer membranes (24-bit, '
              'saturating), the fast weights Omega_f = -D^T D as an N x N matrix of '
              f'{data["weight_bits"]}-bit mantissas with one exponent (exact: the decoder\'s LSB is chosen so '
              'that the Gram matrix fits), per-neuron integer thresholds (1 + w) ||D_i||^2 / 2, binary '
              'spikes, 12-bit decays; the slow input D^T y from n state compartments (A, K, B in '
              f'{data["weight_bits"]}-bit mantissas, one exponent per row; each input u_j scaled so the largest '
              'weight of its column is a power of two; each velocity held in the chip\'s own unit, within '
              '2^0.5 of the state scale, that makes the kinematic coupling dt s_v / s_p of A a power of two, the '
              'estimate read out in m and m/s). The synchronous rule as the float kernel runs it '
              f'(T = {rule["ticks_per_sample"]} ticks, K = {rule["firing_slots"]} slots, w = '
              f'{rule["threshold_widening"]:g}, R = {rule["refractory_ticks"]}): every eligible neuron above its '
              'own threshold fires in the tick, no global comparison. Against the same network in float64 '
              f'(precision float64), both with the 4-set schedule, dispersed start, {data["runs"]} runs, seeds '
              '0.. ; position RMSE (norm of the x, y, z RMSE) over the window. docs/decisions.md, 64-66.'), '',
             '| filter | window | state scale | chip velocity unit (mm/s) | RMSE pos. (m) | float (m) | ratio | '
             'spikes/step | float | diverged |', '|---|---|---|---|---|---|---|---|---|---|']
    for row in data['rows']:
        unit = row.get('chip_velocity_unit_m_s')
        lines.append(f"| {row['filter']} | {row['window']} | {row['state_scale']} | "
                     f"{'' if unit is None else f'{unit * 1e3:.6g}'} | {row['rmse_position_m']:.4g} | "
                     f"{row['rmse_position_float_m']:.4g} | {row['rmse_ratio_position']:.3f} | "
                     f"{row['spikes_per_step']:.1f} | {row['spikes_per_step_float']:.1f} | "
                     f"{row['diverged']} / {row['diverged_float']} |")
    met = [row for row in data['rows'] if row['rmse_ratio_position'] <= data['goal_ratio'] and not row['diverged']]
    missed = [row for row in data['rows'] if row not in met]
    lines += ['', (f'Goal of issue 40 (within {data["goal_ratio"]}x of float at {data["weight_bits"]}-bit weights): '
                   f'met in {len(met)} of {len(data["rows"])} rows'
                   + ('; missed: ' + '; '.join(f"{r['filter']}, {r['window']}, {r['state_scale']} "
                                                f"({r['rmse_ratio_position']:.2f}x)" for r in missed) if missed else '')
                   + '.')]
    return lines


def run_all(args, float_energy: dict) -> dict:
    """Every chip figure (see the module docstring)."""
    started = time.perf_counter()
    data = {'bit_sweep': bit_sweep(args.chip_spec, args.chip_runs),
            'emulator': emulator_check(args.emulator_seconds, args.substeps),
            'schedule': schedule_study(args.schedule_runs),
            'controller': controller_study(args.controller_runs),
            'energy': chip_energy(float_energy)}
    data['wall_time_s'] = round(time.perf_counter() - started, 1)
    return data


def markdown(data: dict) -> list[str]:
    """The chip section of results/neuromorphic.md."""
    sweep = data['bit_sweep']
    lines = ['', '## On the chip: Loihi\'s integer formats, weights a chip holds, a spiking LQR', '',
             ('Generated by `snn_neuromorphic` (snn_tools/neuromorphic/chip.py). The network in '
              '`precision: loihi` (snn_estimator/spiking/chip.py): signed weight mantissas with one exponent per '
              'matrix, 24-bit state (membrane, coding error, readout; currents wrap, the membrane saturates), '
              '12-bit decays rounded toward zero (Davies et al. 2018, IEEE Micro 38(1); Lava\'s bit-accurate '
              'Loihi LIF). Run factored (v = D^T e): the literal dense N x N network in these formats drives '
              'the null space of D^T with its rounding and hits the spike cap from the first sample.'), '',
             f'### Fixed point against float per bit width ({sweep["spec"]}, {sweep["runs"]} runs, dispersed '
             'start, 4 weight sets)', '',
             '| filter | weight bits | state bits | RMSE pos. (m) | float (m) | ratio pos. | ratio vel. | '
             'final range max (m) | spike fraction |', '|---|---|---|---|---|---|---|---|---|']
    for row in sweep['rows']:
        lines.append(f'| {row["filter"]} | {row["weight_bits"]} | {row["membrane_bits"]} | '
                     f'{row["rmse_position_m"]:.4g} | {row["rmse_position_float_m"]:.4g} | '
                     f'{row["rmse_ratio_position"]:.3g} | {row["rmse_ratio_velocity"]:.3g} | '
                     f'{row["final_range_max_m"]:.3g} | {row["spike_fraction"]:.3g} |')
    emulator = data['emulator']
    lines += ['', '### An independent re-simulation of the integer network', '',
              (f'Brian2 built from the NIR file of the Loihi-format SNN-EKF (the dense weights its quantized '
               f'factors compute; steady-state gain), sampled greedy reading, {emulator["substeps"]} sub-steps, '
               f'{emulator["seconds"]:g} s of a closed loop the integer network drives: RMSE ratio (position, '
               f'Brian2 / ours) {emulator["rmse_ratio_position"]:.4f}, spikes {emulator["spikes_independent"]} / '
               f'{emulator["spikes_ours"]}, largest position difference '
               f'{emulator["max_difference_position_m"]:.2g} m (the integer network rounds its drive to the '
               'readout LSB, 0.17 mm; Brian2 does not).'), '',
              ('Loihi emulators: `brian2-loihi` 0.5.2 installs beside brian2 2.9.0 and numpy 2.2 (no '
               'conflict), and `pip install --dry-run nengo-loihi` resolves (nengo-loihi 1.1.0 with nengo 4.1.0). '
               'Neither can express this network: brian2-loihi\'s LoihiNeuronGroup has one threshold per group '
               '(threshold_v_mant), resets v to 0 with a refractory period of at least one tick, takes input only '
               'as binary spikes (no bias) and fires every neuron above threshold in a tick; the spike-coding '
               'network needs a threshold per neuron (T_i = ||D_i||^2 / 2), a subtractive reset (the self term of '
               'Omega_f), graded z and u, and the greedy resolution within a sample (every-neuron-above firing '
               'runs away: the all_above rows above). nengo-loihi\'s emulator runs Nengo models through its '
               'builder (NEF ensembles, decoded connections), not a hand-set spike-coding network with these '
               'weights. So the independent re-simulation is Brian2 from the NIR file.')]
    lines += ['', f'### Weights a chip can hold, from the dispersed Monte Carlo ({data["schedule"]["runs"]} runs, '
              'Loihi formats 8/24/12)', '',
              '| filter | weight sets | switch times (s) | RMSE pos. (m) | final range max (m) | median (m) | '
              'runs < 0.1 m |', '|---|---|---|---|---|---|---|']
    for kind, rows in data['schedule']['filters'].items():
        for row in rows:
            lines.append(f'| {kind} | {row["weight_sets"]} | {row["switch_times_s"]} | {row["rmse_position_m"]:.4g} | '
                         f'{row["final_range_max_m"]:.3g} | {row["final_range_median_m"]:.3g} | '
                         f'{row.get("runs_below_0.1m", "")} |')
    lines += ['', ('Set j holds the mean of the time-varying gain over its interval, the last one the gain at the '
                   'last switch (for ever); one set is the steady-state gain. `snn_export` writes one NIR graph per '
                   'set with its interval in the metadata (nir_export.export_schedule).')]
    control = data['controller']
    lines += ['', f'### Spiking LQR beside the LQR ({control["runs"]} runs, dispersed start; snn_lqr: '
              f'{control["controller_neurons"]} neurons, leak {control["controller_leak"]} 1/s)', '',
              '| estimator | controller | final range max (m) | median (m) | delta-v (m/s) | peak thrust (m/s^2) | '
              'estimator spikes/step | controller spikes/step |', '|---|---|---|---|---|---|---|---|']
    for row in control['rows']:
        est = '' if row['estimator_spikes_per_step'] is None else f'{row["estimator_spikes_per_step"]:.3g}'
        ctl = '' if row['controller_spikes_per_step'] is None else f'{row["controller_spikes_per_step"]:.3g}'
        lines.append(f'| {row["estimator"]} | {row["controller"]} | {row["final_range_max_m"]:.4g} | '
                     f'{row["final_range_median_m"]:.4g} | {row["delta_v_mean_m_s"]:.4g} | '
                     f'{row["peak_thrust_m_s2"]:.4g} | {est} | {ctl} |')
    energy = data['energy']
    lines += ['', '### Energy per estimate of the fixed-point network (Loihi)', '',
              (f'{energy["filter"]}, {energy["precision"]}: {energy["spikes_per_step"]:.3g} spikes, '
               f'{energy["synops_per_step"]:.0f} synaptic operations and {energy["compartment_updates_per_step"]} '
               f'compartment updates per estimate (counted by the kernel) -> '
               f'{energy["energy_per_step_pj"] / 1e3:.3g} nJ; the float network\'s count for the same spikes: '
               f'{energy["float_network_synops_per_step_same_spikes"]:.0f} operations, '
               f'{energy["float_network_energy_per_step_pj_same_spikes"] / 1e3:.3g} nJ (its own run: '
               f'{energy["float_network_energy_per_step_pj_own_run"] / 1e3:.3g} nJ). Source: {energy["source"]}. '
               f'{energy["note"]}.')]
    return lines
