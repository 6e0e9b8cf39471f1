"""The offline closed loop on the blocks the ROS nodes wrap (truth, sensor, LQR: blocks.py).

One step of the loop at t_k (identical in the ROS pipeline):
``u_k = -K x_hat_k``; ``z_k = C x_k + v_k``; ``x_hat_{k+1} = estimator.step(z_k, u_k, dt)``;
``x_{k+1} = plant.step(u_k, dt)``.

Random streams: component ``c`` of run ``b`` draws from ``default_rng([seed + b, c])`` with
c = 1 (plant process noise), 2 (sensor noise), 3 (decoder / membrane noise), so a single ROS
run with seed s reproduces run 0 of an offline batch with seed s.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np
import scipy.stats

from snn_estimator import defaults as D
from snn_estimator.config import EstimatorConfig, sensor_boundary_layer
from snn_estimator.filters.estimators import TWIN_OF, make_estimator
from snn_estimator.models import DEFAULT_ORBIT_RADIUS, ClohessyWiltshire, StateSpaceModel, VanDerPol

from . import compiled_loop
from .blocks import (  # noqa: F401 (re-exported: the loop's blocks beside the loop)
    PLANT_STREAM,
    SENSOR_STREAM,
    FusedSensor,
    GaussianStream,
    MeasurementSensor,
    Plant,
    PositionSensor,
    lqr_control,
    lqr_gain,
    matrix_sqrt,
)
from .sums import ChunkSink, LoopSums


@dataclass(frozen=True)
class Scenario:
    """A complete experiment set-up."""

    name: str
    model: StateSpaceModel
    x0: np.ndarray
    dt: float
    duration: float
    process_noise: np.ndarray
    measurement_noise: np.ndarray
    estimator: EstimatorConfig
    #: LQR weights; None means open loop (u = 0).
    lqr_state_weight: np.ndarray | None = None
    lqr_input_weight: np.ndarray | None = None
    #: Length of the final window the tables average over, s.
    metric_window: float = 60.0
    #: Model of the truth when it differs from the filters' model (None: the same).
    truth_model: StateSpaceModel | None = None
    #: The state the LQR regulates to, u = -K (x_hat - setpoint) (None: the origin, docking).
    setpoint: np.ndarray | None = None
    #: Truth by Basilisk (basilisk_truth.BasiliskSettings) instead of the model (None: the model).
    basilisk: object | None = None
    #: How the truth reads Eq. 1's w: spectral_density (variance Q dt per step) | held_sample
    #: (w ~ N(0, Q) held over the step, variance ~ Q dt^2): blocks.TRUTH_NOISE_READINGS.
    truth_noise: str = 'spectral_density'
    #: The sensor (a snn_estimator.measurements model) the loop measures with and the filters
    #: linearise; None: the model's linear C with ``measurement_noise`` (Table 6's position).
    sensor: object | None = None
    #: Open loop (no LQR weights): the known control of each step, (steps, m_u) (None: u = 0).
    control_schedule: np.ndarray | None = None
    #: With a stacked ``sensor``: steps between two samples of each of its sensors (None: every step).
    sensor_periods: tuple | None = None

    @property
    def steps(self) -> int:
        return int(round(self.duration / self.dt))


PRESETS = ('default', 'as_published')
#: How simulate() steps its loop (see simulate).
ENGINES = ('auto', 'compiled', 'reference')


def _apply_preset(config: EstimatorConfig, preset: str, changes: dict) -> EstimatorConfig:
    """'as_published' runs the network literally as the paper's tables give it: no state
    scaling and forward-Euler steps; 'default' keeps this package's numerical choices."""
    if preset == 'as_published':
        config = config.replace(state_scale=None, discretization='euler')
    elif preset != 'default':
        raise ValueError(f"preset must be one of {', '.join(PRESETS)}; got {preset!r}")
    return config.replace(**changes)


def rendezvous_scenario(preset: str = 'default', cw_model: str = 'standard',
                        orbit_radius: float = DEFAULT_ORBIT_RADIUS, plant: str = 'cw', basilisk=None,
                        **estimator_changes) -> Scenario:
    """Sec. 3.2 / Table 6: CW rendezvous, 360 s at dt = 0.1 s, LQR in the loop.

    ``preset='as_published'`` keeps Table 6 literally in the network (decoder variance 1/15,
    no state scaling) and integrates by forward Euler; 'default' uses this package's choices.
    ``cw_model='as_published'`` gives the filters and the LQR design the matrix printed as
    Eq. 41 while the truth stays standard CW, to measure what the misprint costs.
    ``plant='basilisk'`` flies the truth with Basilisk (two-body gravity, J2, thrust limits:
    ``basilisk``, a BasiliskSettings; default: J2 on, circular orbit of ``orbit_radius``)
    while the filters keep the CW model.
    """
    config = _apply_preset(EstimatorConfig(), preset, estimator_changes)
    truth = ClohessyWiltshire(orbit_radius=orbit_radius)
    model = truth if cw_model == 'standard' else ClohessyWiltshire(orbit_radius=orbit_radius, form=cw_model)
    return Scenario(
        name='rendezvous', model=model, x0=np.array(D.RENDEZVOUS_X0), dt=D.RENDEZVOUS_TIME_STEP,
        duration=D.RENDEZVOUS_DURATION, process_noise=D.RENDEZVOUS_PROCESS_NOISE * np.eye(6),
        measurement_noise=D.RENDEZVOUS_MEASUREMENT_NOISE * np.eye(3), estimator=config,
        lqr_state_weight=D.LQR_STATE_WEIGHT * np.eye(6), lqr_input_weight=D.LQR_INPUT_WEIGHT * np.eye(3),
        metric_window=D.RENDEZVOUS_METRIC_WINDOW, truth_model=None if model is truth else truth,
        basilisk=_truth_settings(plant, basilisk, orbit_radius))


