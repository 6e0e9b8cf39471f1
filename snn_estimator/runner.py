"""Feeding a filter from a message stream: pairing, gating, start-up and recovery, no ROS.

A middleware delivers measurements z_k and controls u_k (stamped t_k) in any order, late,
twice, or not at all. :class:`FilterRunner` turns that stream into the filter's steps
``x_hat_{k+1} = estimator.step(z_k, u_k, dt)`` in stamp order, exactly as the offline
simulator steps (so a ROS run equals an offline run), and decides what to do with everything
else:

* gating: inputs that cannot be used are rejected with a reason (duplicate, too old, stale,
  misaligned, in the future, before the start) and counted;
* pairing: a step runs when z_k and u_k are both here; a u_k still missing two measurements
  later is replaced by the last control (as the plant holds it); a z_k missing while the
  clock runs two steps ahead is predicted over (sensor dropout);
* start-up (:meth:`start`): from the configured initial state at the first measurement, from
  an earlier estimator's newest estimate (hot swap: the measurements since then are
  replayed), or from a least-squares fit of a measurement history (a restart after a crash);
* recovery: a persistently inconsistent innovation (NIS) or a non-finite state re-initialises
  the filter from the measurement; a restart (clock jump, reset) waits for the next
  measurement.

Stamps are integer nanoseconds. The caller supplies the clock reading ``now_ns`` (0 when there
is no clock yet), a wall clock (for the dropout wait) and a ``publish(stamp_ns)`` callback
that is called after each estimate (the estimator then holds x_hat at ``stamp_ns``).
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np

from .catalog import START_MODES  # noqa: F401 (re-exported)
from .estimators import Estimator
from .gates import NS, seconds_ahead, seconds_to_ns
from .initialization import least_squares_start
from .plant_runner import control_in_force

#: Controls kept for pairing and replay.
CONTROL_MEMORY = 2000


@dataclass(frozen=True)
class RunnerSettings:
    """How the runner gates, pairs and recovers. Times in seconds."""

    #: Step of the filter and of the stamps.
    time_step: float
    #: Measurements more than this behind the newest one (stragglers), or stamped more than this
    #: plus two steps ahead of the clock, are rejected.
    max_input_age: float = 1.0
    #: NIS above which a step counts as inconsistent, and how many in a row re-initialise (0:
    #: never).
    nis_threshold: float = 25.0
    nis_window: int = 10
    #: Wall-clock seconds without any measurement before the clock may be predicted up to.
    dropout_wait: float = 0.25
    #: Seconds of measurement history a least-squares start fits.
    initial_fit_window: float = 10.0
    #: Without a running clock, a measurement this far before the estimate time means the time
    #: base restarted.
    time_jump_threshold: float = 1.0
    #: Simulated s a control stays in force after its stamp (then zero thrust), as the plant
    #: applies it (snn_estimator.plant_runner.control_in_force).
    control_validity: float = 0.5


@dataclass
class History:
    """What the topics held when the filter joined: stamp (ns) -> value."""

    measurements: Mapping[int, np.ndarray]
    controls: Mapping[int, np.ndarray]
    #: Estimates an earlier estimator published: stamp -> (x, covariance or None).
    estimates: Mapping[int, tuple]


class FilterRunner:
    """Steps ``estimator`` from time-stamped inputs (see the module docstring)."""

    def __init__(self, estimator: Estimator, settings: RunnerSettings, measurement_covariance,
                 publish: Callable[[int], None], log: Callable[[str, str], None] | None = None,
                 wall_clock: Callable[[], float] = time.monotonic):
        self.estimator = estimator
        self.settings = settings
        #: R per sample, for the NIS check and the least-squares start.
        self.measurement_covariance = np.asarray(measurement_covariance, dtype=float)
        self._publish = publish
        self._log = log or (lambda level, message: None)
        self._wall = wall_clock
        self._dt_ns = seconds_to_ns(settings.time_step)
        self.time_ns: int | None = None       # stamp of the current estimate
        self.start_ns: int | None = None      # stamp the filter started at
        self._pending: dict[int, np.ndarray] = {}
        self._from_history: set[int] = set()  # queued stamps that came with the start-up history
        self._controls: dict[int, np.ndarray] = {}
        self._last_measurement_ns: int | None = None
        self._newest_ns: int | None = None
        self._last_arrival = wall_clock()
        self._held = {}  # stamp -> u: the newest control used, while it may still be in force
        self._expired = False
        self._high_nis = 0
        self._clock_agrees: bool | None = None  # stamps on the clock's time base (None: not known)
        self._awaiting_start = False
        self.rejected = Counter()          # measurements, by reason
        self.control_rejected = Counter()  # controls, by reason
        self.events = Counter()            # starts, restarts, re-initialisations, ...
        self.measurements_received = 0
        self.measurements_used = 0
        self.measurements_dropped = 0
        self.measurements_repeated = 0
        self.controls_missing = 0
        self.dropout_steps = 0
        self.step_seconds: list[float] = []

    # ---------------------------------------------------------------- state
    @property
    def started(self) -> bool:
        return self.time_ns is not None

    @property
    def pending(self) -> int:
        return len(self._pending)

    def has_measurement(self, stamp_ns: int) -> bool:
        """True when a measurement stamped ``stamp_ns`` is queued or was used since the start
        (the same sample again: a resend, not new information)."""
        if stamp_ns in self._pending:
            return True
        last = self._last_measurement_ns
        return last is not None and self.start_ns is not None and self.start_ns <= stamp_ns <= last

    def repeated(self) -> None:
        """Count a measurement that came again and was answered again (not stepped)."""
        self.measurements_received += 1
        self.measurements_repeated += 1

    def replace_settings(self, settings: RunnerSettings) -> None:
        """New gating/recovery settings between two steps (the time step must stay)."""
        if seconds_to_ns(settings.time_step) != self._dt_ns:
            raise ValueError('time_step cannot change while running')
        self.settings = settings

    # ---------------------------------------------------------------- inputs
    def measurement(self, stamp_ns: int, z: np.ndarray, now_ns: int = 0) -> str | None:
        """Offer z stamped ``stamp_ns``; None if accepted, else the reason it was rejected
        (also counted). Steps the filter as far as the inputs allow."""
        self.measurements_received += 1
        reason = self._gate_measurement(stamp_ns, now_ns)
        if reason is not None:
            self.rejected[reason] += 1
            return reason
        self._newest_ns = stamp_ns if self._newest_ns is None else max(self._newest_ns, stamp_ns)
        self._last_arrival = self._wall()
        self._check_time_base(stamp_ns, now_ns)
        self._pending[stamp_ns] = np.asarray(z, dtype=float)
        if self._awaiting_start and not self.started:
            self._begin(min(self._pending), publish=True)
            self.events['cold_starts'] += 1
            self._log('info', f'started from the parameters at t = {self.start_ns / NS:.3f} s')
        self._process()
        return None

    def _gate_measurement(self, stamp_ns: int, now_ns: int) -> str | None:
        s = self.settings
        where = f'measurement at {stamp_ns / NS:.3f} s'
        if (self.started and now_ns <= 0
                and stamp_ns < self.time_ns - seconds_to_ns(s.time_jump_threshold)):
            # no clock: stamps far in the past mean the time base restarted (a bag loop)
            self.restart(f'measurement time went back from {self.time_ns / NS:.3f} s to '
                         f'{stamp_ns / NS:.3f} s', 'time_jumps')
        if stamp_ns in self._pending or stamp_ns == self._last_measurement_ns:
            return self._say('duplicate', f'second {where}')
        if self.started and stamp_ns < self._newest_ns - seconds_to_ns(s.max_input_age):
            return self._say('too_old', f'{where} is more than {s.max_input_age} s older than the '
                             f'newest measurement ({self._newest_ns / NS:.3f} s)')
        if self.started and stamp_ns < self.time_ns:
            return self._say('stale', f'{where} is older than the estimate at {self.time_ns / NS:.3f} s')
        if self.started and (stamp_ns - self.time_ns) % self._dt_ns:
            return self._say('misaligned', f'{where} does not fall on the estimate time '
                             f'{self.time_ns / NS:.3f} s plus steps of {s.time_step} s (time_step?)')
        ahead = self.seconds_ahead(stamp_ns, now_ns)
        if ahead:  # queued, it would make every real measurement 'too_old'
            return self._say('future', f'{where} is {ahead:.3f} s ahead of the clock')
        return None

    def seconds_ahead(self, stamp_ns: int, now_ns: int) -> float:
        """See :func:`snn_estimator.gates.seconds_ahead`."""
        return seconds_ahead(stamp_ns, now_ns, self.settings.max_input_age, self.settings.time_step)

    def control(self, stamp_ns: int, u: np.ndarray) -> str | None:
        """Offer u stamped ``stamp_ns``; None if accepted, else the rejection reason."""
        if self.start_ns is not None and stamp_ns < self.start_ns:
            self.control_rejected['before_init'] += 1
            self._log('warning', f'rejected control at {stamp_ns / NS:.3f} s: it predates the start '
                      f'at {self.start_ns / NS:.3f} s')
            return 'before_init'
        self._controls[stamp_ns] = np.asarray(u, dtype=float)
        if len(self._controls) > CONTROL_MEMORY:
            del self._controls[min(self._controls)]
        if self.started:
            self._process()
        return None

    def _say(self, reason: str, detail: str) -> str:
        self._log('warning', f'rejected {detail}')
        return reason

    def watchdog(self, now_ns: int) -> None:
        """Sensor dropout: with no measurement queued and none arrived for dropout_wait wall
        seconds, predict up to the clock once it is two steps past the estimate. Only while the
        measurements' stamps agree with the clock: with stamps on another time base (simulated
        stamps, a wall clock) the clock says nothing about missing samples."""
        if not self.started or self._pending or self._clock_agrees is False:
            return
        if self._wall() - self._last_arrival < self.settings.dropout_wait:
            return
        if now_ns >= self.time_ns + 2 * self._dt_ns:
            while self.time_ns + self._dt_ns <= now_ns:
                self._step(None, self.time_ns)

    def _check_time_base(self, stamp_ns: int, now_ns: int) -> None:
        """Note whether measurement stamps and the clock share a time base (within
        max_input_age plus two steps); say so once when they do not."""
        if now_ns <= 0:
            return  # no clock yet: nothing to compare with
        lead = seconds_to_ns(self.settings.max_input_age + 2 * self.settings.time_step)
        agrees = abs(now_ns - stamp_ns) <= lead
        if not agrees and self._clock_agrees is not False:
            self.events['stamps_off_the_clock'] += 1
            self._log('warning', f'measurement stamped {stamp_ns / NS:.3f} s with the clock at '
                      f'{now_ns / NS:.3f} s: not predicting over sensor dropouts (is use_sim_time set '
                      'as the sensor stamps?)')
        self._clock_agrees = agrees

    # ---------------------------------------------------------------- start-up
    def start(self, mode: str, history: History | None = None) -> str:
        """Choose how to start (see :data:`snn_estimator.catalog.START_MODES`) and do it; returns what was done:
        'last_estimate' (warm start, replaying the queued measurements), 'history'
        (least-squares fit), or 'waiting' (the configured initial state at the next
        measurement). 'auto' takes the first that the history allows, in that order."""
        if mode not in START_MODES:
            raise ValueError(f'start mode must be one of {", ".join(START_MODES)}; got {mode!r}')
        history = history or History({}, {}, {})
        for stamp_ns, z in sorted(history.measurements.items()):
            if stamp_ns not in self._pending:
                self._pending[stamp_ns] = np.asarray(z, dtype=float)
                self._from_history.add(stamp_ns)
            self._newest_ns = stamp_ns if self._newest_ns is None else max(self._newest_ns, stamp_ns)
        self.events['history_measurements'] += len(self._from_history)
        for stamp_ns, u in history.controls.items():
            self._controls.setdefault(stamp_ns, np.asarray(u, dtype=float))
        if mode in ('auto', 'last_estimate') and history.estimates:
            stamp_ns = max(history.estimates)
            x, covariance = history.estimates[stamp_ns]
            if self._warm_start(stamp_ns, x, covariance):
                return 'last_estimate'
        if mode in ('auto', 'history') and self._fit_start():
            return 'history'
        if mode in ('last_estimate', 'history'):
            self._log('warning', f'no {mode} to start from: starting from the parameters at the next measurement')
        # a fresh loop: the first measurement (queued or next) starts the filter
        self._awaiting_start = True
        if self._pending:
            self._begin(min(self._pending), publish=True)
            self.events['cold_starts'] += 1
            self._log('info', f'started from the parameters at t = {self.start_ns / NS:.3f} s '
                      f'({len(self._pending)} measurements queued)')
            self._process()
            return 'parameters'
        return 'waiting'

    def _warm_start(self, stamp_ns: int, x: np.ndarray, covariance: np.ndarray | None) -> bool:
        """Start from an earlier estimator's estimate at ``stamp_ns`` (hot swap)."""
        estimator = self.estimator
        estimator.reset()
        try:
            estimator.set_state(x, self.usable_covariance(covariance))
        except ValueError as error:
            self._log('warning', f'cannot warm start from the earlier estimate: {error}')
            return False
        self._drop({t for t in self._pending if t < stamp_ns}, 'it predates the warm start')
        self._begin(stamp_ns, publish=False)
        self.events['warm_starts'] += 1
        self._log('info', f'warm start from the estimate of {stamp_ns / NS:.3f} s; replaying '
                  f'{len(self._pending)} measurements')
        self._process()
        return True

    def _fit_start(self) -> bool:
        """Least-squares start over the newest initial_fit_window seconds of queued
        measurements (controls from the controls' history, the last one held where missing);
        the filter starts at the newest, which its next step uses."""
        window_ns = seconds_to_ns(self.settings.initial_fit_window)
        if not self._pending:
            return False
        newest = max(self._pending)
        stamps = sorted(t for t in self._pending if t >= newest - window_ns)
        if (newest - stamps[0]) < window_ns - self._dt_ns // 2:
            return False  # not a full window: the filter did not join a running loop
        known, validity_ns = [], seconds_to_ns(self.settings.control_validity)
        held = dict(self._held)
        for stamp_ns in stamps:
            u = self._control_for(stamp_ns)
            if u is None:
                u = control_in_force(held, stamp_ns, validity_ns, self.estimator.model.n_input)[0]
            else:
                held = {stamp_ns: u}
            known.append(u)
        try:
            x, covariance = least_squares_start(
                self.estimator.model, np.asarray(stamps) / NS, [self._pending[t] for t in stamps],
                known, self.measurement_covariance)
            self.estimator.reset()
            self.estimator.set_state(x, covariance if self.estimator.has_covariance else None)
        except (ValueError, np.linalg.LinAlgError) as error:
            self._log('warning', f'no least-squares start from the history: {error}')
            return False
        self._drop({t for t in self._pending if t < stamps[0]}, 'older than the least-squares window')
        for stamp_ns in stamps[:-1]:
            del self._pending[stamp_ns]
        self.measurements_used += len(stamps) - 1
        self.events['history_starts'] += 1
        self._begin(stamps[-1], publish=True)
        self._log('info', f'started from a least-squares fit of {len(stamps) - 1} measurements '
                  f'({stamps[0] / NS:.1f}-{stamps[-2] / NS:.1f} s) at t = {stamps[-1] / NS:.3f} s')
        self._process()
        return True

    def usable_covariance(self, blocks: np.ndarray | None) -> np.ndarray | None:
        """A received covariance if it is one (finite, symmetric, positive definite on each
        published block), else P0; None for a filter without a covariance."""
        if not self.estimator.has_covariance:
            return None
        p0 = self.estimator.settings.initial_covariance
        if blocks is None:
            return p0
        blocks = np.asarray(blocks, dtype=float)
        n = blocks.shape[0]
        half = n // 2
        if (np.all(np.isfinite(blocks)) and np.allclose(blocks, blocks.T)
                and np.all(np.linalg.eigvalsh(blocks[:half, :half]) > 0)
                and np.all(np.linalg.eigvalsh(blocks[half:, half:]) > 0)):
            return blocks
        return p0

    def _begin(self, stamp_ns: int, publish: bool) -> None:
        self.time_ns = self.start_ns = stamp_ns
        self._from_history = {t for t in self._from_history if t in self._pending}
        self._awaiting_start = False
        self._controls = {t: u for t, u in self._controls.items() if t >= stamp_ns}
        if publish:
            self._publish(stamp_ns)

    def restart(self, why: str, event: str) -> None:
        """Back to the configured initial state, started again by the next measurement."""
        self.events[event] += 1
        self._log('warning', f'{why}: restarting the filter from its initial state')
        self.estimator.reset()
        self.time_ns = self.start_ns = self._last_measurement_ns = self._newest_ns = None
        self._drop(set(self._pending), 'the filter restarted')
        self._controls.clear()
        self._high_nis = 0
        self._awaiting_start = True

    def set_state(self, x: np.ndarray, covariance: np.ndarray | None) -> None:
        """Replace the estimate (ValueError, nothing changed, if it cannot be represented)."""
        self.estimator.set_state(x, self.usable_covariance(covariance))
        self._high_nis = 0
        self.events['set_state'] += 1

    def _drop(self, stamps, why: str) -> None:
        """Discard queued measurements: counted as dropped (not as rejected), except those of
        the start-up history that the start did not need."""
        for stamp_ns in sorted(stamps):
            del self._pending[stamp_ns]
            if stamp_ns in self._from_history:
                self._from_history.discard(stamp_ns)
                continue
            self.measurements_dropped += 1
            self._log('warning', f'dropped the measurement at {stamp_ns / NS:.3f} s: {why}')

    # ---------------------------------------------------------------- stepping
    def _control_for(self, stamp_ns: int) -> np.ndarray | None:
        u = self._controls.get(stamp_ns)
        if u is not None:
            return u
        for control_ns, value in self._controls.items():
            if abs(control_ns - stamp_ns) * 2 < self._dt_ns:
                return value
        return None

    def _process(self) -> None:
        """Step through every measurement whose control is known (in stamp order); a missing
        measurement between two that came is predicted over."""
        while self._pending and self.started:
            first = min(self._pending)
            if first < self.time_ns or (first - self.time_ns) % self._dt_ns:
                self._drop({first}, 'it does not fall on a step of the estimate')
                continue
            if self._control_for(self.time_ns) is None and len(self._pending) <= 2:
                return  # wait: the next measurement may overtake this step's control
            self._step(self._pending.pop(first) if first == self.time_ns else None, self.time_ns)

    def _in_force(self, stamp_ns: int) -> np.ndarray:
        """The control the plant applied from ``stamp_ns`` when none stamped for it came: the
        last one while younger than control_validity, else zero thrust (the plant's rule)."""
        validity_ns = seconds_to_ns(self.settings.control_validity)
        u, stamp = control_in_force(self._held, stamp_ns, validity_ns, self.estimator.model.n_input)
        if stamp is None and self._held:
            self.events['controls_expired'] += 1
            if not self._expired:
                self._log('warning', f'the control of t = {max(self._held) / NS:.3f} s expired at t = '
                          f'{stamp_ns / NS:.3f} s: predicting with zero thrust, as the plant applies')
            self._expired = True
        return u

    def _step(self, z: np.ndarray | None, stamp_ns: int) -> None:
        u = self._control_for(stamp_ns)
        if u is None:
            u = self._in_force(stamp_ns)
            self.controls_missing += 1
            self._log('warning', f'no control for t = {stamp_ns / NS:.3f} s: using the one in force')
        else:
            self._held, self._expired = {stamp_ns: u}, False
        if z is None:
            self.dropout_steps += 1
        else:
            self.measurements_used += 1
            self._last_measurement_ns = stamp_ns
            self._check_consistency(z)
        started = time.perf_counter()
        try:
            self.estimator.step(z, u, self.settings.time_step)
        except FloatingPointError as error:
            self._reinitialise(z, str(error), 'non_finite_state')
        self.step_seconds.append(time.perf_counter() - started)
        if len(self.step_seconds) > 2000:
            del self.step_seconds[:1000]
        self.time_ns = stamp_ns + self._dt_ns
        self._controls = {t: v for t, v in self._controls.items() if t > stamp_ns}
        self._publish(self.time_ns)

    def _check_consistency(self, z: np.ndarray) -> None:
        """NIS over nis_threshold for nis_window steps in a row means the filter lost the
        truth: re-initialise from the measurement."""
        nis = float(self.estimator.innovation_nis(z, self.measurement_covariance)[0])
        s = self.settings
        self._high_nis = self._high_nis + 1 if nis > s.nis_threshold else 0
        if self._high_nis >= s.nis_window > 0:
            self._reinitialise(z, f'normalised innovation squared {nis:.1f} > {s.nis_threshold} '
                               f'for {self._high_nis} steps', 'inconsistent_innovation')

    def _reinitialise(self, z: np.ndarray | None, why: str, reason: str) -> None:
        """Measured states from ``z``, the rest of the estimate kept where finite (else the
        initial state), covariance P0."""
        est = self.estimator
        x = np.array(est.x_hat, dtype=float)
        x = np.where(np.isfinite(x), x, est.settings.initial_state)
        if z is not None:
            c = est.model.measurement_matrix
            measured = np.flatnonzero(np.abs(c).sum(axis=0))
            x[measured] = np.linalg.pinv(c)[measured] @ z
        try:
            est.reset(x, est.settings.initial_covariance)
        except ValueError:  # not representable (absurd measurement): back to the parameters
            est.reset()
        self._high_nis = 0
        self.events[f'reinitialisations.{reason}'] += 1
        self._log('error', f'filter re-initialised from the measurement: {why}')

    # ---------------------------------------------------------------- reporting
    def values(self) -> dict:
        """Counters for diagnostics: measurements received = rejected + used + dropped + pending +
        repeated."""
        est = self.estimator
        steps = est.steps
        times = np.asarray(self.step_seconds[-1000:]) * 1e6
        values = {
            'filter': est.kind, 'neurons': est.neuron_count, 'steps': steps,
            'measurements_received': self.measurements_received,
            'measurements_used': self.measurements_used, 'measurements_dropped': self.measurements_dropped,
            'measurements_repeated': self.measurements_repeated,
            'measurements_pending': len(self._pending),
            'spikes_total': est.total_spikes,
            'spike_fraction': (est.total_spikes / (steps * est.neuron_count)
                               if steps and est.neuron_count else 0.0),
            'silenced_neurons': len(est.silenced),
            'step_time_us_last': float(times[-1]) if times.size else 0.0,
            'step_time_us_median': float(np.median(times)) if times.size else 0.0,
            'controls_missing': self.controls_missing, 'dropout_steps': self.dropout_steps,
        }
        values['measurements_rejected'] = sum(self.rejected.values())
        values.update({f'measurements_rejected.{k}': v for k, v in sorted(self.rejected.items())})
        values['controls_rejected'] = sum(self.control_rejected.values())
        values.update({f'controls_rejected.{k}': v for k, v in sorted(self.control_rejected.items())})
        values.update(sorted(self.events.items()))
        values['reinitialisations'] = sum(v for k, v in self.events.items() if k.startswith('reinit'))
        return values

    def problems(self) -> list[str]:
        """What a diagnostics status should warn about."""
        problems = []
        rejected = sum(self.rejected.values()) + sum(self.control_rejected.values())
        if rejected:
            problems.append(f'{rejected} inputs rejected')
        if self.controls_missing:
            problems.append(f'{self.controls_missing} controls missing')
        if self.dropout_steps:
            problems.append(f'{self.dropout_steps} steps without measurement')
        reinit = sum(v for k, v in self.events.items() if k.startswith('reinit'))
        if reinit:
            problems.append(f'{reinit} re-initialisations')
        return problems



class Standby:
    """When a standby estimator should take over: its own estimate is newer than the newest one
    the active estimator published for ``timeout`` wall-clock seconds, or by two steps of
    simulated time (the active one died or was deactivated; in lockstep the clock stops with
    it, so the wall clock decides; in realtime the clock runs on, so it does)."""

    def __init__(self, timeout: float, time_step: float, wall_clock: Callable[[], float] = time.monotonic):
        self.timeout = timeout
        self._lag_ns = 2 * seconds_to_ns(time_step)
        self._wall = wall_clock
        self.foreign_ns = -1  # newest estimate another estimator published
        self._ahead_since: float | None = None

    def saw(self, stamp_ns: int) -> None:
        """An estimate another estimator published."""
        self.foreign_ns = max(self.foreign_ns, stamp_ns)

    def due(self, own_ns: int, start_ns: int) -> bool:
        """True when the standby, whose estimate is at ``own_ns``, should activate."""
        if own_ns <= self.foreign_ns:
            self._ahead_since = None
            return False
        self._ahead_since = self._ahead_since or self._wall()
        lag_ns = own_ns - max(self.foreign_ns, start_ns)
        return self._wall() - self._ahead_since >= self.timeout or lag_ns >= self._lag_ns
