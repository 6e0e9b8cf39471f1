"""Cost of the measurement models per step: what a filter will call each step (h, H, validity)
and what the sensor draws, for 1 run (a ROS node) and a batch, against the linear position.

``python -m snn_tools.measurement_bench [--repeat 2000] [--runs 100] [--out results/measurement_bench.json]``

Best of five passes, in microseconds per call. PositionSensor is today's sensor, the reference
for the ``position`` model's MeasurementSensor.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from snn_estimator import ClohessyWiltshire
from snn_estimator.measurements import MODELS, make_model
from snn_estimator.offline.blocks import MeasurementSensor, PositionSensor

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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='measurement_bench', description=__doc__.split('\n\n')[0])
    parser.add_argument('--repeat', type=int, default=2000, help='calls per pass (best of 5 passes)')
    parser.add_argument('--runs', type=int, default=100, help='the batch size besides 1 run')
    parser.add_argument('--out', type=Path, help='also write the figures as JSON')
    args = parser.parse_args(argv)
    figures = measure(args.repeat, args.runs)
    for batch, rows in figures.items():
        print(f'{batch}: PositionSensor.measure {rows["PositionSensor.measure"]:.1f} us')
        print(f'  {"model":26s} {"h":>7s} {"H":>7s} {"valid":>7s} {"sensor":>7s}  (us per call)')
        for name in MODELS:
            r = rows[name]
            print(f'  {name:26s} {r["h_us"]:7.1f} {r["jacobian_us"]:7.1f} {r["validity_us"]:7.1f} '
                  f'{r["sensor_measure_us"]:7.1f}')
    if args.out:
        rounded = {b: {k: (round(v, 2) if isinstance(v, float) else {kk: round(vv, 2) for kk, vv in v.items()})
                       for k, v in rows.items()} for b, rows in figures.items()}
        args.out.write_text(json.dumps(rounded, indent=2) + '\n')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
