"""simulate(): the closed loop on the blocks the ROS nodes wrap (truth, sensors, LQR:
snn_estimator.plant).

One step of the loop at t_k (identical in the ROS pipeline):
``u_k = -K x_hat_k``; ``z_k = C x_k + v_k``; ``x_hat_{k+1} = estimator.step(z_k, u_k, dt)``;
``x_{k+1} = plant.step(u_k, dt)``.

Random streams: component ``c`` of run ``b`` draws from ``default_rng([seed + b, c])`` with
c = 1 (plant process noise), 2 (sensor noise), 3 (decoder / membrane noise), so a single ROS
run with seed s reproduces run 0 of an offline batch with seed s.

"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Callable, Sequence

import numpy as np

from snn_estimator.config import EstimatorConfig
from snn_estimator.filters.estimators import make_estimator
from snn_estimator.plant.control import lqr_control, lqr_gain
from snn_estimator.plant.sensors import FusedSensor, MeasurementSensor, PositionSensor
from snn_estimator.plant.truth import Plant

from . import compiled_loop
from .results import SimulationResult, normalised_squares
from .scenarios import Scenario
from .sums import ChunkSink, LoopSums

#: How simulate() steps its loop (see simulate).
ENGINES = ('auto', 'compiled', 'reference')


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
        sink = (compiled_loop.FullRecord(record, runs, scenario.model.n_state, estimator.network.r.shape[1])
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
    from snn_estimator.plant.basilisk_truth import BasiliskPlant
    settings = scenario.basilisk
    return BasiliskPlant(scenario.x0, scenario.process_noise, seeds, dt=scenario.dt, orbit=settings.orbit,
                         chaser_mass=settings.chaser_mass, thrust_limit=settings.thrust_limit,
                         cache_dir=settings.cache_dir)
