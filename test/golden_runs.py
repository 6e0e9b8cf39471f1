"""The golden runs of test/core/test_golden.py (test/data/golden.json): every filter kind on three
short closed loops, and the spiking networks' potentials after a fixed input, as this code
computes them.

    .venv/bin/python test/golden_runs.py test/data/golden.json

Each spiking case is run a second time with membrane noise of 1e-13 per step (``PERTURBATION``),
the size of the rounding another CPU's fast-math kernels introduce (~4e-14 was seen): a case whose
spikes do not change is ``robust``, and the test holds it to its spikes exactly; a case whose
spikes flip (a decision within rounding of a threshold, which can go either way on another CPU)
is compared within the tolerances the test states. Regenerate only when a change of the numbers
is intended, and say why in the commit.
"""

import hashlib
import json
import math
import sys
from dataclasses import replace

import numpy as np

from snn_estimator import FILTER_KINDS, make_estimator
from snn_estimator.sim.scenarios import rendezvous_scenario, sensor_rendezvous_scenario, van_der_pol_scenario
from snn_estimator.sim.simulate import simulate

SEED, RUNS, EVERY = 7, 2, 25
#: Membrane noise per step of the robustness check (membrane_noise is per sqrt(s)).
PERTURBATION = 1e-13


def scenarios() -> tuple:
    """(name, scenario, event of the spiking filters) of each closed loop: the dispersed
    rendezvous with a quarter of the neurons silenced at step 100, Van der Pol, the LIDAR."""
    silence = {100: lambda e: e.silence(range(0, e.neuron_count, 4))}
    return (('rendezvous', replace(rendezvous_scenario(initial_state_dispersion=True), duration=20.0), silence),
            ('van_der_pol', replace(van_der_pol_scenario(), duration=1.0), None),
            ('lidar', replace(sensor_rendezvous_scenario(initial_state_dispersion=True), duration=20.0), None))


def perturbed(config, dt: float):
    return config.replace(membrane_noise=PERTURBATION / math.sqrt(dt))


def run(kind: str, scenario, events, perturb: bool = False) -> dict:
    """Estimates and diag P every EVERY steps, spikes per run and step."""
    if perturb:
        scenario = replace(scenario, estimator=perturbed(scenario.estimator, scenario.dt))
    result = simulate(scenario, kind, runs=RUNS, seed=SEED, events=events if FILTER_KINDS[kind].spiking else None)
    case = {'estimate': result.estimate[:, ::EVERY].tolist()}
    if result.covariance_diag is not None:
        case['covariance_diag'] = result.covariance_diag[:, ::EVERY].tolist()
    if result.spikes_per_step is not None:
        case['spikes'] = result.spikes_per_step.tolist()
    return case


def potentials(kind: str, perturb: bool = False) -> dict:
    """v, r and x_hat of two runs after 100 steps of a fixed input, the spikes of each step (per
    run) and a digest of every neuron's spikes."""
    config = rendezvous_scenario(initial_state_dispersion=True).estimator
    estimator = make_estimator(kind, perturbed(config, 0.1) if perturb else config, runs=2, seeds=[SEED, SEED + 1])
    x = np.array([70.0, 30.0, -5.0, -1.7, -0.9, 0.25])
    spikes = []
    for k in range(100):
        t = 0.1 * k
        z = np.stack([x[:3] + x[3:] * t + 0.05 * np.sin(t + b) for b in range(2)])
        estimator.step(z, np.full((2, 3), 1e-3 * np.cos(t)), 0.1)
        spikes.append(estimator.spikes.copy())
    return {'v': estimator.potentials.tolist(), 'r': estimator.rates.tolist(), 'x_hat': estimator.x_hat.tolist(),
            'spikes': np.sum(spikes, axis=2).T.tolist(), 'digest': spike_digest(np.array(spikes))}


def spike_digest(spikes: np.ndarray) -> str:
    """A digest of every neuron's spikes (int64, step by step)."""
    return hashlib.sha256(np.ascontiguousarray(spikes, dtype=np.int64).tobytes()).hexdigest()


def golden() -> dict:
    out = {}
    for kind, spec in FILTER_KINDS.items():
        for name, scenario, events in scenarios():
            case = run(kind, scenario, events)
            case['robust'] = not spec.spiking or case['spikes'] == run(kind, scenario, events, True)['spikes']
            out[f'{kind}/{name}'] = case
        if spec.spiking:
            case = potentials(kind)
            case['robust'] = case['digest'] == potentials(kind, True)['digest']
            out[f'{kind}/potentials'] = case
    return out


if __name__ == '__main__':
    with open(sys.argv[1], 'w') as handle:
        json.dump(golden(), handle, separators=(',', ':'))