def _truth_settings(plant: str, basilisk, orbit_radius: float):
    """None for the CW truth; Basilisk settings (default: J2, circular orbit of orbit_radius)."""
    if plant == 'cw':
        return None
    if plant != 'basilisk':
        raise ValueError(f"plant must be one of cw, basilisk; got {plant!r}")
    from .basilisk_truth import BasiliskSettings, OrbitSettings
    return basilisk or BasiliskSettings(orbit=OrbitSettings(semi_major_axis=orbit_radius))


def far_range_scenario(plant: str = 'basilisk', basilisk=None, orbit_radius: float = DEFAULT_ORBIT_RADIUS,
                       **estimator_changes) -> Scenario:
    """A V-bar approach from 5 km behind the target to a hold point 100 m behind it (where the
    paper's 100 m scenario begins), over about one orbit (not in the paper).

    Here the model the filters use is wrong in earnest: rectilinear CW against a curved orbit
    (a point 5 km back on the straight V-bar drifts ~70 m per orbit in truth), J2, and the
    thrust limit. 1 s steps (far-range navigation rates); the LQR weights of defaults.FAR_RANGE_*
    reach the hold point in about an orbit within the thrust limit. Measurements as in Table 6.
    """
    config = EstimatorConfig().replace(**{**D.FAR_RANGE_ESTIMATOR, **estimator_changes})
    model = ClohessyWiltshire(orbit_radius=orbit_radius)
    return Scenario(
        name='far_range', model=model, x0=np.array(D.FAR_RANGE_X0), dt=D.FAR_RANGE_TIME_STEP,
        duration=D.FAR_RANGE_DURATION, process_noise=D.RENDEZVOUS_PROCESS_NOISE * np.eye(6),
        measurement_noise=D.RENDEZVOUS_MEASUREMENT_NOISE * np.eye(3), estimator=config,
        lqr_state_weight=D.FAR_RANGE_LQR_STATE_WEIGHT * np.eye(6),
        lqr_input_weight=D.FAR_RANGE_LQR_INPUT_WEIGHT * np.eye(3),
        metric_window=D.FAR_RANGE_METRIC_WINDOW, setpoint=np.array(D.FAR_RANGE_SETPOINT),
        basilisk=_truth_settings(plant, basilisk, orbit_radius))


def sensor_rendezvous_scenario(sensor: str = 'range_azimuth_elevation', preset: str = 'default', noise=None,
                              sensor_options: dict | None = None,
                              boundary_layer_units: str = D.SENSOR_BOUNDARY_LAYER_UNITS,
                              **estimator_changes) -> Scenario:
    """Sec. 3.2 measured by ``sensor`` (a model of snn_estimator.measurements) instead of Table
    6's position (issue 22): noise R per sample ``noise`` (default defaults.SENSOR_NOISE), the
    sensor on the chaser looking back at the target (defaults.CLOSE_SENSOR_MOUNTING; no field of
    view, and the range limit defaults.CLOSE_SENSOR_MIN_RANGE, unless ``sensor_options`` sets
    them). The filters take the sensor's R as their R (times measurement_noise_scale) and Table
    6's delta per component in ``boundary_layer_units`` (config.sensor_boundary_layer: 'sigma',
    one sensor sigma, the default; 'variance', 10 R_jj; Decision 35), unless ``measurement_noise``
    or ``boundary_layer`` is given. The spiking filters
    code the deviation from the prediction in units of 1 mm and 0.01 mm/s (defaults.SENSOR_NETWORK;
    Decision 36) unless ``network_coding`` or ``state_scale`` is given or the preset is
    'as_published'."""
    from snn_estimator.measurements import make_model
    base = rendezvous_scenario(preset, **_sensor_network(preset, estimator_changes))
    options = {'mounting_rotation': D.CLOSE_SENSOR_MOUNTING, 'min_range': D.CLOSE_SENSOR_MIN_RANGE,
               **(sensor_options or {})}
    model = make_model(sensor, D.SENSOR_NOISE[sensor] if noise is None else noise, **options)
    config = base.estimator
    if 'measurement_noise' not in estimator_changes:
        config = config.replace(measurement_noise=model.noise)
    if 'boundary_layer' not in estimator_changes:  # Table 6's delta per component (Decision 35)
        config = config.replace(boundary_layer=sensor_boundary_layer(model.noise, boundary_layer_units))
    return replace(base, name=f'rendezvous_{sensor}', sensor=model, estimator=config,
                   measurement_noise=model.noise)


def _sensor_network(preset: str, estimator_changes: dict) -> dict:
    """``estimator_changes`` with the sensors' network (defaults.SENSOR_NETWORK) where it does not
    say otherwise; the 'as_published' preset keeps the paper's network."""
    if preset == 'as_published':
        return estimator_changes
    return {**D.SENSOR_NETWORK, **estimator_changes}


