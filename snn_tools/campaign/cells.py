"""One campaign cell, run on any machine: settings -> scenario -> batched Monte Carlo -> row
(or, for the approach, -> flights -> their safety figures: snn_tools.campaign.approach_cells).

The part of a campaign that faces the core and knows nothing of Dask, so ``make experiments``
can call :func:`run_cell` directly and get the numbers a campaign would put in its table.

A *cell* is one filter at one point of a grid of settings, ``runs`` Monte-Carlo runs. Its runs
are stepped in batches of at most ``runs_per_task`` (the batched kernel is the fast path); each
batch is one :func:`run_chunk` call (one Dask task in a campaign) returning sums, and
:func:`combine` turns the sums of all batches into the row. Run ``b`` of a cell draws from seed
``seed + b`` whatever batch it lands in (the core's runs in a batch are independent, bit for
bit), so a cell's numbers depend on the spec only, never on the worker or the order.

:data:`SETTINGS` is the one table of allowed setting names and where each goes;
:data:`RUNNERS` says how each scenario's cells are checked, batched and combined.
"""

from __future__ import annotations

import dataclasses
import functools
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from snn_estimator.config import EstimatorConfig, silenced_neurons
from snn_estimator.sim.results import consistency_check
from snn_estimator.sim.scenarios import (
    Scenario,
    docking_scenario,
    far_range_scenario,
    rendezvous_scenario,
    van_der_pol_scenario,
)
from snn_estimator.sim.simulate import simulate
from snn_tools.campaign.approach_cells import (
    FIRST_HOLDS,
    approach_cell_scenario,
    approach_chunk,
    check_approach,
    combine_approach,
)
from snn_tools.paths import PACKAGE, SOURCE_ROOT

#: The approach from 5 km to contact (snn_estimator.sim.approach): its cells fly approaches.
APPROACH = 'approach'
#: Scenario name -> factory(preset, [factory arguments], **EstimatorConfig changes).
SCENARIOS: dict[str, Callable[..., Any]] = {
    'rendezvous': rendezvous_scenario,
    'far_range': far_range_scenario,
    'van_der_pol': van_der_pol_scenario,
    'docking': docking_scenario,  # Sec. 3.2 to contact on the docking suite (docs/sensors.md)
    APPROACH: approach_cell_scenario,  # ApproachScenario, not Scenario: see RUNNERS
}
#: The scenarios whose cells are Monte-Carlo batches of a Scenario (simulate()).
MONTE_CARLO = tuple(name for name in SCENARIOS if name != APPROACH)
#: Scenarios whose truth starts with a relative position (m): their rows get final_range_*,
#: delta_v_* and saturated_steps_mean.
RANGE_SCENARIOS = ('rendezvous', 'far_range', 'docking')
#: Runs stepped together in one task by default (100 rendezvous runs: ~3 s, ~60 MB of arrays).
RUNS_PER_TASK = 100

# Where a setting goes.
ESTIMATOR = 'estimator'  # an EstimatorConfig field, applied by the scenario factory after its preset
FACTORY = 'factory'      # a keyword argument of the scenario factory
SCENARIO = 'scenario'    # a field of the built Scenario (dataclasses.replace)
DERIVED = 'derived'      # computed from the built scenario by Setting.apply


@dataclass(frozen=True)
class Setting:
    """Where one campaign setting goes, and for which scenarios it exists."""

    target: str
    help: str = ''
    scenarios: tuple[str, ...] = tuple(SCENARIOS)
    #: For DERIVED settings: (scenario, value, seed) -> scenario.
    apply: Callable[[Scenario, Any, int], Scenario] | None = None


def _silence_fraction(scenario: Scenario, fraction, seed: int) -> Scenario:
    """Silence round(fraction N) neurons chosen with the campaign seed, by the ROS estimator's
    own rule (snn_estimator.config.silenced_neurons), so a cell silences exactly the neurons an
    estimator node with the same seed and silenced_fraction would."""
    config = scenario.estimator
    silenced = silenced_neurons(int(config.neuron_count), seed, fraction, config.silenced_neurons)
    return dataclasses.replace(scenario, estimator=config.replace(silenced_neurons=tuple(silenced)))


def _basilisk(**changes):
    """A derived setting that changes the Basilisk truth's orbit (plant: basilisk only)."""
    def apply(scenario: Scenario, value, seed: int) -> Scenario:
        if scenario.basilisk is None:
            raise ValueError(f'{", ".join(changes)} applies to the Basilisk truth only: add plant: basilisk')
        orbit = dataclasses.replace(scenario.basilisk.orbit, **{name: convert(value)
                                                                  for name, convert in changes.items()})
        return dataclasses.replace(scenario, basilisk=dataclasses.replace(scenario.basilisk, orbit=orbit))
    return apply


