"""The local, synchronous spike rule against the greedy one and the non-spiking twin (issue 40).

A chip resolves no global argmax: each tick every neuron fires from its own potential
(``spike_rule: synchronous``, docs/decisions.md, 58-59). Per scenario (position, LIDAR; dispersed
start) and spiking kind, :func:`measure` flies the closed loop with the twin, the greedy rule
and the synchronous rule at its defaults and the other SETTINGS, the same seeds for all, and
keeps position RMSE over the metric window, spikes per step, ticks per sample and the runs that
diverged or were lost. ``python -m snn_tools.neuromorphic.tables --local-rule-only`` (``make
spike-rules``) writes it into ``results/neuromorphic.json`` and its table into neuromorphic.md.
"""

from __future__ import annotations

import time

import numpy as np

from snn_estimator import defaults as D
from snn_estimator.catalog import TWIN_OF
from snn_estimator.sim.scenarios import rendezvous_scenario, sensor_rendezvous_scenario
from snn_estimator.sim.simulate import simulate
from snn_estimator.spiking.costs import CHIPS, CostModel

#: The kinds that converge from the dispersed start (catalog.CONVERGES_FROM_DISPERSION) and spike.
KINDS = ('snn_ekf', 'snn_emsif_weighted')
SCENARIOS = {'position': lambda: rendezvous_scenario(initial_state_dispersion=True),
             'lidar': lambda: sensor_rendezvous_scenario(initial_state_dispersion=True)}
#: The synchronous settings measured: the defaults first, then a narrower box, and a narrower box
#: with a finer tick.
SETTINGS = (
    {'ticks_per_sample': D.SYNCHRONOUS_TICKS, 'threshold_widening': D.SYNCHRONOUS_WIDENING,
     'refractory_ticks': D.SYNCHRONOUS_REFRACTORY, 'firing_slots': D.SYNCHRONOUS_SLOTS},
    {'ticks_per_sample': 100, 'threshold_widening': 1.0, 'refractory_ticks': 0, 'firing_slots': 10},
    {'ticks_per_sample': 200, 'threshold_widening': 1.0, 'refractory_ticks': 0, 'firing_slots': 20},
)
#: A run counts as lost when its position RMSE over the window exceeds this (m).
LOST_M = 1.0
#: The issue's goal for the best setting: RMSE / twin and spikes / greedy.
GOAL_RMSE_RATIO, GOAL_SPIKE_RATIO = 1.2, 2.0


def _row(result, rule: str, setting: dict, wall: float) -> dict:
    """The figures of one simulate() result (trajectories=False)."""
    sums = result.sums
    kept = ~result.diverged
    error = sums.error[kept][:, :, :3]
    per_run = np.sqrt(np.mean(np.sum(error ** 2, axis=2), axis=1))
    row = {'rule': rule, **setting, 'runs': int(result.runs), 'diverged': int(result.diverged.sum()),
           'lost': int(np.sum(per_run > LOST_M)),
           'rmse_position_m': float(np.linalg.norm(result.rmse()[:3])),
           'rmse_position_median_run_m': float(np.median(per_run)),
           'final_range_median_m': float(np.nanmedian(result.final_range())),
           'capped_steps': int(result.capped_steps), 'wall_s': round(wall, 1)}
    if result.neuron_count:
        row['spikes_per_step'] = float(sums.spikes[kept].mean() / sums.steps)
    return row


def _run(scenario, kind: str, runs: int, seed: int, rule: str | None, setting: dict) -> dict:
    config = scenario.estimator if rule is None else scenario.estimator.replace(spike_rule=rule, **setting)
    started = time.perf_counter()
    result = simulate(scenario, kind, runs=runs, seed=seed, config=config, trajectories=False)
    return _row(result, rule or 'twin', setting, time.perf_counter() - started)


def measure(runs: dict, seed: int = 0, kinds=KINDS, settings=SETTINGS, report=print) -> dict:
    """Rows per scenario and kind: the twin, greedy, and each synchronous setting, over ``runs[scenario]``
    runs from seed ``seed``. Ratios against the twin's RMSE and greedy's spikes."""
    started = time.perf_counter()
    out = {'runs': dict(runs), 'seed': seed, 'lost_m': LOST_M, 'rows': []}
    for name, count in runs.items():
        scenario = SCENARIOS[name]()
        out.setdefault('sample_period_s', scenario.dt)
        out.setdefault('neurons', int(scenario.estimator.neuron_count))
        for kind in kinds:
            twin = _run(scenario, TWIN_OF[kind], count, seed, None, {})
            greedy = _run(scenario, kind, count, seed, 'greedy', {})
            rows = [twin, greedy] + [_run(scenario, kind, count, seed, 'synchronous', s) for s in settings]
            for row in rows:
                row.update(scenario=name, kind=kind if row['rule'] != 'twin' else TWIN_OF[kind],
                           rmse_ratio=row['rmse_position_m'] / twin['rmse_position_m'])
                if 'spikes_per_step' in row:
                    row['spike_ratio'] = row['spikes_per_step'] / greedy['spikes_per_step']
                report(f"{name} {row['kind']} {row['rule']} {setting_label(row)}: RMSE {row['rmse_position_m']:.4g} m "
                       f"({row['rmse_ratio']:.3f}x twin), spikes {row.get('spikes_per_step', 0):.1f}/step, "
                       f"{row['wall_s']} s")
            out['rows'] += rows
    out['wall_time_s'] = round(time.perf_counter() - started, 1)
    return out