def handover_scenario(preset: str = 'default', lidar_max_range: float = D.HANDOVER_LIDAR_MAX_RANGE,
                      periods=D.HANDOVER_PERIODS, boundary_layer_units: str = D.SENSOR_BOUNDARY_LAYER_UNITS,
                      **estimator_changes) -> Scenario:
    """Sec. 3.2 flown on two sensors fused in one filter (issue 22; not in the paper): a camera
    (line_of_sight, every ``periods[0]`` steps) for the whole approach and a LIDAR
    (range_azimuth_elevation, every ``periods[1]`` steps) within ``lidar_max_range``; both on the
    chaser looking back at the target, no closer than defaults.CLOSE_SENSOR_MIN_RANGE. Far, the
    filter has the bearings only (the LQR's known burns make the range observable); once the
    LIDAR sees the target it hands over. R_hat = scale * blockdiag(R_camera, R_lidar), delta
    and the network as in :func:`sensor_rendezvous_scenario`."""
    from snn_estimator.measurements import make_model
    from snn_estimator.measurements.stacked import Stacked
    base = rendezvous_scenario(preset, **_sensor_network(preset, estimator_changes))
    geometry = {'mounting_rotation': D.CLOSE_SENSOR_MOUNTING, 'min_range': D.CLOSE_SENSOR_MIN_RANGE}
    camera = make_model('line_of_sight', D.SENSOR_NOISE['line_of_sight'], **geometry)
    lidar = make_model('range_azimuth_elevation', D.SENSOR_NOISE['range_azimuth_elevation'],
                       max_range=lidar_max_range, **geometry)
    model = Stacked([camera, lidar])
    config = base.estimator
    if 'measurement_noise' not in estimator_changes:
        config = config.replace(measurement_noise=model.noise)
    if 'boundary_layer' not in estimator_changes:
        config = config.replace(boundary_layer=sensor_boundary_layer(model.noise, boundary_layer_units))
    return replace(base, name='rendezvous_camera_lidar', sensor=model, estimator=config,
                   measurement_noise=model.noise, sensor_periods=tuple(periods))


def angles_only_scenario(maneuver: bool = False, noise=None, **estimator_changes) -> Scenario:
    """An angles-only far approach (issue 22; not in the paper): a camera (line_of_sight) on the
    chaser, 1 km behind the target and 50 m below its orbit, drifting toward it under free CW
    motion, open loop, 1 s samples for 3000 s (defaults.ANGLES_ONLY_*). The filters start 30 m
    off along the line of sight. Under free drift the bearings of x and of k x are the same for
    every k (linear dynamics, no input), so the range cannot be observed; ``maneuver`` adds a known
    radial burn (defaults.ANGLES_ONLY_MANEUVER), which breaks that scale symmetry."""
    from snn_estimator.measurements import make_model
    truth = ClohessyWiltshire()
    x0 = np.array(D.ANGLES_ONLY_X0, dtype=float)
    x0[3] = 1.5 * truth.mean_motion * x0[2]  # the drift of a lower orbit: no secular radial motion
    camera = make_model('line_of_sight', D.SENSOR_NOISE['line_of_sight'] if noise is None else noise)
    config = EstimatorConfig().replace(**{
        'initial_state': tuple(x0 + np.array(D.ANGLES_ONLY_INITIAL_ERROR)),
        'initial_covariance': D.ANGLES_ONLY_INITIAL_COVARIANCE, 'measurement_noise': camera.noise,
        'state_scale': (1.0, 1e-2, 1e-2, 1e-3, 1e-3, 1e-3), **estimator_changes})
    steps = int(round(D.ANGLES_ONLY_DURATION / D.ANGLES_ONLY_TIME_STEP))
    schedule = np.zeros((steps, 3))
    if maneuver:
        start, end, acceleration = D.ANGLES_ONLY_MANEUVER
        times = D.ANGLES_ONLY_TIME_STEP * np.arange(steps)
        schedule[(times >= start) & (times < end)] = acceleration
    return Scenario(
        name='angles_only' + ('_maneuver' if maneuver else ''), model=truth, x0=x0, dt=D.ANGLES_ONLY_TIME_STEP,
        duration=D.ANGLES_ONLY_DURATION, process_noise=D.RENDEZVOUS_PROCESS_NOISE * np.eye(6),
        measurement_noise=camera.noise, estimator=config, metric_window=D.ANGLES_ONLY_METRIC_WINDOW,
        sensor=camera, control_schedule=schedule)


def van_der_pol_scenario(preset: str = 'default', **estimator_changes) -> Scenario:
    """Sec. 3.1 / Table 1: Van der Pol, 20 s at dt = 0.01 s, open loop, x1 measured."""
    config = EstimatorConfig(
        neuron_count=100, leak_rate=0.5, boundary_layer=0.05, decoder_variance=0.25,
        process_noise=0.01 * np.eye(2), measurement_noise=0.1, process_noise_scale=1.0,
        measurement_noise_scale=1.0, initial_covariance=(0.01, 0.01), initial_state=(0.0, 0.0),
        state_scale=(0.01, 0.01))
    config = _apply_preset(config, preset, estimator_changes)
    return Scenario(
        name='van_der_pol', model=VanDerPol(mu=D.VAN_DER_POL_MU), x0=np.array(D.VAN_DER_POL_X0),
        dt=D.VAN_DER_POL_TIME_STEP, duration=D.VAN_DER_POL_DURATION, process_noise=0.01 * np.eye(2),
        measurement_noise=np.array([[0.1]]),
        estimator=config, metric_window=10.0)


