"""``snn_bench``: microseconds per estimator step on the rendezvous, beside a dense reference.

For every filter and N in (50, 100, 200, 300) it replays the measurements and controls of one
closed-loop rendezvous through a fresh single-run estimator and reports the median wall time
of ``step`` (best of three passes), next to :mod:`snn_estimator.filters.reference` (plain numpy that
forms the paper's N x N weight products every step) timed in the same run. It also times a
100-run Monte Carlo of each filter. Results go to stdout and ``--out`` (JSON).

In the same run it times filterpy's ``KalmanFilter`` (``predict(u)`` then ``update(z)``, plain
numpy, the usual reference a Python user would reach for) on the same CW model, dimensions
(6 states, 3 inputs, 3 measurements), noise and inputs: key ``filterpy_kf_us``, printed with
its ratio to SNN-EMSIF at N = 300 (``filterpy_kf_over_snn_emsif_300``).

And the EKF and SNN-EKF (N = 200) on the far-range approach with the filters' model CW and the
nonlinear relative motion, whose weights follow A(x_hat) each step (key ``nonlinear_model``,
:mod:`snn_tools.bench.dynamics`; issue 39's goal: SNN-EKF nonlinear / CW <= 1.5).
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from snn_estimator.filters.estimators import FILTER_KINDS, make_estimator
from snn_estimator.filters.reference import DenseFilter, DenseSpikingFilter
from snn_estimator.plant.control import lqr_control, lqr_gain
from snn_estimator.plant.sensors import PositionSensor
from snn_estimator.plant.truth import Plant
from snn_estimator.sim.scenarios import rendezvous_scenario
from snn_estimator.sim.simulate import simulate
from snn_tools.experiments.tables import time_steps
from snn_tools.progress import track

from . import dynamics

NEURON_COUNTS = (50, 100, 200, 300)


def record_inputs(scenario, steps: int):
    """z_k and u_k of one EMSIF-driven closed-loop rendezvous."""
    model = scenario.model
    plant = Plant(model, scenario.x0, scenario.process_noise)
    sensor = PositionSensor(model, scenario.measurement_noise)
    gain = lqr_gain(model, scenario.lqr_state_weight, scenario.lqr_input_weight)
    driver = make_estimator('emsif', scenario.estimator, model)
    zs, us = np.empty((steps, model.n_meas)), np.empty((steps, model.n_input))
    for k in range(steps):
        us[k] = lqr_control(gain, driver.x_hat)
        zs[k] = sensor.measure(plant.x)[0]
        driver.step(zs[k], us[k], scenario.dt)
        plant.step(us[k], scenario.dt)
    return zs, us


class FilterpyStep:
    """filterpy's linear ``KalmanFilter`` on the scenario's discretised CW model, with the
    estimators' ``step(z, u, dt)`` signature so :func:`time_steps` times it alike."""

    def __init__(self, scenario):
        from filterpy.kalman import KalmanFilter
        model = scenario.model
        phi, gamma = model.discrete_matrices(scenario.dt)
        kf = KalmanFilter(dim_x=model.n_state, dim_z=model.n_meas, dim_u=model.n_input)
        kf.F, kf.B, kf.H = phi, gamma, model.measurement_matrix
        kf.Q = np.asarray(scenario.process_noise, dtype=float)
        kf.R = np.asarray(scenario.measurement_noise, dtype=float) * np.eye(model.n_meas)
        kf.x = np.asarray(scenario.x0, dtype=float).reshape(-1, 1).copy()
        self.kf = kf

    def step(self, z, u, dt):
        self.kf.predict(u=u.reshape(-1, 1))
        self.kf.update(z.reshape(-1, 1))
        return self.kf.x


def time_filterpy(scenario, zs, us) -> float | None:
    """us per filterpy predict+update (best of three medians); None without filterpy."""
    try:
        FilterpyStep(scenario)
    except ImportError:
        return None
    time_steps(FilterpyStep(scenario), zs[:100], us[:100], scenario.dt)
    return best_median(lambda: FilterpyStep(scenario), zs, us, scenario.dt)


@contextmanager
def filter_doing_nothing():
    """Within: simulate's compiled loop steps a filter that does nothing (its state stays as
    set up, the step returns OK at once) around the same truth, sensor, noise draws, LQR,
    metrics and bookkeeping: the loop's own cost, what no filter can take below it."""
    import numba

    from snn_estimator.sim import compiled_loop

    @numba.njit(cache=True)
    def nothing_step(consts, state, network, running, dt, dynamics, drift, z, u, noise):
        return 0, 0  # kernels.STATUS_OK, no run capped

    original = compiled_loop.loop_kernel
    compiled_loop.loop_kernel = lambda step: original(nothing_step)
    try:
        yield
    finally:
        compiled_loop.loop_kernel = original


