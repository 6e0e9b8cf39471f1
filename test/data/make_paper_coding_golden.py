"""Golden numbers of the paper's coding, generated from the code before network_coding existed
(commit 5549053): PYTHONPATH=<checkout of 5549053> python make_paper_coding_golden.py paper_coding_golden.json"""
import json
import sys
from dataclasses import replace

from snn_estimator.catalog import FILTER_KINDS
from snn_estimator.offline.simulation import rendezvous_scenario, simulate, van_der_pol_scenario


def golden():
    out = {}
    cw = replace(rendezvous_scenario(initial_state_dispersion=True), duration=20.0)
    vdp = replace(van_der_pol_scenario(), duration=1.0)
    for kind, spec in FILTER_KINDS.items():
        if not spec.spiking:
            continue
        for name, sc, events in (('rendezvous', cw, {100: lambda e: e.silence(range(0, e.neuron_count, 4))}),
                                 ('van_der_pol', vdp, None)):
            res = simulate(sc, kind, runs=2, seed=7, events=events)
            out[f'{kind}/{name}'] = {'spikes': res.spikes_per_step.sum(axis=1).tolist(),
                                     'estimate': res.estimate[:, ::25].tolist()}
        out[f'{kind}/potentials'] = potentials(kind)
    return out


def potentials(kind):
    import numpy as np

    from snn_estimator import make_estimator
    config = rendezvous_scenario(initial_state_dispersion=True).estimator
    estimator = make_estimator(kind, config, runs=2, seeds=[7, 8])
    x = np.array([70.0, 30.0, -5.0, -1.7, -0.9, 0.25])
    for k in range(100):
        t = 0.1 * k
        z = np.stack([x[:3] + x[3:] * t + 0.05 * np.sin(t + b) for b in range(2)])
        u = np.full((2, 3), 1e-3 * np.cos(t))
        estimator.step(z, u, 0.1)
    return {'v': estimator.potentials.tolist(), 'r': estimator.rates.tolist(), 'x_hat': estimator.x_hat.tolist()}

if __name__ == '__main__':
    json.dump(golden(), open(sys.argv[1], 'w'))