@dataclass
class SimulationResult:
    """Trajectories of a (batched) closed-loop run; arrays have a leading runs axis."""

    kind: str
    scenario: Scenario
    time: np.ndarray            # (steps + 1,)
    truth: np.ndarray           # (runs, steps + 1, n)
    estimate: np.ndarray        # (runs, steps + 1, n)
    covariance_diag: np.ndarray | None  # (runs, steps + 1, n)
    control: np.ndarray         # (runs, steps, m_u)
    spikes_per_step: np.ndarray | None  # (runs, steps)
    raster: np.ndarray | None   # (steps, N) spikes per neuron per step for run 0
    neuron_count: int
    wall_time: float
    capped_steps: int = 0
    extra: dict = field(default_factory=dict)
    #: e^T P^-1 e per run and time (e = truth - estimate, P the filter's covariance), shape
    #: (runs, steps + 1); None for filters without a covariance.
    nees: np.ndarray | None = None
    #: nu^T (C P C^T + R_hat)^-1 nu of each measurement against the prior estimate, (runs,
    #: steps); None without a covariance.
    nis: np.ndarray | None = None
    #: The readings without the trajectories (simulate(..., trajectories=False); then truth,
    #: estimate, covariance_diag, control, NEES, NIS and the raster are None): sums.LoopSums.
    kept_sums: LoopSums | None = None
    #: The step at which each run diverged (its state or control went non-finite), -1 for a run
    #: that did not; its samples after that step are NaN (None: not recorded).
    diverged_at: np.ndarray | None = None

    @property
    def runs(self) -> int:
        return self.kept_sums.runs if self.truth is None else self.truth.shape[0]

    @property
    def diverged(self) -> np.ndarray:
        """True for each run that diverged, shape (runs,). The statistics below (RMSE, mean
        error, spikes, NEES/NIS) are over the other runs; per-run arrays keep NaN for it."""
        if self.diverged_at is None:
            return np.zeros(self.runs, dtype=bool)
        return self.diverged_at >= 0

    def _kept(self, per_run: np.ndarray) -> np.ndarray:
        """``per_run`` (leading runs axis) without the runs that diverged (as it is if none did)."""
        diverged = self.diverged
        return per_run[~diverged] if diverged.any() else per_run

    @property
    def sums(self) -> LoopSums:
        """The metric window's samples and the per-run totals (sums.LoopSums): kept as such, or
        taken from the trajectories."""
        return self.kept_sums if self.truth is None else LoopSums.of_trajectories(self)

    def _without_trajectories(self, what: str, seconds: float | None = None) -> bool:
        """True when only the window was kept (then ``seconds`` must be the metric window)."""
        if self.truth is not None:
            return False
        if seconds is not None and abs(seconds - self.scenario.metric_window) > 1e-9:
            raise ValueError(f'{what} over {seconds} s needs the trajectories (kept: the metric window of '
                             f'{self.scenario.metric_window} s): simulate(..., trajectories=True)')
        return True

    @property
    def error(self) -> np.ndarray:
        if self.truth is None:
            raise ValueError('this run kept no trajectories: simulate(..., trajectories=True)')
        return self.truth - self.estimate

    def window(self, seconds: float | None = None) -> slice:
        seconds = self.scenario.metric_window if seconds is None else seconds
        count = int(round(seconds / self.scenario.dt))
        return slice(self.time.size - count, self.time.size)

    def rmse(self, seconds: float | None = None) -> np.ndarray:
        """Ordinary RMSE per state over the final window: sqrt(mean over runs and time of e^2)."""
        if self._without_trajectories('rmse', seconds):
            e = self._kept(self.kept_sums.error)
        else:
            e = self._kept(self.error)[:, self.window(seconds)]
        return np.sqrt(np.mean(e * e, axis=(0, 1)))

    def mean_error(self, seconds: float | None = None) -> np.ndarray:
        """Time average over the final window of |mean over runs of e(t)| per state."""
        if self._without_trajectories('mean_error', seconds):
            e = self._kept(self.kept_sums.error)
        else:
            e = self._kept(self.error)[:, self.window(seconds)]
        return np.mean(np.abs(e.mean(axis=0)), axis=0)

    def rmse_history(self) -> np.ndarray:
        """RMSE over runs at each time, shape (steps + 1, n)."""
        return np.sqrt(np.mean(self._kept(self.error) ** 2, axis=0))

    @property
    def spike_fraction(self) -> float | None:
        """Spikes emitted / (N x steps), averaged over runs (Fig. 7: 17%)."""
        if self.truth is None and self.neuron_count:
            spikes = self._kept(self.kept_sums.spikes)
            return float(spikes.sum() / (spikes.shape[0] * self.kept_sums.steps * self.neuron_count))
        if self.spikes_per_step is None:
            return None
        spikes = self._kept(self.spikes_per_step)
        steps = spikes.shape[1]
        return float(spikes.sum() / (spikes.shape[0] * steps * self.neuron_count))

    def final_range(self) -> np.ndarray:
        """Distance of the chaser from where the controller steers it (the target, or the
        scenario's setpoint) at the end, per run, m (NaN for a run that diverged)."""
        aim = np.zeros(3) if self.scenario.setpoint is None else self.scenario.setpoint[:3]
        final = self.kept_sums.final_state if self.truth is None else self.truth[:, -1]
        return np.linalg.norm(final[:, :3] - aim, axis=1)

    def delta_v(self) -> np.ndarray:
        """Velocity change the thrusters delivered, per run, m/s: sum over steps of
        |u_x| + |u_y| + |u_z| times dt (one thruster pair per axis: propellant goes as this;
        NaN for a run that diverged)."""
        if self.control is None:
            return self.kept_sums.delta_v()
        return np.abs(self.control).sum(axis=(1, 2)) * self.scenario.dt

    def consistency(self, seconds: float | None = None) -> dict:
        """Average NEES and NIS over the final window against their 95 % chi-square bounds
        (:func:`consistency_check`); empty for a filter without a covariance."""
        sensor = self.scenario.sensor
        dof = self.scenario.model.n_meas if sensor is None else sensor.dim
        if self._without_trajectories('consistency', seconds):
            if not self.kept_sums.covariance:
                return {}
            nees, nis = self._kept(self.kept_sums.nees), self._kept(self.kept_sums.nis)
        else:
            if self.nees is None:
                return {}
            window = self.window(seconds)
            nees = self._kept(self.nees)[:, window]
            nis = self._kept(self.nis)[:, window.start - 1:window.stop - 1]
        runs = nees.shape[0]
        if sensor is not None:  # steps without a measurement have no NIS (NaN): average the others
            nis = nis[:, np.isfinite(nis).all(axis=0)]
        return {'nees': consistency_check(nees.mean(axis=0), runs, self.scenario.model.n_state),
                'nis': consistency_check(nis.mean(axis=0), runs, dof)}


