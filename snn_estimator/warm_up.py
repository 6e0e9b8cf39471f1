"""Compile every kernel the package runs into numba's on-disk cache (``make`` runs it at
install through ``python -m snn_tools.warm_cache``; a node warms only its own filter's,
:meth:`Estimator.warm_up <snn_estimator.filters.estimators.Estimator.warm_up>`).

It sits on top of the core and may import any of it: compiling means building small filters,
closed loops and plants of every kind, which only the top knows how to assemble.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from snn_estimator.catalog import DEFAULT_FILTER, FILTER_KINDS
from snn_estimator.config import EstimatorConfig
from snn_estimator.filters import kernels
from snn_estimator.filters.estimators import Estimator
from snn_estimator.models import ClohessyWiltshire, NonlinearCircular
from snn_estimator.schema import NETWORK_CODINGS
from snn_estimator.sim.scenarios import rendezvous_scenario, van_der_pol_scenario
from snn_estimator.sim.simulate import simulate


def filter_kernels(kinds=None) -> None:
    """Compile (or load) the step kernels of every filter kind (or of ``kinds``: processes can
    share the work), gain schedule and spike rule (and of network_coding deviation with the
    greedy rule) on small filters of the CW model (linear) and Van der Pol (nonlinear: the direct
    filters' drift), and the nonlinear relative motion's compiled dynamics (filters.model_kernels)."""
    unknown = set(kinds or ()) - set(FILTER_KINDS)
    if unknown:
        raise ValueError(f'unknown filter kinds {sorted(unknown)}; choose from {", ".join(FILTER_KINDS)}')
    linear, nonlinear = ClohessyWiltshire(), van_der_pol_scenario()
    for kind, spec in FILTER_KINDS.items():
        if kinds is not None and kind not in kinds:
            continue
        for rule in (kernels.SPIKE_RULES if spec.spiking else ('greedy',)):
            # the deviation coding (Decision 13b) with the default rule only: the other rules
            # compile on first use, which keeps make's warm-up from growing by half
            for coding in (NETWORK_CODINGS if spec.spiking and rule == 'greedy' else ('state',)):
                for schedule in ('time_varying', 'steady_state'):
                    config = EstimatorConfig(neuron_count=4, spike_rule=rule, gain_schedule=schedule,
                                             network_coding=coding)
                    Estimator(kind, linear, config).warm_up()
                config = nonlinear.estimator.replace(neuron_count=4, spike_rule=rule, network_coding=coding)
                Estimator(kind, nonlinear.model, config).warm_up()
    # one compiled function for every kind (its flags are arguments); the step kernels are Van der Pol's
    Estimator('ekf', NonlinearCircular(), EstimatorConfig(dynamics_model='nonlinear_circular')).warm_up()


def closed_loops(kinds=None, basilisk: bool = True) -> None:
    """Compile (or load) the compiled closed loop (snn_estimator.sim.compiled_loop) of every
    filter kind (or of ``kinds``) at its default settings, and with ``basilisk`` the loop on the
    Basilisk truth and the Basilisk plant's own kernels when Basilisk is installed."""
    scenario = rendezvous_scenario()
    scenario = dataclasses.replace(scenario, duration=scenario.dt, metric_window=scenario.dt)
    for kind in FILTER_KINDS if kinds is None else kinds:
        simulate(scenario, kind, engine='compiled')
    if not basilisk:
        return
    try:
        from snn_estimator.plant import basilisk_truth
        basilisk_truth.warm_up()
    except ImportError:  # without the basilisk extra
        return
    on_basilisk = rendezvous_scenario(plant='basilisk')
    simulate(dataclasses.replace(on_basilisk, duration=on_basilisk.dt, metric_window=on_basilisk.dt), 'ekf',
             engine='compiled')


def demo(kind: str = DEFAULT_FILTER) -> None:
    """What ``make demo`` runs compiled: the estimator node's kernels for ``kind`` at its
    default settings (the step, the spikes of a silencing, the runner's NIS check). The kernels'
    types depend on the filter's composition, not on its sizes, so a small network compiles the
    node's."""
    estimator = Estimator(kind, ClohessyWiltshire(), EstimatorConfig(neuron_count=4))
    estimator.warm_up()
    estimator.innovation_nis(estimator.x_hat[:3], np.eye(3))


def everything() -> None:
    """Every kernel: the filters', the closed loops', the Basilisk plant's."""
    filter_kernels()
    closed_loops()