def noise_draw_cost(scenario, runs: int) -> float:
    """CPU seconds of the loop's Gaussian draws for ``runs`` runs of ``scenario`` (the plant's
    and the sensor's, from one generator per run, in the compiled loop's chunks)."""
    from snn_estimator.sim.compiled_loop import CHUNK
    generators = [np.random.default_rng(b) for b in range(2 * runs)]
    widths = (scenario.model.n_state, scenario.measurement_noise.shape[0])
    clock = time.thread_time()
    for first in range(0, scenario.steps, CHUNK):
        count = min(CHUNK, scenario.steps - first)
        for width, half in zip(widths, (generators[:runs], generators[runs:])):
            out = np.empty((runs, count, width))
            for b, generator in enumerate(half):
                out[b] = generator.standard_normal((count, width))
    return time.thread_time() - clock


def closed_loop_costs(scenario, kind: str, runs: int = 100, passes: int = 3) -> dict:
    """us per run-step at ``runs`` runs of the whole closed loop, compiled (keeping the
    trajectories, and only the window's sums as campaigns do) and reference (simulate's
    engines), and of the filter's own batched ``step`` replaying the compiled run's measurements
    and controls (what the loop wraps): the thread's CPU time (other processes on the machine
    do not count), best of ``passes``, interleaved."""
    steps = scenario.steps
    simulate(scenario, kind, runs=2, engine='compiled')  # compile (or load) the loop
    first = simulate(scenario, kind, runs=runs, engine='compiled')
    rng = np.random.default_rng(0)
    zs = first.truth[:, :-1, :3] + rng.standard_normal((runs, steps, 3)) * np.sqrt(scenario.measurement_noise[0, 0])
    zs, us = np.ascontiguousarray(zs.transpose(1, 0, 2)), np.ascontiguousarray(first.control.transpose(1, 0, 2))
    with filter_doing_nothing():
        simulate(scenario, kind, runs=2, engine='compiled', trajectories=False)  # compile (or load) it
    best = dict.fromkeys(('compiled', 'compiled_sums', 'reference', 'filter_step', 'loop_around_nothing',
                          'noise_draws'), math.inf)
    for _ in range(passes):
        for name, engine, trajectories in (('compiled', 'compiled', True), ('compiled_sums', 'compiled', False),
                                           ('reference', 'reference', True)):
            result = simulate(scenario, kind, runs=runs, engine=engine, trajectories=trajectories)
            best[name] = min(best[name], result.extra['cpu_time'])
        with filter_doing_nothing():
            result = simulate(scenario, kind, runs=runs, engine='compiled', trajectories=False)
        best['loop_around_nothing'] = min(best['loop_around_nothing'], result.extra['cpu_time'])
        best['noise_draws'] = min(best['noise_draws'], noise_draw_cost(scenario, runs))
        estimator = make_estimator(kind, scenario.estimator, scenario.model, runs=runs, seeds=list(range(runs)))
        clock = time.thread_time()
        for k in range(steps):
            estimator.step(zs[k], us[k], scenario.dt)
        best['filter_step'] = min(best['filter_step'], time.thread_time() - clock)
    costs = {name: round(1e6 * seconds / (runs * steps), 3) for name, seconds in best.items()}
    for name in ('compiled', 'compiled_sums', 'reference', 'loop_around_nothing'):
        costs[f'{name}_over_filter_step'] = round(best[name] / best['filter_step'], 2)
    return costs