def consistency_check(per_step: np.ndarray, runs: int, dof: int) -> dict:
    """Judge a filter's covariance from the per-step average over ``runs`` runs of its NEES
    (dof = states) or NIS (dof = measurements): each step's average is compared with
    chi2(runs dof)/runs at 2.5 % and 97.5 % (Bar-Shalom et al., Sec. 5.4). Returns the time
    average, the bounds, the share of steps inside them and a verdict: consistent (>= 90 % of
    steps inside), overconfident (the +-3 sigma the filter publishes is too narrow: mostly
    above) or conservative (mostly below)."""
    per_step = np.asarray(per_step, dtype=float)
    low, high = (scipy.stats.chi2.ppf(q, runs * dof) / runs for q in (0.025, 0.975))
    inside = float(np.mean((per_step >= low) & (per_step <= high)))
    above = float(np.mean(per_step > high))
    verdict = ('consistent' if inside >= 0.9 else
               'overconfident' if above > 0.5 * (1.0 - inside) else 'conservative')
    return {'average': float(per_step.mean()), 'dof': dof, 'bounds': [float(low), float(high)],
            'fraction_inside': inside, 'verdict': verdict}


class _Control:
    """The control of every run from its estimate: u = -K (x_hat - setpoint) (Eq. 42), the same law
    by the spiking LQR, a known open-loop schedule (no LQR weights), or none."""

    def __init__(self, scenario: Scenario, seeds, controller: str, options: dict | None):
        model = scenario.model
        self.setpoint = np.zeros(model.n_state) if scenario.setpoint is None else scenario.setpoint
        self.gain = (lqr_gain(model, scenario.lqr_state_weight, scenario.lqr_input_weight)
                     if scenario.lqr_state_weight is not None else None)
        self.spiking_lqr = None
        if controller == 'snn_lqr' and self.gain is not None:
            from snn_estimator.spiking.lqr import SpikingLQR
            self.spiking_lqr = SpikingLQR(self.gain, seeds=seeds, **(options or {}))
        elif controller not in ('lqr', 'snn_lqr'):
            raise ValueError(f"controller must be one of lqr, snn_lqr; got {controller!r}")
        self.schedule = scenario.control_schedule
        self.zero_u = np.zeros((len(seeds), model.n_input))

    def __call__(self, k: int, x_hat: np.ndarray, dt: float) -> np.ndarray:
        if self.spiking_lqr is not None:
            return self.spiking_lqr.control(x_hat - self.setpoint, dt)
        if self.gain is not None:
            return lqr_control(self.gain, x_hat - self.setpoint)
        if self.schedule is not None:  # a known open-loop control
            return np.broadcast_to(self.schedule[k], self.zero_u.shape)
        return self.zero_u