_RENDEZVOUS = ('rendezvous',)
_ORBITAL = ('rendezvous', 'far_range', APPROACH)
#: The scenarios whose factory builds the filters' model from the estimator's dynamics_model
#: (rendezvous and docking fly Sec. 3.2's CW model, Van der Pol has no relative motion).
_RELATIVE_MOTION = ('far_range', APPROACH)
#: Every setting a campaign spec may name (in ``grid`` or ``settings``) and where it goes. Every
#: EstimatorConfig field but the seed (the spec's own ``seed``) is one; adding a key is one line.
SETTINGS: dict[str, Setting] = {
    **{field.name: Setting(ESTIMATOR, 'see EstimatorConfig (snn_estimator/config.py)')
       for field in dataclasses.fields(EstimatorConfig) if field.name != 'seed'},
    'dynamics_model': Setting(ESTIMATOR, "the filters' model of relative motion: cw | nonlinear_circular | ss_j2 "
                              '(Schweighart-Sedwick J2, 51.6 deg)',
                              _RELATIVE_MOTION),
    'preset': Setting(FACTORY, 'default | as_published (the paper\'s literal network)',
                      ('rendezvous', 'van_der_pol', 'docking')),
    'cw_model': Setting(FACTORY, 'standard | as_published (filters and LQR use the printed Eq. 41)',
                        _RENDEZVOUS),
    'orbit_radius': Setting(FACTORY, 'target orbit radius, m', _ORBITAL),
    'plant': Setting(FACTORY, 'the truth: cw | nonlinear_circular (two-body without J2) | ss_j2 (far_range, approach) '
                     '| basilisk (two-body gravity, J2; thrust limit but on the approach)', _ORBITAL),
    'j2': Setting(DERIVED, "Basilisk truth: Earth's J2 on (true) or off", _ORBITAL,
                  apply=_basilisk(j2=bool)),
    'eccentricity': Setting(DERIVED, "Basilisk truth: the target orbit's eccentricity", _ORBITAL,
                            apply=_basilisk(eccentricity=float)),
    'sensors': Setting(FACTORY, 'position (Table 6 at every range) | by_range (relative GPS, LIDAR, '
                       'docking camera, each in its range) | angles_far (a far camera on angles alone, '
                       'LIDAR, docking camera; the 5 km observability hop)', (APPROACH,)),
    'first_hold': Setting(FACTORY, f'the hold the approach starts at: {" | ".join(FIRST_HOLDS)}', (APPROACH,)),
    'max_duration': Setting(FACTORY, 'an approach still flying after this many s ends (outcome hold, '
                            'transfer or final)', (APPROACH,)),
    'duration': Setting(SCENARIO, 'simulated time, s', MONTE_CARLO),
    'dt': Setting(SCENARIO, 'time step of the loop, s', MONTE_CARLO),
    'metric_window': Setting(SCENARIO, 'final window the readings average over, s', MONTE_CARLO),
    'truth_noise': Setting(SCENARIO, "the truth's process noise: spectral_density (variance Q dt per "
                           'step) | held_sample (w ~ N(0, Q) held over the step, ~Q dt^2)', MONTE_CARLO),
    'silenced_fraction': Setting(DERIVED, 'fraction of neurons silenced, chosen with the seed',
                                 apply=_silence_fraction),
}


def check_setting(name: str, scenario_name: str) -> Setting:
    """The table entry of ``name``; ValueError naming the key when it is unknown or does not
    apply to ``scenario_name``."""
    if scenario_name not in SCENARIOS:
        raise ValueError(f'scenario must be one of {", ".join(SCENARIOS)}; got {scenario_name!r}')
    setting = SETTINGS.get(name)
    if setting is None:
        hint = " (the spec's top-level seed seeds every cell)" if name == 'seed' else ''
        raise ValueError(f'unknown setting {name!r}{hint}; known: {", ".join(sorted(SETTINGS))}')
    if scenario_name not in setting.scenarios:
        raise ValueError(f'setting {name!r} applies to {", ".join(setting.scenarios)} only, '
                         f'not {scenario_name}')
    return setting


def build_scenario(scenario_name: str, settings: dict, seed: int) -> Scenario:
    """The scenario of one cell: factory arguments and EstimatorConfig fields first (after the
    preset), then Scenario fields, then derived settings (they may read N). ValueError names
    the setting to fix."""
    targets = {name: check_setting(name, scenario_name) for name in settings}
    factory_args = {name: value for name, value in settings.items()
                    if targets[name].target in (ESTIMATOR, FACTORY)}
    scenario = SCENARIOS[scenario_name](**factory_args)
    fields = {name: value for name, value in settings.items() if targets[name].target == SCENARIO}
    if fields:
        scenario = dataclasses.replace(scenario, **fields)
        _check_timing(scenario)
    for name, value in settings.items():
        if targets[name].target == DERIVED:
            scenario = targets[name].apply(scenario, value, seed)
    return scenario