def setting_label(row: dict) -> str:
    if row['rule'] != 'synchronous':
        return ''
    return (f"T = {row['ticks_per_sample']}, K = {row['firing_slots']}, w = {row['threshold_widening']:g}, "
            f"R = {row['refractory_ticks']}")


def neuron_updates(row: dict, neurons: int) -> str:
    """Neuron updates per estimate: T ticks of all N neurons (synchronous); one pass over the N
    neurons per spike plus the one that finds none above threshold (greedy's argmax)."""
    if row['rule'] == 'synchronous':
        return f"{row['ticks_per_sample'] * neurons:.0f}"
    if row['rule'] == 'greedy':
        return f"{(row['spikes_per_step'] + 1.0) * neurons:.0f}"
    return ''


def loihi_energy_nj(row: dict, neurons: int, states: int = 6, measurements: int = 3, inputs: int = 3) -> str:
    """Energy per estimate on Loihi (costs.CHIPS, Davies et al. 2018), nJ: the neuron updates of
    :func:`neuron_updates` at the inactive-update price, each spike's active-update difference and
    its synaptic events (costs.CostModel.synops_per_spike: N - 1 fast, N slow, n readout), and the
    graded inputs F_k z + F u set once per sample (N (m + nu)); host work (the gain) excluded."""
    updates = neuron_updates(row, neurons)
    if not updates:
        return ''
    model = CostModel(neurons, states, measurements, inputs)
    spikes = row['spikes_per_step']
    synops = spikes * model.synops_per_spike + model.input_synops
    loihi = CHIPS['loihi']
    return f"{(synops * loihi.synop_pj + float(updates) * loihi.neuron_update_pj + spikes * loihi.spike_pj) / 1e3:.0f}"


def markdown(data: dict) -> list[str]:
    """The section of results/neuromorphic.md."""
    runs = ', '.join(f'{name} {count}' for name, count in data['runs'].items())
    fewer = data['runs'].get('lidar', 100) < 100
    lines = ['', '## A rule a chip can run: the local, synchronous spike rule (issue 40)', '',
             (f'Generated by `make spike-rules` (`snn_tools.neuromorphic.local_rule`; {data["wall_time_s"]} s). '
              f'Dispersed start, seeds {data["seed"]}.. ; runs: {runs}'
              + (' (LIDAR fewer than 100 runs, to save time).' if fewer else '.')
              + ' Position RMSE over the last 60 s (norm of the x, y, z RMSE), ratio to the non-spiking '
              "twin's; spikes per 0.1 s step, ratio to the greedy rule's. `synchronous`: T ticks per sample, "
              'every neuron in its slot ((t + i) mod K = 0) whose potential is above (1 + w) ||D_i||^2 / 2 '
              'fires, all in the same tick, R refractory ticks (docs/decisions.md, 58-59). A chip spends T '
              f'ticks per estimate, each updating all N = {data["neurons"]} neurons; greedy spends one argmax '
              'pass over the N per spike and one more (no chip runs it): neuron updates per estimate count '
              'both, synaptic events (N per spike, the Gram row) come on top alike. Energy per estimate on '
              'Loihi (Davies et al. 2018: 52 pJ per neuron update, 23.6 pJ per synaptic event, 30.7 pJ more '
              'per spike): those updates, each spike\'s 2N - 1 + n synaptic events and the N (m + nu) graded '
              'inputs of the sample; the host\'s gain is not counted. A chip pays for its ticks: at T = 100 '
              'the updates of idle neurons dominate. '
              f'Lost: runs whose position RMSE exceeds {data["lost_m"]:g} m; diverged: '
              'runs left out by simulate (non-finite, or the spike cap).'), '',
             '| scenario | kind | rule | setting | RMSE pos. (m) | / twin | spikes/step | / greedy | ticks/sample '
             '| neuron updates/estimate | Loihi nJ/estimate | lost | diverged |',
             '|---|---|---|---|---|---|---|---|---|---|---|---|---|']
    for row in data['rows']:
        spikes = f"{row['spikes_per_step']:.1f}" if 'spikes_per_step' in row else ''
        ratio = f"{row['spike_ratio']:.2f}" if 'spike_ratio' in row else ''
        ticks = row.get('ticks_per_sample', '') if row['rule'] == 'synchronous' else ''
        lines.append(f"| {row['scenario']} | {row['kind']} | {row['rule']} | {setting_label(row)} | "
                     f"{row['rmse_position_m']:.4g} | {row['rmse_ratio']:.3f} | {spikes} | {ratio} | {ticks} | "
                     f"{neuron_updates(row, data['neurons'])} | {loihi_energy_nj(row, data['neurons'])} | "
                     f"{row['lost']} | {row['diverged']} |")
    met = [row for row in data['rows'] if row['rule'] == 'synchronous' and row['rmse_ratio'] <= GOAL_RMSE_RATIO
           and row['spike_ratio'] <= GOAL_SPIKE_RATIO and not row['lost'] and not row['diverged']]
    lines += ['', (f'Goal of issue 40 (RMSE within {GOAL_RMSE_RATIO}x the twin and spikes within '
                   f'{GOAL_SPIKE_RATIO}x greedy, no run lost): met by '
                   + ('; '.join(f"{r['scenario']} {r['kind']} ({setting_label(r)})" for r in met) if met else 'no row')
                   + '.')]
    return lines