class _Sensing:
    """The sensor of every run and the filter's step on its sample, with the NIS recorded: the
    position sensor (z = C x + v), or a measurement model with limits, whose runs without a
    sample predict only (counted in ``unmeasured``)."""

    def __init__(self, scenario: Scenario, estimator, seeds):
        truth_model = scenario.truth_model or scenario.model
        self.with_limits = scenario.sensor is not None
        if getattr(scenario.sensor, 'partial', False):  # several sensors fused (measurements.stacked)
            self.sensor = FusedSensor(scenario.sensor, seeds, scenario.sensor_periods)
        elif self.with_limits:
            self.sensor = MeasurementSensor(scenario.sensor, seeds)
        else:
            self.sensor = PositionSensor(truth_model, scenario.measurement_noise, seeds)
        self.c, self.r_hat = scenario.model.measurement_matrix, estimator.settings.r_hat
        self.unmeasured = np.zeros(len(seeds), dtype=np.int64)

    def step(self, k: int, plant, estimator, record, u: np.ndarray, dt: float,
             running: np.ndarray | None = None) -> None:
        """Measure and step the filter; ``running`` (None: every run) masks out the runs that
        diverged: they are not measured."""
        x_hat, covariance, c, r_hat = estimator.batch_x_hat, estimator.batch_P, self.c, self.r_hat
        if not self.with_limits:
            z = self.sensor.measure(plant.x)
            if covariance is not None:
                record.nis[:, k] = normalised_squares(z - x_hat @ c.T, c @ covariance @ c.T + r_hat)
            estimator.step(z, u, dt, valid=running)
            return
        sample = self.sensor.measure(plant.x)
        valid = sample.valid if running is None else sample.valid & running
        self.unmeasured += ~valid
        if covariance is not None:
            record.nis[:, k] = np.nan
            if getattr(self.sensor.model, 'partial', False):  # NIS of one dof: every sensor present
                valid = valid & np.isfinite(sample.z).all(axis=1)
            if valid.any():
                record.nis[valid, k] = estimator.innovation_nis(np.where(valid[:, None], sample.z, 0.0),
                                                                r_hat)[valid]
            valid = sample.valid if running is None else sample.valid & running
        estimator.step(sample.z, u, dt, valid=valid)


class _Divergence:
    """The runs of a batch that diverged, so that the others go on. A run diverges at step k when
    its control at k, or its estimate, covariance or truth after step k, is not finite, its P is
    not positive definite (the step's guard, Estimator.batch_fault), or its network's spikes in step k reached
    max_spikes_per_step (1000 N by default: the network no longer follows the filter, its
    estimate is what the cap left). From then on its filter is restarted with its network
    silenced (Estimator.retire: it fires no more) and never measured, it flies with u = 0, and its samples from k + 1 on
    (controls, NIS and spikes from k) are discarded (NaN; :attr:`SimulationResult.diverged`).
    With no run diverged nothing here touches a number."""

    def __init__(self, runs: int):
        #: The step at which each run diverged, -1 for none.
        self.at = np.full(runs, -1, dtype=np.int64)
        #: What went first: control, estimate, covariance, truth or spike_cap ('' for none).
        self.cause = np.full(runs, '', dtype=object)
        #: The runs still flying (None while every run is: the loop's arrays pass unchanged).
        self.running: np.ndarray | None = None

    def control(self, k: int, u: np.ndarray, estimator) -> np.ndarray:
        """``u`` with the diverged runs' rows zero; a run whose control is not finite diverges here."""
        finite = np.isfinite(u).all(axis=1)
        if not finite.all():
            self._mark(k, np.where(finite, '', 'control'), estimator)
        return u if self.running is None else np.where(self.running[:, None], u, 0.0)

    def check(self, k: int, estimator, plant) -> int:
        """Mark the runs that became non-finite in step ``k`` and restart their filters (a run
        that diverged before and blew up again restarts again); returns how many runs were
        non-finite."""
        estimate = np.isfinite(estimator.batch_x_hat).all(axis=1)
        covariance = ~estimator.batch_fault & (np.isfinite(estimator.batch_P).all(axis=(1, 2))
                                               if estimator.has_covariance else estimate)
        truth = np.isfinite(plant.x).all(axis=1)
        spikes = (estimator.batch_spikes.sum(axis=1) < estimator.settings.max_spikes_per_step if estimator.spiking
                  else truth)
        if estimate.all() and covariance.all() and truth.all() and spikes.all():
            return 0
        cause = np.where(estimator.batch_fault, 'covariance', np.where(~estimate, 'estimate', np.where(
            ~covariance, 'covariance', np.where(~truth, 'truth', np.where(~spikes, 'spike_cap', '')))))
        self._mark(k, cause, estimator, broken=~(estimate & covariance))
        return int((cause != '').sum())

    def _mark(self, k: int, cause: np.ndarray, estimator, broken: np.ndarray | None = None) -> int:
        """Runs with a ``cause`` diverge at step ``k`` (the first cause is kept); the new ones and
        any whose filter state is ``broken`` restart."""
        new = (cause != '') & (self.at < 0)
        self.at[new] = k
        self.cause[new] = cause[new]
        self.running = self.at < 0
        restart = new if broken is None else new | broken
        if restart.any():
            estimator.retire(restart)
        return int(new.sum())