def best_median(make, zs, us, dt, passes: int = 3) -> float:
    best = math.inf
    for _ in range(passes):
        best = min(best, time_steps(make(), zs, us, dt))
    return best


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='snn_bench', description=__doc__.split('\n\n')[0])
    parser.add_argument('--out', type=Path, default=Path('results/bench.json'))
    parser.add_argument('--dense-steps', type=int, default=600,
                        help='steps timed for the (slow) dense reference (default 600)')
    parser.add_argument('--mc-runs', type=int, default=100, help='runs of the timed Monte Carlo')
    args = parser.parse_args(argv)
    scenario = rendezvous_scenario()
    zs, us = record_inputs(scenario, scenario.steps)
    dt = scenario.dt
    print(f'snn_rendezvous benchmark: rendezvous, {scenario.steps} steps replayed, dt = {dt} s; '
          f'{platform.processor() or platform.machine()}, Python {platform.python_version()}')
    print(f'{"filter":<16}{"N":>5}{"compiled us/step":>18}{"dense us/step":>15}{"ratio":>8}')
    results: dict = {}
    for kind, spec in track(FILTER_KINDS.items(), 'filters', 'snn_bench'):  # progress on a terminal
        for neurons in NEURON_COUNTS:
            config = scenario.estimator.replace(neuron_count=neurons)

            def fresh(config=config, kind=kind):
                return make_estimator(kind, config, scenario.model)

            time_steps(fresh(), zs[:100], us[:100], dt)  # compile, warm caches
            compiled = best_median(fresh, zs, us, dt)
            dense_class = DenseSpikingFilter if spec.spiking else DenseFilter
            dense = best_median(lambda dense_class=dense_class: dense_class(fresh()), zs[:args.dense_steps],
                                us[:args.dense_steps], dt, passes=1)
            results.setdefault(kind, {})[str(neurons)] = {
                'us_per_step': round(compiled, 2), 'dense_reference_us_per_step': round(dense, 2)}
            print(f'{kind:<16}{neurons:>5}{compiled:>18.1f}{dense:>15.1f}{dense / compiled:>7.0f}x')
            sys.stdout.flush()
    filterpy_us = time_filterpy(scenario, zs, us)
    if filterpy_us is None:
        print('\nfilterpy KalmanFilter: not installed (pip install filterpy; it is in the test extra)')
    else:
        results['filterpy_kf_us'] = round(filterpy_us, 2)
        snn = results.get('snn_emsif', {}).get('300', {}).get('us_per_step')
        line = f'\nfilterpy KalmanFilter predict+update, same model: {filterpy_us:.1f} us/step'
        if snn:
            results['filterpy_kf_over_snn_emsif_300'] = round(filterpy_us / snn, 2)
            line += f' = {filterpy_us / snn:.2f}x SNN-EMSIF N = 300 ({snn:.1f} us)'
        print(line)
    print()
    results['nonlinear_model'] = dynamics.rows()
    print(f'\n{args.mc_runs}-run rendezvous Monte Carlo (360 s each, dispersed start), us of CPU per run-step: '
          'the closed loop compiled (with trajectories; with the sums only, as campaigns run) and in Python '
          "(simulate engine=compiled | reference) against the filter's own batched step "
          "(goal: loop <= 1.25x the step); 'nothing': the sums loop around a filter that does nothing "
          "(the loop's own cost; the goal needs it <= 0.25x the step), 'draws' the Gaussian draws within it")
    print(f'{"filter":<20}{"loop":>8}{"sums":>8}{"python":>9}{"step":>8}{"loop/step":>11}{"sums/step":>11}'
          f'{"python/step":>13}{"wall s":>8}{"nothing":>9}{"draws":>7}{"nothing/step":>14}')
    monte_carlo, wall = {}, {}
    dispersed = rendezvous_scenario(initial_state_dispersion=True)
    for kind in track(FILTER_KINDS, 'filters', 'Monte Carlo'):
        costs = monte_carlo[kind] = closed_loop_costs(dispersed, kind, args.mc_runs)
        wall[kind] = round(costs['compiled'] * args.mc_runs * dispersed.steps * 1e-6, 2)
        print(f'{kind:<20}{costs["compiled"]:>8.2f}{costs["compiled_sums"]:>8.2f}{costs["reference"]:>9.2f}'
              f'{costs["filter_step"]:>8.2f}{costs["compiled_over_filter_step"]:>10.2f}x'
              f'{costs["compiled_sums_over_filter_step"]:>10.2f}x{costs["reference_over_filter_step"]:>12.2f}x'
              f'{wall[kind]:>8.2f}{costs["loop_around_nothing"]:>9.2f}{costs["noise_draws"]:>7.2f}'
              f'{costs["loop_around_nothing_over_filter_step"]:>13.2f}x')
        sys.stdout.flush()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + '\n')
    (args.out.parent / 'bench_monte_carlo.json').write_text(json.dumps(
        {'runs': args.mc_runs, 'steps': dispersed.steps, 'wall_time_s': wall,
         'us_per_run_step': monte_carlo}, indent=2) + '\n')
    print(f'\nwrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
