"""Microseconds per estimator step with the filters' model CW or the nonlinear relative motion
(``python -m snn_tools.bench.dynamics``; ``make bench`` prints and writes the rows of
:data:`BENCH_KINDS`; issue 39).

One single-run estimator of each kind (spiking ones with ``--neurons`` neurons) replays the same
measurements of a coasting chaser 5 km behind the target (1 s steps), once on each model; the
median wall time of ``step`` after a warm-up, best of three passes (the two models interleaved,
so a drifting machine shifts both), is printed with the ratio nonlinear / CW. On the nonlinear
model a step also evaluates A(x_hat) and its zero-order hold (and, for a filter that integrates
f, one RK4 step of f): one compiled call per step (snn_estimator.filters.model_kernels,
docs/decisions.md, 62). Issue 39's goal: the SNN-EKF's ratio <= 1.5 at N = 200.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from snn_estimator.filters.estimators import make_estimator
from snn_estimator.models import relative_motion
from snn_estimator.sim.scenarios import far_range_scenario
from snn_tools.experiments.tables import time_steps

KINDS = ('ekf', 'emsif', 'snn_ekf', 'snn_emsif')
#: The rows ``make bench`` adds (snn_tools.bench.steps): the issue's SNN-EKF and its twin.
BENCH_KINDS = ('ekf', 'snn_ekf')
MODELS = ('cw', 'nonlinear_circular')


def measurements(steps: int, seed: int = 0) -> np.ndarray:
    """Positions (m) of a chaser coasting from 5 km behind, nonlinear truth, 0.1 m noise."""
    model, rng = relative_motion('nonlinear_circular'), np.random.default_rng(seed)
    x, zs = np.array(far_range_scenario(plant='cw').x0, dtype=float), np.empty((steps, 3))
    for k in range(steps):
        zs[k] = x[:3] + 0.1 * rng.normal(size=3)
        x = model.transition(x, np.zeros(3), 1.0)
    return zs


def fresh(kind: str, dynamics_model: str, neurons: int):
    """A single-run estimator of ``kind`` on the far-range scenario with the filters' model named."""
    scenario = far_range_scenario(plant='cw', dynamics_model=dynamics_model)
    return make_estimator(kind, scenario.estimator.replace(neuron_count=neurons), scenario.model)


def step_times(kind: str, zs: np.ndarray, neurons: int, passes: int = 3, warm_up: int = 50) -> dict:
    """us per ``step`` on each model (:data:`MODELS`): the median over ``zs`` after ``warm_up``
    steps, best of ``passes``, the models interleaved; and the ratio nonlinear / CW."""
    us = np.zeros((len(zs), 3))
    best = dict.fromkeys(MODELS, math.inf)
    for _ in range(passes):
        for model in MODELS:
            estimator = fresh(kind, model, neurons)
            time_steps(estimator, zs[:warm_up], us[:warm_up], 1.0)
            best[model] = min(best[model], time_steps(estimator, zs[warm_up:], us[warm_up:], 1.0))
    return {'cw_us': round(best['cw'], 2), 'nonlinear_us': round(best['nonlinear_circular'], 2),
            'ratio': round(best['nonlinear_circular'] / best['cw'], 2)}


def rows(kinds=BENCH_KINDS, steps: int = 2000, neurons: int = 200, print_rows: bool = True) -> dict:
    """:func:`step_times` of each of ``kinds`` on ``steps`` timed steps, printed as a table."""
    zs = measurements(steps + 50)
    if print_rows:
        print(f'us per step, far range (5 km, 1 s steps), CW against the nonlinear model: median of {steps} '
              f'steps, best of 3 (N = {neurons}; goal SNN-EKF nonlinear / CW <= 1.5)')
        print(f'{"filter":<16}{"cw":>10}{"nonlinear":>12}{"ratio":>8}')
    results = {}
    for kind in kinds:
        row = results[kind] = step_times(kind, zs, neurons)
        if print_rows:
            print(f'{kind:<16}{row["cw_us"]:>10.1f}{row["nonlinear_us"]:>12.1f}{row["ratio"]:>7.2f}x', flush=True)
    return {'neurons': neurons, 'steps': steps, 'dt_s': 1.0, 'kinds': results}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--steps', type=int, default=2000, help='steps timed per filter and pass')
    parser.add_argument('--neurons', type=int, default=200, help='neurons of the spiking filters')
    parser.add_argument('--kinds', nargs='+', default=list(KINDS), choices=KINDS)
    parser.add_argument('--out', type=Path, help='write the rows as JSON')
    args = parser.parse_args(argv)
    results = rows(args.kinds, args.steps, args.neurons)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=2) + '\n')


if __name__ == '__main__':
    main()
