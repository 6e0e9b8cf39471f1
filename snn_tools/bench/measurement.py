"""Cost of the measurement models per step: what a filter will call each step (h, H, validity)
and what the sensor draws, for 1 run (a ROS node) and a batch, against the linear position.

``python -m snn_tools.bench.measurement [--repeat 2000] [--runs 100] [--out results/measurement_bench.json]``

Best of five passes, in microseconds per call. PositionSensor is today's sensor, the reference
for the ``position`` model's MeasurementSensor.

``filter_step_us``: what one ``Estimator.step`` costs with each model (the filter re-linearises a
nonlinear one every step: h, H, residual, C^+ in numpy, then the compiled kernel), for 1 run and
per run of a batch, median over 300 steps of a free CW drift, against the filter on the model's
own C (``model_c``, the path of every position result).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from snn_estimator import ClohessyWiltshire, EstimatorConfig, make_estimator
from snn_estimator.measurements import MODELS, make_model
from snn_estimator.plant.sensors import MeasurementSensor, PositionSensor

FILTER_KINDS_TIMED = ('ekf', 'emsif_weighted', 'snn_ekf')
X_DRIFT = np.array([70.0, 30.0, -5.0, -0.1, -0.05, 0.02])

NOISE = {'position': 1e-2, 'range_azimuth_elevation': [1e-4, 1e-6, 1e-6], 'line_of_sight': [1e-6, 1e-6],
         'range': 1e-4, 'range_rate': 1e-6}


def _best_us(call, x: np.ndarray, repeat: int) -> float:
    best = float('inf')
    for _ in range(5):
        start = time.perf_counter()
        for _ in range(repeat):
            call(x)
        best = min(best, (time.perf_counter() - start) / repeat)
    return best * 1e6


def measure(repeat: int, runs: int) -> dict:
    rng = np.random.default_rng(0)
    figures = {}
    for batch in (1, runs):
        x = np.array([70.0, 30.0, -5.0, -1.7, -0.9, 0.25]) + rng.normal(size=(batch, 6))
        reference = PositionSensor(ClohessyWiltshire(), 1e-2, range(batch))
        rows = {'PositionSensor.measure': _best_us(reference.measure, x, repeat)}
        for name in MODELS:
            model = make_model(name, NOISE.get(name, 1e-4), field_of_view=3.0)  # any model, even a new one
            sensor = MeasurementSensor(model, range(batch))
            rows[name] = {'h_us': _best_us(model.h, x, repeat), 'jacobian_us': _best_us(model.jacobian, x, repeat),
                          'validity_us': _best_us(model.validity, x, repeat),
                          'sensor_measure_us': _best_us(sensor.measure, x, repeat)}
        figures[f'runs={batch}'] = rows
    return figures


def _median_step_us(estimator, zs, batch: int) -> float:
    u = np.zeros((batch, 3))
    samples = np.empty(len(zs))
    for k, z in enumerate(zs):
        start = time.perf_counter()
        estimator.step(z, u, 0.1)
        samples[k] = time.perf_counter() - start
    return float(np.median(samples) * 1e6)


def filter_costs(runs: int, steps: int = 300) -> dict:
    """us per Estimator.step (per run for the batch) with each model, by filter kind."""
    cw = ClohessyWiltshire()
    truth = np.array([cw.transition(X_DRIFT, np.zeros(3), 0.1 * k) for k in range(steps)])
    figures = {}
    for batch in (1, runs):
        rows = {}
        for name in ('model_c',) + tuple(MODELS):
            model = None if name == 'model_c' else make_model(name, NOISE.get(name, 1e-4),
                                                               mounting_rotation=(0.0, 0.0, 1.0, 0.0))
            zs = (truth[:, :3] if model is None else model.h(truth))
            zs = np.repeat(zs[:, None, :], batch, axis=1)
            noise = 1e-2 if model is None else model.noise
            config = EstimatorConfig(measurement_noise=noise, initial_state=tuple(X_DRIFT), neuron_count=200,
                                     initial_covariance=(1e-5,) * 3 + (1e-7,) * 3)
            rows[name] = {}
            for kind in FILTER_KINDS_TIMED:
                best = float('inf')
                for _ in range(3):
                    estimator = make_estimator(kind, config, runs=batch, measurement=model)
                    _median_step_us(estimator, zs[:5], batch)  # compile, warm caches
                    estimator.reset()
                    best = min(best, _median_step_us(estimator, zs, batch) / batch)
                rows[name][kind] = best
        figures[f'runs={batch}'] = rows
    return figures


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='measurement_bench', description=__doc__.split('\n\n')[0])
    parser.add_argument('--repeat', type=int, default=2000, help='calls per pass (best of 5 passes)')
    parser.add_argument('--runs', type=int, default=100, help='the batch size besides 1 run')
    parser.add_argument('--steps', type=int, default=300, help='filter steps timed per model and kind')
    parser.add_argument('--out', type=Path, help='also write the figures as JSON')
    args = parser.parse_args(argv)
    figures = measure(args.repeat, args.runs)
    steps = filter_costs(args.runs, args.steps)
    for batch, rows in figures.items():
        print(f'{batch}: PositionSensor.measure {rows["PositionSensor.measure"]:.1f} us')
        print(f'  {"model":26s} {"h":>7s} {"H":>7s} {"valid":>7s} {"sensor":>7s}  (us per call)')
        for name in MODELS:
            r = rows[name]
            print(f'  {name:26s} {r["h_us"]:7.1f} {r["jacobian_us"]:7.1f} {r["validity_us"]:7.1f} '
                  f'{r["sensor_measure_us"]:7.1f}')
    for batch, rows in steps.items():
        print(f'Estimator.step, {batch} (us per run): ' + ', '.join(FILTER_KINDS_TIMED))
        for name, row in rows.items():
            print(f'  {name:26s} ' + ' '.join(f'{row[kind]:8.1f}' for kind in FILTER_KINDS_TIMED))
    if args.out:
        rounded = {b: {k: (round(v, 2) if isinstance(v, float) else {kk: round(vv, 2) for kk, vv in v.items()})
                       for k, v in rows.items()} for b, rows in figures.items()}
        rounded['filter_step_us'] = {b: {name: {k: round(v, 2) for k, v in row.items()} for name, row in rows.items()}
                                     for b, rows in steps.items()}
        args.out.write_text(json.dumps(rounded, indent=2) + '\n')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
