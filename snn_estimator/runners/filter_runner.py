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
* recovery: a persistently inconsistent innovation (NIS), a non-finite state or a reset on
  request re-initialises the filter from the data (:mod:`snn_estimator.runners.recovery`: a
  least-squares fit of the recent measurements, never the parameters' initial state
  mid-flight; reset storms are reported); a new time base (the clock or the stamps went
  back) starts again from the parameters at the next measurement;
* the control of a step: the one the plant reports it stepped with (:meth:`applied`, its
  ``applied_control``) once a plant reports them, so estimate and truth agree on what was applied
  also when a control came after a realtime plant's tick; else (no such report, or it was lost)
  the controller's u_k; a missing control: the one in force by the plant's rule
  (:mod:`snn_estimator.runners.plant_runner`). A step whose report is not here yet is taken at
  once with the controller's u_k and corrected if the report differs
  (:mod:`snn_estimator.runners.provisional`; ``provisional_steps``).

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
from typing import Callable, Iterable

import numpy as np

from snn_estimator.catalog import MEASUREMENT_TIMINGS, START_MODES  # noqa: F401 (START_MODES re-exported)
from snn_estimator.filters.estimators import Estimator

from .gates import NS, seconds_to_ns
from .provisional import PROVISIONAL_LIMIT, ProvisionalSteps  # noqa: F401 (PROVISIONAL_LIMIT re-exported)
from .recovery import Recovery
from .runner_parts import CONTROL_MEMORY, Controls, Gating, HeldMeasurements, History, Reporting, StartUp  # noqa: F401 (History, CONTROL_MEMORY re-exported)


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


