"""Microseconds per estimator step with the filters' model CW or the nonlinear relative motion
(``python -m snn_tools.bench.dynamics``; issue 39).

One single-run estimator of each kind (spiking ones with ``--neurons`` neurons) replays the same
measurements of a coasting chaser 5 km behind the target (1 s steps), once on each model; the
median wall time of ``step`` after a warm-up is printed with the ratio nonlinear / CW. On the
nonlinear model a step also evaluates A(x_hat) and its zero-order hold (and, for a filter that
integrates f, four evaluations of f): numpy on 6 x 6 arrays, outside the compiled kernel.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from snn_estimator.filters.estimators import make_estimator
from snn_estimator.models import relative_motion
from snn_estimator.sim.scenarios import far_range_scenario

KINDS = ('ekf', 'emsif', 'snn_ekf', 'snn_emsif')


def measurements(steps: int, seed: int = 0) -> np.ndarray:
    """Positions (m) of a chaser coasting from 5 km behind, nonlinear truth, 0.1 m noise."""
    model, rng = relative_motion('nonlinear_circular'), np.random.default_rng(seed)
    x, zs = np.array(far_range_scenario(plant='cw').x0, dtype=float), np.empty((steps, 3))
    for k in range(steps):
        zs[k] = x[:3] + 0.1 * rng.normal(size=3)
        x = model.transition(x, np.zeros(3), 1.0)
    return zs


def step_time(kind: str, dynamics_model: str, zs: np.ndarray, neurons: int, warm_up: int = 20) -> float:
    """Median wall time of one ``step``, microseconds."""
    scenario = far_range_scenario(plant='cw', dynamics_model=dynamics_model)
    estimator = make_estimator(kind, scenario.estimator.replace(neuron_count=neurons), scenario.model)
    u, times = np.zeros(3), []
    for k, z in enumerate(zs):
        start = time.perf_counter()
        estimator.step(z, u, 1.0)
        if k >= warm_up:
            times.append(time.perf_counter() - start)
    return 1e6 * float(np.median(times))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--steps', type=int, default=500, help='steps replayed per filter')
    parser.add_argument('--neurons', type=int, default=200, help='neurons of the spiking filters')
    args = parser.parse_args(argv)
    zs = measurements(args.steps)
    print(f'us per step, median of {args.steps} steps (N = {args.neurons} for the spiking filters)')
    print(f'{"kind":<12}{"cw":>10}{"nonlinear":>12}{"ratio":>8}')
    for kind in KINDS:
        cw, nonlinear = (step_time(kind, model, zs, args.neurons) for model in ('cw', 'nonlinear_circular'))
        print(f'{kind:<12}{cw:>10.1f}{nonlinear:>12.1f}{nonlinear / cw:>8.1f}')


if __name__ == '__main__':
    main()