def simulate(scenario: Scenario, kind: str, runs: int = 1, seed: int = 0,
             config: EstimatorConfig | None = None, on_step: Callable[[int], None] | None = None,
             events: dict[int, Callable] | None = None, controller: str = 'lqr',
             controller_options: dict | None = None, engine: str = 'auto',
             trajectories: bool = True) -> SimulationResult:
    """Run the closed loop of ``scenario`` with filter ``kind`` for ``runs`` seeds seed..seed+runs-1.

    ``events`` maps a step index to ``fn(estimator)`` called before that step (fault injection,
    e.g. silencing neurons). ``on_step(k)`` is called after each step (progress bars; per chunk
    of steps with the compiled engine). ``controller``: lqr (u = -K (x_hat - setpoint)) or
    snn_lqr (the same law computed by a spike-coding network, snn_estimator.spiking.lqr;
    ``controller_options``: its neurons, leak). ``engine``: compiled (the loop in numba,
    :mod:`.compiled_loop`: the same numbers, several times faster), reference (the loop in
    Python, :func:`_python_loop`), or auto (compiled where it applies: a linear model and the
    position sensor, the float64 network, the LQR). ``trajectories=False`` keeps only the metric
    window's errors, NEES and NIS and per-run totals (``result.sums``, :mod:`.sums`): with the
    compiled engine a run then holds ~60 kB instead of its trajectories (~0.7 MB for the 360 s
    rendezvous). A run whose control, estimate, covariance or truth goes non-finite, or whose
    network hits its spike cap, is marked (``result.diverged``, ``result.diverged_at``,
    :class:`_Divergence`), its later samples are NaN and the batch's statistics leave it out;
    the other runs go on as if it were not there.
    """
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {', '.join(ENGINES)}; got {engine!r}")
    seeds = [seed + b for b in range(runs)]
    config = scenario.estimator if config is None else config
    estimator = make_estimator(kind, config.replace(seed=seed), scenario.model, runs=runs, seeds=seeds,
                               measurement=scenario.sensor)
    plant = truth_plant(scenario, seeds)
    sensing = _Sensing(scenario, estimator, seeds)
    control = _Control(scenario, seeds, controller, controller_options)
    why_not = compiled_loop.unsupported(scenario, estimator, controller)
    if engine == 'compiled' and why_not:
        raise ValueError(f'engine compiled does not run {why_not}: use engine auto or reference')
    compiled = engine != 'reference' and not why_not
    steps, dt = scenario.steps, scenario.dt
    record = sums = None
    divergence = _Divergence(runs)
    if compiled and not trajectories:
        sums = _first_sums(scenario, estimator, plant)
    else:
        record = _Record(estimator, runs, steps)
        record.sample(0, plant, estimator.batch_x_hat, estimator.batch_P)
    started, cpu_started = time.perf_counter(), time.thread_time()
    if compiled:
        loop = compiled_loop.CompiledLoop(estimator, plant, sensing.sensor, control, dt, sensing.c, sensing.r_hat)
        sink = (compiled_loop.FullRecord(record, runs, scenario.model.n_state, estimator._network.r.shape[1])
                if record is not None else
                ChunkSink(sums, scenario.model.n_input, estimator.spiking))
        loop.run(sink, steps, divergence, events, on_step)
    else:
        _python_loop(scenario, estimator, plant, sensing, control, record, divergence, events, on_step)
    if record is not None:
        record.discard(divergence.at)
    result = _result(kind, scenario, estimator, plant, sensing, control, record, sums, divergence,
                     time.perf_counter() - started, trajectories)
    result.extra['cpu_time'] = time.thread_time() - cpu_started  # of the loop, this thread: a bench under load
    return result


def _result(kind, scenario, estimator, plant, sensing, control, record, sums, divergence, wall: float,
            trajectories: bool) -> SimulationResult:
    """simulate's result: the trajectories of ``record``, or the window's ``sums`` (taken from
    ``record`` when the reference engine ran without trajectories)."""
    result = SimulationResult(
        kind=kind, scenario=scenario, time=scenario.dt * np.arange(scenario.steps + 1), truth=None,
        estimate=None, covariance_diag=None, control=None, spikes_per_step=None, raster=None,
        neuron_count=estimator.neuron_count, wall_time=wall, capped_steps=estimator.capped_steps, kept_sums=sums,
        diverged_at=divergence.at,
        extra={'saturated_steps': plant.saturated_steps.copy(), 'unmeasured_steps': sensing.unmeasured,
               'diverged_cause': divergence.cause,
               'controller_spikes': (None if control.spiking_lqr is None
                                     else control.spiking_lqr.total_spikes.copy())})
    if record is None:
        return result
    result = replace(result, truth=record.truth, estimate=record.estimate, covariance_diag=record.cov,
                     control=record.controls, spikes_per_step=record.spikes, raster=record.raster,
                     nees=record.nees, nis=record.nis)
    if trajectories:
        return result
    return replace(result, truth=None, estimate=None, covariance_diag=None, control=None, spikes_per_step=None,
                   raster=None, nees=None, nis=None, kept_sums=result.sums)


def _first_sums(scenario: Scenario, estimator, plant) -> LoopSums:
    """The window of a run that keeps no trajectory, with sample 0 (the start) in it."""
    runs, n = estimator.runs, scenario.model.n_state
    window_start = scenario.steps + 1 - int(round(scenario.metric_window / scenario.dt))
    sums = LoopSums(runs, n, scenario.steps, window_start, scenario.dt, estimator.has_covariance)
    x, x_hat = np.array(plant.x), estimator.batch_x_hat
    nees = normalised_squares(x - x_hat, estimator.batch_P)[:, None] if estimator.has_covariance else None
    sums.add_samples(0, x[:, None], x_hat[:, None], nees)
    return sums


