"""Feeding a filter from a message stream: pairing, gating, start-up and recovery, no ROS.

A middleware delivers measurements z_k and controls u_k (stamped t_k) in any order, late,
twice, or not at all. :class:`FilterRunner` turns that stream into the filter's steps
``x_hat_{k+1} = estimator.step(z_k, u_k, dt)`` in stamp order, exactly as the offline
simulator steps (so a ROS run equals an offline run), and decides what to do with everything
else. It is composed of parts, each a plain class that owns its state and is tested alone:

* gating (:mod:`~snn_estimator.runners.measurement_queue`): measurements that cannot be used
  are rejected with a reason (duplicate, too old, stale, misaligned, in the future) and
  counted, the others queued until their step; controls before the start are rejected too
  (:mod:`~snn_estimator.runners.control_book`);
* pairing (here): a step runs when z_k and u_k are both here; a u_k still missing two
  measurements later is replaced by the last control (as the plant holds it); a z_k missing
  while the clock runs two steps ahead is predicted over (sensor dropout);
* start-up (:meth:`FilterRunner.start`, :mod:`~snn_estimator.runners.start_up`): from the
  configured initial state at the first measurement, from an earlier estimator's newest estimate
  (hot swap: the measurements since then are replayed), or from a least-squares fit of a
  measurement history (a restart after a crash);
* recovery (:mod:`~snn_estimator.runners.recovery`): a persistently inconsistent innovation
  (NIS), a non-finite state or a reset on request re-initialises the filter from the data (a
  least-squares fit of the recent measurements, never the parameters' initial state
  mid-flight; reset storms are reported); a new time base (the clock or the stamps went
  back) starts again from the parameters at the next measurement;
* the control of a step (:mod:`~snn_estimator.runners.control_book`): the one the plant reports
  it stepped with (:meth:`FilterRunner.applied`, its ``applied_control``) once a plant reports
  them, so estimate and truth agree on what was applied also when a control came after a
  realtime plant's tick; else (no such report, or it was lost) the controller's u_k; a missing
  control: the one in force by the plant's rule. A step whose report is not here yet is taken
  at once with the controller's u_k and corrected if the report differs
  (:mod:`~snn_estimator.runners.provisional`; ``provisional_steps``);
* diagnostics (:mod:`~snn_estimator.runners.reporting`): the parts' counters.

How measurement stamps relate to the filter's steps (``measurement_timing``, docs/decisions.md,
31): ``grid``: z_k at t_k steps the filter to t_k + time_step, published at once (a one-step
prediction; stamps off the grid are rejected as misaligned); ``any``: z_j is the filter's input
from t_j until the next measurement's stamp t_{j+1} (a zero-order hold, as a continuous-time
filter or a spiking network sees a sampled sensor): the arrival of z_{j+1} steps the filter over
[t_j, t_{j+1}) with dt = t_{j+1} - t_j and publishes x_hat(t_{j+1}). On grid stamps both publish
the same estimates at the same stamps. An interval of :data:`HOLD_LIMIT` steps or more is a
dropout: the measurement is held one step, the rest predicted.

Stamps are integer nanoseconds. The caller supplies the clock reading ``now_ns`` (0 when there
is no clock yet), a wall clock (for the dropout wait) and a ``publish(stamp_ns)`` callback
that is called after each estimate (the estimator then holds x_hat at ``stamp_ns``), and
optionally ``republish(stamp_ns)`` for an estimate corrected after it was published (default:
``publish``): every stamp is published once as it is first estimated, and again each time a
correction changes it.
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass
from typing import Any, Callable, Iterable

import numpy as np

from snn_estimator.catalog import MEASUREMENT_TIMINGS, START_MODES
from snn_estimator.filters.estimators import CovarianceLost, Estimator

from .control_book import ControlBook
from .gates import NS, seconds_to_ns
from .measurement_queue import MeasurementQueue
from .provisional import HeldStep, ProvisionalLog
from .recovery import Recovery, RestartTrigger
from .reporting import RunnerReport
from .start_up import History, StartUp

#: measurement_timing any: an interval between two measurements of this many time steps or more
#: is a dropout (the measurement held one step, the rest predicted).
HOLD_LIMIT = 2
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
    #: applies it (snn_estimator.runners.plant_runner.control_in_force).
    control_validity: float = 0.5
    #: 'grid': measurement stamps fall on the estimate time plus steps of time_step (the loop's
    #: sensor); 'any': stamped at any time (a sensor on its own clock), each measurement held
    #: until the next one's stamp (see :data:`MEASUREMENT_TIMINGS`).
    measurement_timing: str = 'grid'
    #: Once the plant reports its applied controls: take a step at once with the controller's u_k
    #: and correct it when the report differs (True), or wait for the report (False: the estimate
    #: one realtime tick later). Grid timing only (snn_estimator.runners.provisional).
    provisional_steps: bool = True

    def __post_init__(self):
        if self.measurement_timing not in MEASUREMENT_TIMINGS:
            raise ValueError(f'measurement_timing must be one of {", ".join(MEASUREMENT_TIMINGS)}; '
                             f'got {self.measurement_timing!r}')




@dataclass(frozen=True)
class Checkpoint:
    """The state a step changes, from before it (a provisional step is taken again from it)."""

    time_ns: int
    estimator: Any
    recovery: tuple
    restart_trigger: tuple
    measurements: tuple
    controls: tuple


class FilterRunner:
    """Steps ``estimator`` from time-stamped inputs (see the module docstring).

    It holds the estimate time, the start time and its own events (starts, restarts,
    re-initialisations, and what its wrapper counts with :meth:`count`); the rest lives in its
    parts: :attr:`measurement_queue`, :attr:`control_book`, :attr:`start_up`,
    :attr:`provisional_log`, :attr:`restart_trigger`, :attr:`recovery` and :attr:`report`.
    """

    def __init__(self, estimator: Estimator, settings: RunnerSettings, measurement_covariance,
                 publish: Callable[[int], None], log: Callable[[str, str], None] | None = None,
                 wall_clock: Callable[[], float] = time.monotonic,
                 republish: Callable[[int], None] | None = None):
        self.estimator = estimator
        self._settings = settings
        #: R per sample, for the NIS check and the least-squares starts.
        self.measurement_covariance = np.asarray(measurement_covariance, dtype=float)
        self._publish = publish
        self._republish = republish or publish
        self._log = log or (lambda level, message: None)
        self._dt_ns = seconds_to_ns(settings.time_step)
        self._time_ns: int | None = None
        self._start_ns: int | None = None
        self._events = Counter()
        log = self._log
        self.measurement_queue = MeasurementQueue(settings.time_step, log, wall_clock)
        self.control_book = ControlBook(settings.time_step, estimator.model.n_input, log)
        self.start_up = StartUp(estimator, self.measurement_covariance, log)
        self.provisional_log = ProvisionalLog(settings.time_step, log)
        self.restart_trigger = RestartTrigger()
        #: Where a re-initialisation starts from (recent data, never the parameters mid-flight).
        self.recovery = Recovery(estimator, self.measurement_covariance, settings.initial_fit_window,
                                 settings.time_step, log=log)
        self.report = RunnerReport(estimator, self.measurement_queue, self.control_book, self.provisional_log,
                                   self.recovery, self._events)

    # ---------------------------------------------------------------- state
    @property
    def settings(self) -> RunnerSettings:
        return self._settings

    @property
    def time_ns(self) -> int | None:
        """Stamp of the current estimate (None: not started)."""
        return self._time_ns

    @property
    def start_ns(self) -> int | None:
        """Stamp the filter started at (None: not started)."""
        return self._start_ns

    @property
    def started(self) -> bool:
        return self._time_ns is not None

    @property
    def on_grid(self) -> bool:
        return self._settings.measurement_timing == 'grid'

    @property
    def events(self) -> Counter:
        """The runner's events (starts, restarts, re-initialisations, resets, ...) and its
        wrapper's; each part counts its own (all of them in :meth:`values`)."""
        return self._events

    def count(self, event: str) -> None:
        """Count a wrapper's event (set_state_rejected, yields, ...) in the diagnostics."""
        self._events[event] += 1

    def has_measurement(self, stamp_ns: int) -> bool:
        """True when a measurement stamped ``stamp_ns`` is queued or was used since the start
        (the same sample again: a resend, not new information)."""
        return self.measurement_queue.has(stamp_ns, self._start_ns)

    def repeated(self) -> None:
        """Count a measurement that came again and was answered again (not stepped)."""
        self.measurement_queue.count_repeat()

    def measurement_unreadable(self, reason: str) -> None:
        """Count a measurement message the wrapper could not read, by reason."""
        self.measurement_queue.unreadable(reason)

    def control_unreadable(self, reason: str) -> None:
        """Count a control message the wrapper could not read, by reason."""
        self.control_book.unreadable(reason)

    def replace_settings(self, settings: RunnerSettings) -> None:
        """New gating/recovery settings between two steps (the time step and the measurement
        timing must stay)."""
        if seconds_to_ns(settings.time_step) != self._dt_ns:
            raise ValueError('time_step cannot change while running')
        if settings.measurement_timing != self._settings.measurement_timing:
            raise ValueError('measurement_timing cannot change while running')
        self._settings = settings

    def values(self) -> dict:
        """Counters for diagnostics (:meth:`snn_estimator.runners.reporting.RunnerReport.values`)."""
        return self.report.values()

    def problems(self) -> list[str]:
        """What a diagnostics status should warn about."""
        return self.report.problems()

    @property
    def _provisional_allowed(self) -> bool:
        """Steps may be taken before the plant's report (grid timing only)."""
        return self._settings.provisional_steps and self.on_grid

    @property
    def _validity_ns(self) -> int:
        return seconds_to_ns(self._settings.control_validity)

    # ---------------------------------------------------------------- inputs
    def measurement(self, stamp_ns: int, z: np.ndarray, now_ns: int = 0) -> str | None:
        """Offer z stamped ``stamp_ns``; None if accepted, else the reason it was rejected
        (also counted). Steps the filter as far as the inputs allow."""
        self._restart_if_time_went_back(stamp_ns, now_ns)
        reason = self.measurement_queue.offer(stamp_ns, z, now_ns, self._time_ns, self._settings)
        if reason is not None:
            return reason
        if self.start_up.waiting and not self.started:
            self._cold_start()
        self._process()
        return None

    def no_measurement(self, stamp_ns: int, now_ns: int = 0) -> str | None:
        """The sensor sampled at ``stamp_ns`` and says it measured nothing (outside its field of
        view or range: docs/sensors.md, "What is not measured"): the filter predicts over that
        step as soon as its control is known, instead of waiting dropout_wait for a measurement
        that will not come. Gated like a measurement; None if accepted, else the reason."""
        self._restart_if_time_went_back(stamp_ns, now_ns)
        reason = self.measurement_queue.offer_unmeasured(stamp_ns, now_ns, self._time_ns, self._settings)
        if reason is not None or not self.started or not self.on_grid:
            return reason  # it starts at its first measurement; off the grid the next one ends a hold
        self.measurement_queue.put_unmeasured(stamp_ns)
        self._process()
        return None

    def _restart_if_time_went_back(self, stamp_ns: int, now_ns: int) -> None:
        """No clock and a stamp far in the past: the time base restarted (a bag loop)."""
        if self.measurement_queue.time_base_restarted(stamp_ns, now_ns, self._time_ns,
                                                      self._settings.time_jump_threshold):
            self.restart(f'measurement time went back from {self._time_ns / NS:.3f} s to '
                         f'{stamp_ns / NS:.3f} s', 'time_jumps')

    def control(self, stamp_ns: int, u: np.ndarray) -> str | None:
        """Offer u stamped ``stamp_ns``; None if accepted, else the rejection reason."""
        reason = self.control_book.offer(stamp_ns, u, self._start_ns)
        if reason is None and self.started:
            self._process()
        return reason

    def applied(self, stamp_ns: int, u: np.ndarray) -> str | None:
        """Offer the control the plant reports it stepped with from ``stamp_ns``; None if
        accepted, else the rejection reason. From the first one on, a step predicts with the
        plant's report: taken provisionally with the controller's u_k until it comes, corrected
        if it differs (snn_estimator.runners.provisional), or, without provisional steps, waiting
        for it (as long as it waits for a control)."""
        reason = self.control_book.offer_applied(stamp_ns, u, self._start_ns)
        if reason is not None:
            return reason
        redo = self.provisional_log.report(stamp_ns, np.asarray(u, dtype=float))
        if redo:
            self._take_again(redo)
        if self.started:
            self._process()
        return None

    def watchdog(self, now_ns: int) -> None:
        """Sensor dropout: with no measurement queued and none arrived for dropout_wait wall
        seconds, predict up to the clock once it is two steps past the estimate. Only while the
        measurements' stamps agree with the clock: with stamps on another time base (simulated
        stamps, a wall clock) the clock says nothing about missing samples."""
        queue = self.measurement_queue
        if not self.started or queue.pending_count or queue.clock_agrees is False:
            return
        if not queue.quiet_for(self._settings.dropout_wait):
            return
        if now_ns >= self._time_ns + 2 * self._dt_ns:
            if not self.on_grid:  # the held measurement's step first, then predictions
                self._advance_to(self._time_ns + (now_ns - self._time_ns) // self._dt_ns * self._dt_ns)
                return
            while self._time_ns + self._dt_ns <= now_ns:
                self._step(None, self._time_ns)

    # ---------------------------------------------------------------- start, restart, reset
    def start(self, mode: str, history: History | None = None) -> str:
        """Choose how to start (see :mod:`snn_estimator.runners.start_up`) and do it; returns what
        was done: 'last_estimate' (warm start, replaying the queued measurements), 'history'
        (least-squares fit), 'parameters' (the configured initial state at the first queued
        measurement) or 'waiting' (at the next measurement). 'auto' takes the first that the
        history allows, in that order."""
        if mode not in START_MODES:
            raise ValueError(f'start mode must be one of {", ".join(START_MODES)}; got {mode!r}')
        history = history or History({}, {}, {})
        self.measurement_queue.add_history(history.measurements)
        self.control_book.add_history(history.controls)
        if mode in ('auto', 'last_estimate') and history.estimates:
            stamp_ns = max(history.estimates)
            if self._warm_start(stamp_ns, *history.estimates[stamp_ns]):
                return 'last_estimate'
        if mode in ('auto', 'history') and self._fit_start():
            return 'history'
        if mode in ('last_estimate', 'history'):
            self._log('warning', f'no {mode} to start from: starting from the parameters at the next measurement')
        # a fresh loop: the first measurement (queued or next) starts the filter
        self.start_up.wait_for_first_measurement()
        if self.measurement_queue.pending_count:
            self._cold_start(f' ({self.measurement_queue.pending_count} measurements queued)')
            self._process()
            return 'parameters'
        return 'waiting'

    def _cold_start(self, note: str = '') -> None:
        """Start from the parameters at the first queued measurement."""
        self._begin(self.measurement_queue.first_stamp(), publish=True)
        self._events['cold_starts'] += 1
        self._log('info', f'started from the parameters at t = {self._start_ns / NS:.3f} s{note}')

    def _warm_start(self, stamp_ns: int, x: np.ndarray, covariance: np.ndarray | None) -> bool:
        """Start from an earlier estimator's estimate at ``stamp_ns`` (hot swap)."""
        if not self.start_up.from_estimate(x, covariance):
            return False
        self.measurement_queue.drop_before(stamp_ns, 'it predates the warm start')
        self._begin(stamp_ns, publish=False)
        self._events['warm_starts'] += 1
        self._log('info', f'warm start from the estimate of {stamp_ns / NS:.3f} s; replaying '
                  f'{self.measurement_queue.pending_count} measurements')
        self._process()
        return True

    def _fit_start(self) -> bool:
        """Least-squares start over the newest initial_fit_window seconds of queued
        measurements (controls from the controls' history, the one in force where missing);
        the filter starts at the newest, which its next step uses."""
        queue = self.measurement_queue
        stamps = self.start_up.fit_window(queue.measured_stamps(), seconds_to_ns(self._settings.initial_fit_window),
                                          self._dt_ns)
        if stamps is None:
            return False
        controls = self.control_book.controls_over(stamps, self._validity_ns)
        if not self.start_up.from_fit(stamps, [queue.z_at(t) for t in stamps], controls):
            return False
        queue.drop_before(stamps[0], 'older than the least-squares window')
        queue.take_fitted(stamps[:-1])
        self._events['history_starts'] += 1
        self._begin(stamps[-1], publish=True)
        self._log('info', f'started from a least-squares fit of {len(stamps) - 1} measurements '
                  f'({stamps[0] / NS:.1f}-{stamps[-2] / NS:.1f} s) at t = {stamps[-1] / NS:.3f} s')
        self._process()
        return True

    def _begin(self, stamp_ns: int, publish: bool) -> None:
        self._time_ns = self._start_ns = stamp_ns
        self.measurement_queue.begin()
        self.start_up.begun()
        self.control_book.keep_from(stamp_ns)
        self.provisional_log.forget()
        if publish:
            self._publish(stamp_ns)

    def reset(self, why: str) -> str:
        """A reset on request: mid-flight, the next measurement's step re-initialises the
        filter from the data (:class:`snn_estimator.runners.recovery.Recovery`), returns 'data'; before
        the filter ran, it starts from the parameters at the next measurement ('parameters')."""
        if self.started and self.measurement_queue.used:
            self.settle('a reset was requested')
            self._events['resets'] += 1
            self.restart_trigger.request(why)
            return 'data'
        self.restart(why, 'resets')
        return 'parameters'

    def restart(self, why: str, event: str) -> None:
        """A new time base (the clock or the stamps went back: a new flight): back to the
        configured initial state, started again by the next measurement."""
        self._events[event] += 1
        self._log('warning', f'{why}: restarting the filter from its initial state')
        self.estimator.reset()
        self.recovery.clear()
        self.restart_trigger.clear()
        self._time_ns = self._start_ns = None
        self.measurement_queue.restart()
        self.control_book.restart()
        self.provisional_log.forget()
        self.start_up.wait_for_first_measurement()

    def set_state(self, x: np.ndarray, covariance: np.ndarray | None) -> None:
        """Replace the estimate (ValueError, nothing changed, if it cannot be represented)."""
        self.settle('the state was set')
        self.estimator.set_state(x, self.start_up.usable_covariance(covariance))
        self.restart_trigger.forget_inconsistency()
        self._events['set_state'] += 1

    def settle(self, why: str = 'the filter is changed') -> None:
        """Accept every provisional step as it is, before something outside the steps changes the
        filter (:meth:`snn_estimator.runners.provisional.ProvisionalLog.settle`)."""
        self.provisional_log.settle(why)

    # ---------------------------------------------------------------- stepping
    def _process(self) -> None:
        """Step through every measurement whose control is known (in stamp order); a missing
        measurement between two that came is predicted over."""
        queue = self.measurement_queue
        while queue.pending_count and self.started:
            first = queue.first_stamp()
            if first < self._time_ns or (self.on_grid and (first - self._time_ns) % self._dt_ns):
                queue.drop({first}, 'it does not fall on a step of the estimate')
                continue
            if not self.on_grid and first == self._time_ns:
                queue.hold(queue.pop(first))  # the input from now to the next stamp
                continue
            if (not self.control_book.can_step(self._time_ns, self._provisional_allowed)
                    and queue.pending_count <= 2):
                return  # wait: the next measurement may overtake this step's control
            if self.on_grid:
                self._step(queue.pop(first) if first == self._time_ns else None, self._time_ns)
            else:
                self._advance_to(first)

    def _step(self, z: np.ndarray | None, stamp_ns: int, dt_ns: int | None = None,
              continued: bool = False, publish: bool = True) -> None:
        """One filter step from ``stamp_ns`` with input ``z`` (None: a prediction) over
        ``dt_ns`` (default: time_step), published at its end unless ``publish`` is False.
        ``continued``: a later part of one measurement's hold (counted, checked and recorded
        once, on its first part). A step taken before its control is final, or after one that
        was, is held in the provisional log with a checkpoint from before it."""
        if continued:
            return self._continue_hold(z, stamp_ns, dt_ns, publish)
        book = self.control_book
        held = self.provisional_log.held_count or book.before_report(stamp_ns, self._provisional_allowed)
        checkpoint = self._checkpoint() if held else None
        events_before = Counter(self._events) if held else None
        z_held = None if z is None or not held else np.array(z, dtype=float)
        u, final = book.step_control(stamp_ns, self._provisional_allowed, self._validity_ns)
        self.measurement_queue.stepped(stamp_ns, z)
        if z is not None:
            s, trigger = self._settings, self.restart_trigger
            why = trigger.requested or trigger.check(self._nis(z), s.nis_threshold, s.nis_window)
            if why:
                self._reinitialise(z, stamp_ns, *why)
            elif trigger.consistent:
                self.recovery.trusted(stamp_ns)
        started = time.perf_counter()
        dt = self._settings.time_step if dt_ns is None or dt_ns == self._dt_ns else dt_ns / NS
        self._filter_step(z, u, dt, stamp_ns)
        self.recovery.record(stamp_ns, z, u)
        if checkpoint is not None:
            self.provisional_log.hold(HeldStep(stamp_ns, z_held, checkpoint, np.array(u, dtype=float), final,
                                               self._events - events_before))
        self.report.step_took(time.perf_counter() - started)
        self._time_ns = stamp_ns + (self._dt_ns if dt_ns is None else dt_ns)
        book.forget_used(stamp_ns, self.provisional_log.oldest_stamp)
        if publish:
            (self._republish if self.provisional_log.replaying else self._publish)(self._time_ns)

    def _nis(self, z: np.ndarray) -> float:
        return float(self.estimator.innovation_nis(z, self.measurement_covariance)[0])

    def _checkpoint(self) -> Checkpoint:
        return Checkpoint(self._time_ns, self.estimator.snapshot(), self.recovery.snapshot(),
                          self.restart_trigger.snapshot(), self.measurement_queue.step_state(),
                          self.control_book.step_state())

    def _take_again(self, redo: list[HeldStep]) -> None:
        """The first of ``redo`` used another control than the plant applied: back to its
        checkpoint, then it and every later held step again, in order, republished."""
        checkpoint = redo[0].checkpoint
        self._time_ns = checkpoint.time_ns
        self.estimator.restore(checkpoint.estimator)
        self.recovery.restore(checkpoint.recovery)
        self.restart_trigger.restore(checkpoint.restart_trigger)
        self.measurement_queue.restore_step_state(checkpoint.measurements)
        self.control_book.restore_step_state(checkpoint.controls)
        for step in redo:
            self._events.subtract(step.counted)
        for key in [key for key, count in self._events.items() if count <= 0]:
            del self._events[key]
        with self.provisional_log.replay():
            for step in redo:
                if not self.started:
                    break
                self._step(step.z, step.stamp_ns)
        self.provisional_log.release()

    def _filter_step(self, z: np.ndarray | None, u: np.ndarray, dt: float, stamp_ns: int) -> None:
        """A filter step; a non-finite state or an indefinite P re-initialises it (never published)."""
        try:
            self.estimator.step(z, u, dt)
        except CovarianceLost as error:
            self._reinitialise(z, stamp_ns, str(error), 'covariance_lost')
        except FloatingPointError as error:
            self._reinitialise(z, stamp_ns, str(error), 'non_finite_state')

    def _reinitialise(self, z: np.ndarray | None, stamp_ns: int, why: str, reason: str) -> None:
        """Restart the filter at ``stamp_ns`` from the data (never the parameters' initial
        state mid-flight); a state the filter cannot represent leaves it as it is, counted."""
        self.restart_trigger.clear()
        x, covariance, source = self.recovery.restart_state(stamp_ns, z)
        est = self.estimator
        try:
            est.reset(x, covariance if est.has_covariance else None)
        except ValueError as error:
            self._events['reinitialisations_failed'] += 1
            self._log('error', f'cannot re-initialise from {source} ({error}): the filter goes on')
            return
        self._events[f'reinitialisations.{reason}'] += 1
        self._events[f'restarts_from.{source}'] += 1
        self.recovery.note_reset(stamp_ns)
        self._log('error', f'filter re-initialised at t = {stamp_ns / NS:.3f} s from {source.replace("_", " ")}: {why}')

    # ---------------------------------------------------------------- measurement_timing any
    def _advance_to(self, stamp_ns: int) -> None:
        """Step from the estimate time to ``stamp_ns`` with the held measurement as input, in
        equal steps of at most time_step (each a valid step: the one checked at configure, or
        shorter). An interval of HOLD_LIMIT time steps or more is a dropout: the measurement is
        held for one time step and the rest predicted."""
        interval = stamp_ns - self._time_ns
        held = self.measurement_queue.take_held()
        span = interval if interval < HOLD_LIMIT * self._dt_ns else self._dt_ns
        self._steps_over(held, span)
        if self.started and self._time_ns < stamp_ns:
            self._steps_over(None, stamp_ns - self._time_ns)

    def _steps_over(self, z: np.ndarray | None, span_ns: int) -> None:
        """Steps with input ``z`` covering ``span_ns`` from the estimate time: one step when the
        filter can take it (Estimator.check_time_step), else equal steps of at most time_step
        (the last one takes the nanoseconds left). Fewer is better for a held z: each step
        compares it with the estimate at the step's start, so parts of a hold lag the moving
        truth (x RMSE x2 at +-5 ms jitter when split). Predictions (``z`` None) always step by
        at most time_step, published each, as the grid runner's."""
        count = -(-span_ns // self._dt_ns)
        if z is not None and count > 1:
            try:
                self.estimator.check_time_step(span_ns / NS)
                count = 1
            except ValueError:
                pass
        end = self._time_ns + span_ns
        for k in range(count):
            if not self.started:
                return
            last = k == count - 1
            # a held measurement is answered once, at the end of its interval; predictions
            # are published every step (as the grid runner's)
            self._step(z, self._time_ns, end - self._time_ns if last else span_ns // count,
                       continued=k > 0 and z is not None, publish=last or z is None)

    def _continue_hold(self, z: np.ndarray, stamp_ns: int, dt_ns: int, publish: bool) -> None:
        """A later part of a held measurement's interval: the same z, the control in force, no
        new measurement counted."""
        u = self.control_book.final(stamp_ns)
        if u is None:
            u = self.control_book.in_force(stamp_ns, self._validity_ns)
        self._filter_step(z, u, dt_ns / NS, stamp_ns)
        self._time_ns = stamp_ns + dt_ns
        if publish:
            self._publish(self._time_ns)


class Standby:
    """Exactly one active estimator (docs/decisions.md, 24), decided from who is alive, not from
    the age of estimates (at start-up a late estimate says nothing about its estimator).
    :meth:`update` gives the number of other live estimators on `estimate` (liveliness QoS)
    and their node names (the graph):

    * a standby takes over when every other estimator it has seen is gone (killed, stopped,
      deactivated: its liveliness lease expired or it left), once its own filter runs;
    * an active estimator that sees another live one yields (deactivates and stands by) when
      the other's node name sorts before its own: of two started together, after a
      make-before-break swap or when a stopped one comes back, the first name keeps publishing.
    """

    def __init__(self):
        self.others_alive = 0
        self.others: list[str] = []
        self.seen = False  # another estimator was alive once

    def update(self, others_alive: int, others: Iterable[str]) -> None:
        self.others_alive = max(0, others_alive)
        self.others = sorted(others)
        self.seen = self.seen or (self.others_alive > 0 and bool(self.others))

    def takes_over(self, started: bool) -> bool:
        return started and self.seen and self.others_alive == 0

    def yields(self, own_name: str) -> bool:
        """True when an active estimator named ``own_name`` should stand down."""
        return self.others_alive > 0 and any(other < own_name for other in self.others)