def _check_timing(scenario: Scenario) -> None:
    """dt, duration and metric_window must give whole steps and a window inside the run."""
    for name in ('dt', 'duration', 'metric_window'):
        value = getattr(scenario, name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 < value < np.inf:
            raise ValueError(f'{name} must be a positive number of seconds, got {value!r}')
    for name in ('duration', 'metric_window'):
        steps = getattr(scenario, name) / scenario.dt
        if abs(steps - round(steps)) > 1e-9 * max(steps, 1.0):
            raise ValueError(f'{name} ({getattr(scenario, name)} s) must be a whole number of '
                             f'steps of dt = {scenario.dt} s')
    if scenario.metric_window > scenario.duration:
        raise ValueError(f'metric_window ({scenario.metric_window} s) must not exceed duration '
                         f'({scenario.duration} s)')


def check_cell(scenario_name: str, kind: str, settings: dict, seed: int) -> None:
    """Build everything the cell's runs build and take one step, so that a bad value is
    refused before a campaign starts (ValueError or TypeError from the core, naming the field)."""
    RUNNERS[scenario_name].check(build_scenario(scenario_name, settings, seed), kind, seed)


def _check_monte_carlo(scenario: Scenario, kind: str, seed: int) -> None:
    simulate(dataclasses.replace(scenario, duration=scenario.dt), kind, runs=1, seed=seed)


def chunk_bounds(runs: int, runs_per_task: int = RUNS_PER_TASK) -> list[tuple[int, int]]:
    """(first run, run count) of each batch of a cell: a function of the spec only."""
    return [(first, min(runs_per_task, runs - first)) for first in range(0, runs, runs_per_task)]


@functools.cache
def code_version() -> str:
    """The code that computed a number: ``git describe --always --dirty`` of the source checkout,
    or the installed package version (recorded per row: resumed campaigns may span commits)."""
    try:
        described = subprocess.run(['git', 'describe', '--always', '--dirty'], cwd=SOURCE_ROOT,
                                   capture_output=True, text=True, timeout=10, check=False)
        if described.returncode == 0 and described.stdout.strip():
            return described.stdout.strip()
    except (OSError, subprocess.TimeoutExpired):
        pass  # no git: fall back to the installed version
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version(PACKAGE)
    except PackageNotFoundError:
        return 'unknown'


def run_chunk(scenario_name: str, kind: str, settings: dict, seed: int, first_run: int,
              runs: int) -> dict:
    """Runs first_run .. first_run + runs - 1 of a cell (seeds seed + b), reduced by the
    scenario's runner to what its combine needs, with the code version and the worker time;
    the arrays stay on the worker. This is one Dask task."""
    started = time.perf_counter()
    scenario = build_scenario(scenario_name, settings, seed)
    partial = RUNNERS[scenario_name].chunk(scenario_name, scenario, kind, seed, first_run, runs)
    return {**partial, 'code_version': code_version(), 'wall_time_s': time.perf_counter() - started}


def _monte_carlo_chunk(scenario_name: str, scenario: Scenario, kind: str, seed: int, first_run: int,
                       runs: int) -> dict:
    """The sums of :func:`combine` over a batch of simulate()'s runs (a diverged run counted,
    its numbers left out)."""
    result = simulate(scenario, kind, runs=runs, seed=seed + first_run, trajectories=False)
    sums, kept = result.sums, ~result.diverged
    error = sums.error[kept]
    spiking = result.neuron_count > 0
    orbital = scenario_name in RANGE_SCENARIOS
    return {
        # per-step sums over runs of NEES and NIS in the window (consistency), or None
        'nees_sum': sums.nees[kept].sum(axis=0) if sums.covariance else None,
        'nis_sum': sums.nis[kept].sum(axis=0) if sums.covariance else None,
        'dof': (scenario.model.n_state, scenario.model.n_meas),
        'delta_v': result.delta_v()[kept] if orbital else None,
        'peak_thrust': sums.peak_control[kept] if orbital else None,
        'saturated_steps': result.extra['saturated_steps'][kept] if orbital else None,
        'runs': int(kept.sum()),
        'diverged': int(runs - kept.sum()),
        'samples': sums.samples,
        'sum_sq': np.sum(error * error, axis=(0, 1)),
        'sum_error': error.sum(axis=0),
        'spikes': int(sums.spikes[kept].sum()) if spiking else None,
        'spike_slots': int(kept.sum()) * scenario.steps * result.neuron_count if spiking else None,
        'final_range': result.final_range()[kept] if orbital else None,
        'capped_steps': int(result.capped_steps),
        'states': scenario.model.state_names,
    }


def combine(partials: list[dict]) -> dict:
    """The readings of a cell from its batches, in batch order: the same formulas as
    SimulationResult.rmse / mean_error / spike_fraction / final_range over all the cell's runs
    (bit for bit with one batch; to rounding with several)."""
    runs = sum(p['runs'] for p in partials)
    samples = partials[0]['samples']
    states = partials[0]['states']
    rmse = np.sqrt(sum(p['sum_sq'] for p in partials) / (runs * samples))
    mean_error = np.mean(np.abs(sum(p['sum_error'] for p in partials) / runs), axis=0)
    row = {f'rmse_{s}': float(v) for s, v in zip(states, rmse)}
    row.update({f'mean_error_{s}': float(v) for s, v in zip(states, mean_error)})
    spiking = partials[0]['spikes'] is not None
    row['spike_fraction'] = (sum(p['spikes'] for p in partials) / sum(p['spike_slots'] for p in partials)
                             if spiking else None)
    if partials[0]['final_range'] is not None:
        ranges = np.concatenate([p['final_range'] for p in partials])
        row['final_range_median'] = float(np.median(ranges))
        row['final_range_max'] = float(ranges.max())
    if partials[0]['delta_v'] is not None:
        row['delta_v_mean'] = float(np.mean(np.concatenate([p['delta_v'] for p in partials])))
        row['saturated_steps_mean'] = float(np.mean(np.concatenate([p['saturated_steps'] for p in partials])))
    if partials[0].get('peak_thrust') is not None:  # largest |u| on any axis per run, m/s^2
        peaks = np.concatenate([p['peak_thrust'] for p in partials])
        row['peak_thrust_median'] = float(np.median(peaks))
        row['peak_thrust_max'] = float(peaks.max())
    if partials[0]['nees_sum'] is not None:  # the filter's covariance judged (SimulationResult.consistency)
        for name, dof in zip(('nees', 'nis'), partials[0]['dof']):
            check = consistency_check(sum(p[f'{name}_sum'] for p in partials) / runs, runs, dof)
            row.update({f'{name}_average': check['average'], f'{name}_fraction_inside': check['fraction_inside'],
                        f'{name}_verdict': check['verdict']})
    row['capped_steps'] = sum(p['capped_steps'] for p in partials)
    row['diverged_runs'] = sum(p.get('diverged', 0) for p in partials)  # left out of every figure above
    return row


@dataclass(frozen=True)
class CellRunner:
    """How the cells of a scenario run: ``check(scenario, kind, seed)`` builds the filter and
    steps once (ValueError for a bad value), ``chunk(scenario_name, scenario, kind, seed,
    first_run, runs)`` runs one batch of a cell (one Dask task) and ``combine(partials)`` turns
    the batches into the readings of the row."""

    check: Callable[[Any, str, int], None]
    chunk: Callable[[str, Any, str, int, int, int], dict]
    combine: Callable[[list[dict]], dict]


#: Scenario name -> its runner: Monte-Carlo batches of simulate(), or flown approaches.
RUNNERS: dict[str, CellRunner] = {
    **{name: CellRunner(_check_monte_carlo, _monte_carlo_chunk, combine) for name in MONTE_CARLO},
    APPROACH: CellRunner(check_approach, approach_chunk, combine_approach),
}


def row_identity(scenario_name: str, settings: dict, seed: int = 0) -> dict:
    """The ``scenario`` and ``dynamics_model`` columns of a cell's row: the filters' model of
    relative motion as the built scenario has it (None for Van der Pol). Also fills in the rows
    of cells finished before these columns existed (spec.read_rows)."""
    model = build_scenario(scenario_name, settings, seed).model
    return {'scenario': scenario_name, 'dynamics_model': getattr(model, 'dynamics_model', None)}


def cell_row(scenario_name: str, filter_kind: str, settings: dict, runs: int, seed: int,
             partials: list[dict]) -> dict:
    """A cell's row of the table: ``filter``, ``scenario``, ``dynamics_model``, the settings,
    ``runs``, ``seed``, the readings of the scenario's runner, the code version(s) and the
    worker time."""
    return {'filter': filter_kind, **row_identity(scenario_name, settings, seed), **settings,
            'runs': runs, 'seed': seed, **RUNNERS[scenario_name].combine(partials),
            'code_version': ' '.join(sorted({p['code_version'] for p in partials})),
            'wall_time_s': sum(p['wall_time_s'] for p in partials)}


def run_cell(scenario_name: str, filter_kind: str, settings: dict, runs: int, seed: int = 0,
             runs_per_task: int = RUNS_PER_TASK) -> dict:
    """One cell in this process: the row a campaign with the same spec puts in its table."""
    partials = [run_chunk(scenario_name, filter_kind, settings, seed, first, count)
                for first, count in chunk_bounds(runs, runs_per_task)]
    return cell_row(scenario_name, filter_kind, settings, runs, seed, partials)