def _python_loop(scenario: Scenario, estimator, plant, sensing, control, record, divergence, events,
                 on_step) -> None:
    """The loop in Python (engine reference), step by step:
    ``u_k = -K x_hat_k``; ``z_k = C x_k + v_k``; ``x_hat_{k+1} = estimator.step(z_k, u_k, dt)``;
    ``x_{k+1} = plant.step(u_k, dt)``; the samples of k + 1; a run that diverged is marked
    (``divergence``)."""
    x_hat, dt = estimator.batch_x_hat, scenario.dt  # (runs, n) view, updated in place by the estimator
    for k in range(scenario.steps):
        if events and k in events:
            events[k](estimator)
        u = divergence.control(k, control(k, x_hat, dt), estimator)
        try:
            sensing.step(k, plant, estimator, record, u, dt, divergence.running)
        except FloatingPointError:  # every run took the step; the runs that went non-finite are found below
            non_finite = True
        else:
            non_finite = False
        plant.step(u, dt)
        if divergence.check(k, estimator, plant) == 0 and non_finite:  # not a run's state: a bug to see
            raise FloatingPointError(f'the {estimator.kind} state became non-finite')
        record.controls[:, k] = plant.applied
        record.sample(k + 1, plant, x_hat, estimator.batch_P)
        if estimator.spiking:
            step_spikes = estimator.batch_spikes
            record.spikes[:, k] = step_spikes.sum(axis=1)
            record.raster[k] = step_spikes[0]
        if on_step is not None:
            on_step(k)


class _Record:
    """The trajectories :func:`simulate` fills, one sample per time."""

    def __init__(self, estimator, runs: int, steps: int):
        model = estimator.model
        n, covariance, spiking = model.n_state, estimator.has_covariance, estimator.spiking
        self.truth = np.empty((runs, steps + 1, n))
        self.estimate = np.empty((runs, steps + 1, n))
        self.cov = np.empty((runs, steps + 1, n)) if covariance else None
        self.controls = np.empty((runs, steps, model.n_input))
        self.spikes = np.zeros((runs, steps), dtype=np.int64) if spiking else None
        self.raster = np.zeros((steps, estimator.neuron_count), dtype=np.int16) if spiking else None
        self.nees = np.empty((runs, steps + 1)) if covariance else None
        self.nis = np.empty((runs, steps)) if covariance else None

    def discard(self, diverged_at: np.ndarray) -> None:
        """NaN for every sample of a run after the step it diverged at (controls and NIS from
        that step on), no spikes from then on."""
        for b in np.flatnonzero(diverged_at >= 0):
            k = int(diverged_at[b])
            for samples in (self.truth, self.estimate, self.cov, self.nees):
                if samples is not None:
                    samples[b, k + 1:] = np.nan
            self.controls[b, k:] = np.nan
            if self.nis is not None:
                self.nis[b, k:] = np.nan
            if self.spikes is not None:
                self.spikes[b, k:] = 0
                if b == 0:
                    self.raster[k:] = 0

    def sample(self, k: int, plant, x_hat: np.ndarray, covariance: np.ndarray | None) -> None:
        """Truth, estimate, covariance diagonal and NEES at time k."""
        self.truth[:, k] = plant.x
        self.estimate[:, k] = x_hat
        if covariance is not None:
            self.cov[:, k] = np.diagonal(covariance, axis1=1, axis2=2)
            self.nees[:, k] = normalised_squares(plant.x - x_hat, covariance)


def truth_plant(scenario: Scenario, seeds: Sequence[int]):
    """The scenario's truth: the model (exact ZOH with process noise), or Basilisk."""
    if scenario.basilisk is None:
        return Plant(scenario.truth_model or scenario.model, scenario.x0, scenario.process_noise, seeds,
                     noise_reading=scenario.truth_noise)
    if scenario.truth_noise != 'spectral_density':
        raise ValueError('truth_noise applies to the model truth only (the Basilisk truth draws its '
                         'own noise): use truth_noise: spectral_density with plant: basilisk')
    from .basilisk_truth import BasiliskPlant
    settings = scenario.basilisk
    return BasiliskPlant(scenario.x0, scenario.process_noise, seeds, dt=scenario.dt, orbit=settings.orbit,
                         chaser_mass=settings.chaser_mass, thrust_limit=settings.thrust_limit,
                         cache_dir=settings.cache_dir)


def normalised_squares(errors: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """e^T P^-1 e per run: ``errors`` (runs, d), ``covariances`` (runs, d, d). A covariance
    that cannot be inverted gives inf (an overconfident filter, not a crash)."""
    try:
        solved = np.linalg.solve(covariances, errors[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return np.full(errors.shape[0], np.inf)
    return np.einsum('bi,bi->b', errors, solved)


def twin_of(kind: str) -> str | None:
    """The non-spiking filter a spiking filter implements (None for a non-spiking kind)."""
    return TWIN_OF.get(kind)


__all__ = [
    'GaussianStream', 'Plant', 'PositionSensor', 'Scenario', 'SimulationResult', 'lqr_control',
    'lqr_gain', 'matrix_sqrt', 'rendezvous_scenario', 'simulate', 'twin_of', 'van_der_pol_scenario',
]

