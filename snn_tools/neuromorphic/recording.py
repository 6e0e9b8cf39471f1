"""One closed-loop rendezvous driven by a given spiking estimator, recorded step by step
(measurements, controls, spikes, the network's state at chosen steps): what the independent
simulators and the chip are compared on."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from snn_estimator.filters.estimators import Estimator
from snn_estimator.plant.control import lqr_control, lqr_gain
from snn_estimator.plant.sensors import PositionSensor
from snn_estimator.plant.truth import Plant


@dataclass
class Recording:
    """One closed-loop rendezvous driven by our constant-gain network."""

    truth: np.ndarray      # (steps + 1, n)
    estimate: np.ndarray   # (steps + 1, n)
    zs: np.ndarray         # (steps, m)
    us: np.ndarray         # (steps, nu)
    raster: np.ndarray     # (steps, N) spikes per neuron per step
    snapshots: dict        # step -> (v, r) at the start of that step


def record_rendezvous(scenario, estimator: Estimator, snapshot_steps=()) -> Recording:
    """Run the closed loop of ``scenario`` (one run, the estimator's seed) with ``estimator``
    driving the LQR: u_k = -K x_hat_k, z_k = C x_k + v_k, as simulation.simulate does."""
    model, dt, steps = scenario.model, scenario.dt, scenario.steps
    seeds = estimator.seeds
    plant = Plant(scenario.truth_model or model, scenario.x0, scenario.process_noise, seeds)
    sensor = PositionSensor(scenario.truth_model or model, scenario.measurement_noise, seeds)
    gain = lqr_gain(model, scenario.lqr_state_weight, scenario.lqr_input_weight)
    n, neurons = model.n_state, estimator.neuron_count
    truth, estimate = np.empty((steps + 1, n)), np.empty((steps + 1, n))
    zs, us = np.empty((steps, model.n_meas)), np.empty((steps, model.n_input))
    raster = np.empty((steps, neurons), dtype=np.int64)
    snapshots = {}
    truth[0], estimate[0] = plant.x[0], estimator.x_hat
    for k in range(steps):
        if k in snapshot_steps:
            snapshots[k] = (estimator.potentials.copy(), estimator.rates.copy())
        us[k] = lqr_control(gain, estimator.x_hat)
        zs[k] = sensor.measure(plant.x)[0]
        estimator.step(zs[k], us[k], dt)
        plant.step(us[k], dt)
        truth[k + 1], estimate[k + 1], raster[k] = plant.x[0], estimator.x_hat, estimator.spikes
    return Recording(truth, estimate, zs, us, raster, snapshots)


def rmse(truth: np.ndarray, estimate: np.ndarray, window: int) -> np.ndarray:
    """RMSE per state over the last ``window`` samples."""
    error = truth[-window:] - estimate[-window:]
    return np.sqrt(np.mean(error * error, axis=0))