class FilterRunner(Gating, StartUp, Reporting, HeldMeasurements, Controls, ProvisionalSteps):
    """Steps ``estimator`` from time-stamped inputs (see the module docstring)."""

    def __init__(self, estimator: Estimator, settings: RunnerSettings, measurement_covariance,
                 publish: Callable[[int], None], log: Callable[[str, str], None] | None = None,
                 wall_clock: Callable[[], float] = time.monotonic,
                 republish: Callable[[int], None] | None = None):
        self.estimator = estimator
        self.settings = settings
        #: R per sample, for the NIS check and the least-squares start.
        self.measurement_covariance = np.asarray(measurement_covariance, dtype=float)
        self._publish = publish
        self._republish = republish or publish
        self._provisional = []  # Held steps, oldest first (snn_estimator.runners.provisional)
        self._replaying = False
        self._log = log or (lambda level, message: None)
        self._wall = wall_clock
        self._dt_ns = seconds_to_ns(settings.time_step)
        self.time_ns: int | None = None       # stamp of the current estimate
        self.start_ns: int | None = None      # stamp the filter started at
        self._pending: dict[int, np.ndarray] = {}
        self._from_history: set[int] = set()  # queued stamps that came with the start-up history
        self._controls: dict[int, np.ndarray] = {}
        self._applied: dict[int, np.ndarray] = {}  # what the plant reports it stepped with, by stamp
        self._plant_reports = False  # a plant reports its applied controls: wait for them
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
        self.not_measured = 0  # samples the sensor said it could not measure (no_measurement)
        self._last_unmeasured_ns: int | None = None
        self.controls_missing = 0
        self.applied_received = 0  # the plant's reports of the control it applied
        self.dropout_steps = 0
        self.step_seconds: list[float] = []
        #: Where a re-initialisation starts from (recent data, never the parameters mid-flight).
        self.recovery = Recovery(estimator, self.measurement_covariance, settings.initial_fit_window,
                                 settings.time_step, log=self._log)
        self._reset_requested: tuple[str, str] | None = None
        #: measurement_timing any: the measurement the filter holds from the estimate time on
        self._held_z: np.ndarray | None = None

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
        last = max((t for t in (self._last_measurement_ns, self._last_unmeasured_ns) if t is not None), default=None)
        return last is not None and self.start_ns is not None and self.start_ns <= stamp_ns <= last

    def repeated(self) -> None:
        """Count a measurement that came again and was answered again (not stepped)."""
        self.measurements_received += 1
        self.measurements_repeated += 1

    @property
    def on_grid(self) -> bool:
        return self.settings.measurement_timing == 'grid'

    def replace_settings(self, settings: RunnerSettings) -> None:
        """New gating/recovery settings between two steps (the time step and the measurement
        timing must stay)."""
        if seconds_to_ns(settings.time_step) != self._dt_ns:
            raise ValueError('time_step cannot change while running')
        if settings.measurement_timing != self.settings.measurement_timing:
            raise ValueError('measurement_timing cannot change while running')
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
        self._check_time_base(stamp_ns, now_ns)
        self._queue(stamp_ns, np.asarray(z, dtype=float))
        if self._awaiting_start and not self.started:
            self._begin(min(self._pending), publish=True)
            self.events['cold_starts'] += 1
            self._log('info', f'started from the parameters at t = {self.start_ns / NS:.3f} s')
        self._process()
        return None

    def no_measurement(self, stamp_ns: int, now_ns: int = 0) -> str | None:
        """The sensor sampled at ``stamp_ns`` and says it measured nothing (outside its field of
        view or range: docs/sensors.md, "What is not measured"): the filter predicts over that
        step as soon as its control is known, instead of waiting dropout_wait for a measurement
        that will not come. Gated like a measurement; None if accepted, else the reason."""
        self.not_measured += 1  # outside the measurement counts (received = rejected + used + ...)
        reason = self._gate_measurement(stamp_ns, now_ns)
        if reason is not None:
            self.events[f'not_measured_rejected.{reason}'] += 1
            return reason
        if not self.started or not self.on_grid:
            return None  # it starts at its first measurement; off the grid the next one ends a hold
        self._queue(stamp_ns, None)
        self._last_unmeasured_ns = stamp_ns
        self._process()
        return None

    def _queue(self, stamp_ns: int, z: np.ndarray | None) -> None:
        """Hold an accepted input (z None: nothing measured) until its step."""
        self._newest_ns = stamp_ns if self._newest_ns is None else max(self._newest_ns, stamp_ns)
        self._last_arrival = self._wall()
        self._pending[stamp_ns] = z

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
            if not self.on_grid:  # the held measurement's step first, then predictions
                self._advance_to(self.time_ns + (now_ns - self.time_ns) // self._dt_ns * self._dt_ns)
                return
            while self.time_ns + self._dt_ns <= now_ns:
                self._step(None, self.time_ns)

    def _begin(self, stamp_ns: int, publish: bool) -> None:
        self.time_ns = self.start_ns = stamp_ns
        self._from_history = {t for t in self._from_history if t in self._pending}
        self._awaiting_start = False
        self._controls = {t: u for t, u in self._controls.items() if t >= stamp_ns}
        self._applied = {t: u for t, u in self._applied.items() if t >= stamp_ns}
        self._provisional.clear()
        if publish:
            self._publish(stamp_ns)

    def reset(self, why: str) -> str:
        """A reset on request: mid-flight, the next measurement's step re-initialises the
        filter from the data (:class:`snn_estimator.runners.recovery.Recovery`), returns 'data'; before
        the filter ran, it starts from the parameters at the next measurement ('parameters')."""
        if self.started and self.measurements_used:
            self.settle('a reset was requested')
            self.events['resets'] += 1
            self._reset_requested = (why, 'reset')
            return 'data'
        self.restart(why, 'resets')
        return 'parameters'

    def restart(self, why: str, event: str) -> None:
        """A new time base (the clock or the stamps went back: a new flight): back to the
        configured initial state, started again by the next measurement."""
        self.events[event] += 1
        self._log('warning', f'{why}: restarting the filter from its initial state')
        self.estimator.reset()
        self.recovery.clear()
        self._reset_requested = None
        self.time_ns = self.start_ns = self._last_measurement_ns = self._newest_ns = None
        self._last_unmeasured_ns = None
        self._held_z = None
        self._drop(set(self._pending), 'the filter restarted')
        self._controls.clear()
        self._applied.clear()
        self._provisional.clear()
        self._plant_reports = False
        self._high_nis = 0
        self._awaiting_start = True

    def set_state(self, x: np.ndarray, covariance: np.ndarray | None) -> None:
        """Replace the estimate (ValueError, nothing changed, if it cannot be represented)."""
        self.settle('the state was set')
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
    def _process(self) -> None:
        """Step through every measurement whose control is known (in stamp order); a missing
        measurement between two that came is predicted over."""
        while self._pending and self.started:
            first = min(self._pending)
            if first < self.time_ns or (self.on_grid and (first - self.time_ns) % self._dt_ns):
                self._drop({first}, 'it does not fall on a step of the estimate')
                continue
            if not self.on_grid and first == self.time_ns:
                self._held_z = self._pending.pop(first)  # the input from now to the next stamp
                continue
            if not self._can_step(self.time_ns) and len(self._pending) <= 2:
                return  # wait: the next measurement may overtake this step's control
            if self.on_grid:
                self._step(self._pending.pop(first) if first == self.time_ns else None, self.time_ns)
            else:
                self._advance_to(first)

    def _step(self, z: np.ndarray | None, stamp_ns: int, dt_ns: int | None = None,
              continued: bool = False, publish: bool = True) -> None:
        """One filter step from ``stamp_ns`` with input ``z`` (None: a prediction) over
        ``dt_ns`` (default: time_step), published at its end unless ``publish`` is False.
        ``continued``: a later part of one measurement's hold (counted, checked and recorded
        once, on its first part)."""
        if continued:
            return self._continue_hold(z, stamp_ns, dt_ns, publish)
        held = self._checkpoint(stamp_ns, z)  # None unless provisional or after a provisional step
        u, final = self._control_of_step(stamp_ns)
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
            why = self._reset_requested or self._inconsistency(z)
            if why:
                self._reinitialise(z, stamp_ns, *why)
            elif self._high_nis == 0:
                self.recovery.trusted(stamp_ns)
        started = time.perf_counter()
        dt = self.settings.time_step if dt_ns is None or dt_ns == self._dt_ns else dt_ns / NS
        self._filter_step(z, u, dt, stamp_ns)
        self.recovery.record(stamp_ns, z, u)
        if held is not None:
            self._hold(held, u, final)
        self.step_seconds.append(time.perf_counter() - started)
        if len(self.step_seconds) > 2000:
            del self.step_seconds[:1000]
        self.time_ns = stamp_ns + (self._dt_ns if dt_ns is None else dt_ns)
        self._forget_controls(stamp_ns)
        if publish:
            (self._republish if self._replaying else self._publish)(self.time_ns)

    def _inconsistency(self, z: np.ndarray) -> tuple[str, str] | None:
        """NIS over nis_threshold for nis_window steps in a row means the filter lost the
        truth: (why, reason) of the re-initialisation it needs, else None."""
        nis = float(self.estimator.innovation_nis(z, self.measurement_covariance)[0])
        s = self.settings
        self._high_nis = self._high_nis + 1 if nis > s.nis_threshold else 0
        if self._high_nis >= s.nis_window > 0:
            return (f'normalised innovation squared {nis:.1f} > {s.nis_threshold} for {self._high_nis} steps',
                    'inconsistent_innovation')
        return None

    def _reinitialise(self, z: np.ndarray | None, stamp_ns: int, why: str, reason: str) -> None:
        """Restart the filter at ``stamp_ns`` from the data (never the parameters' initial
        state mid-flight); a state the filter cannot represent leaves it as it is, counted."""
        self._reset_requested = None
        self._high_nis = 0
        x, covariance, source = self.recovery.restart_state(stamp_ns, z)
        est = self.estimator
        try:
            est.reset(x, covariance if est.has_covariance else None)
        except ValueError as error:
            self.events['reinitialisations_failed'] += 1
            self._log('error', f'cannot re-initialise from {source} ({error}): the filter goes on')
            return
        self.events[f'reinitialisations.{reason}'] += 1
        self.events[f'restarts_from.{source}'] += 1
        self.recovery.note_reset(stamp_ns)
        self._log('error', f'filter re-initialised at t = {stamp_ns / NS:.3f} s from {source.replace("_", " ")}: {why}')



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
