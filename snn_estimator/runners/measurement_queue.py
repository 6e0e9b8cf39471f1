"""The measurements a :class:`~snn_estimator.runners.filter_runner.FilterRunner` takes: gated,
held until their step, and counted. No ROS.

A measurement is refused with a reason (counted in :attr:`MeasurementQueue.rejected`, logged):

* ``duplicate``: its stamp is queued already, or is the last one a step used;
* ``too_old``: more than max_input_age behind the newest measurement (a straggler);
* ``stale``: before the estimate time (the filter is past it);
* ``misaligned``: (measurement_timing grid) not on the estimate time plus steps of time_step;
* ``future``: further ahead of the clock than max_input_age plus two steps
  (:func:`snn_estimator.runners.gates.seconds_ahead`); queued, it would make every real
  measurement ``too_old``.

Without a clock, a stamp far before the estimate time means the time base restarted
(:meth:`MeasurementQueue.time_base_restarted`: the runner starts over). The queue also notes
whether the stamps share the clock's time base and when the last measurement arrived (the
dropout watchdog needs both), and, with measurement_timing any, the measurement the filter holds
from the estimate time on. Its counts add up: received = rejected + used + dropped + pending +
repeated (a sample the sensor could not measure is counted apart, as ``not_measured``).
"""

from __future__ import annotations

import time
from collections import Counter
from typing import Callable, Iterable, Mapping

import numpy as np

from .gates import NS, seconds_ahead, seconds_to_ns


class MeasurementQueue:
    """Gates measurements, holds them by stamp until their step and counts what became of each.

    ``estimate_ns`` in the methods is the runner's estimate time (None: the filter has not
    started); ``settings`` its :class:`~snn_estimator.runners.filter_runner.RunnerSettings`.
    """

    def __init__(self, time_step: float, log: Callable[[str, str], None] | None = None,
                 wall_clock: Callable[[], float] = time.monotonic):
        self._dt_ns = seconds_to_ns(time_step)
        self._log = log or (lambda level, message: None)
        self._wall = wall_clock
        self._pending: dict[int, np.ndarray | None] = {}  # None: the sensor measured nothing
        self._from_history: set[int] = set()  # queued stamps that came with the start-up history
        self._newest_ns: int | None = None
        self._last_arrival = wall_clock()
        self._last_used_ns: int | None = None
        self._last_unmeasured_ns: int | None = None
        self._clock_agrees: bool | None = None
        self._held_z: np.ndarray | None = None
        #: measurements refused, by reason
        self.rejected = Counter()
        #: stamps_off_the_clock, not_measured_rejected.<reason>, history_measurements
        self.events = Counter()
        self.received = 0
        self.used = 0
        self.dropped = 0
        self.repeated = 0
        #: samples the sensor said it could not measure (no_measurement), outside the counts above
        self.not_measured = 0
        #: steps taken without a measurement (predicted over)
        self.dropout_steps = 0

    # ---------------------------------------------------------------- what it holds
    @property
    def pending_count(self) -> int:
        """Inputs queued (measurements and samples the sensor could not measure)."""
        return len(self._pending)

    @property
    def measured_pending(self) -> int:
        """Measurements queued (not counting samples the sensor could not measure)."""
        return sum(1 for z in self._pending.values() if z is not None)

    def first_stamp(self) -> int:
        return min(self._pending)

    def measured_stamps(self) -> list[int]:
        """Stamps of the queued measurements (the samples measured), in queue order."""
        return [t for t, z in self._pending.items() if z is not None]

    def z_at(self, stamp_ns: int) -> np.ndarray | None:
        return self._pending[stamp_ns]

    def pop(self, stamp_ns: int) -> np.ndarray | None:
        """Take the input stamped ``stamp_ns`` out of the queue (for its step)."""
        return self._pending.pop(stamp_ns)

    @property
    def newest_ns(self) -> int | None:
        return self._newest_ns

    @property
    def clock_agrees(self) -> bool | None:
        """Whether the stamps share the clock's time base (None: not known yet)."""
        return self._clock_agrees

    def has(self, stamp_ns: int, start_ns: int | None) -> bool:
        """True when a measurement stamped ``stamp_ns`` is queued or was used since the start at
        ``start_ns`` (the same sample again: a resend, not new information)."""
        if stamp_ns in self._pending:
            return True
        last = max((t for t in (self._last_used_ns, self._last_unmeasured_ns) if t is not None), default=None)
        return last is not None and start_ns is not None and start_ns <= stamp_ns <= last

    def quiet_for(self, seconds: float) -> bool:
        """True when no measurement arrived for ``seconds`` wall seconds."""
        return self._wall() - self._last_arrival >= seconds

    # ---------------------------------------------------------------- gate
    def time_base_restarted(self, stamp_ns: int, now_ns: int, estimate_ns: int | None, threshold: float) -> bool:
        """Without a clock (``now_ns`` <= 0), a stamp more than ``threshold`` s before the estimate
        time means the time base restarted (a bag played in a loop)."""
        return estimate_ns is not None and now_ns <= 0 and stamp_ns < estimate_ns - seconds_to_ns(threshold)

    def rejection(self, stamp_ns: int, now_ns: int, estimate_ns: int | None, settings) -> str | None:
        """Why a measurement stamped ``stamp_ns`` cannot be used (logged; see the module
        docstring), or None. ``now_ns``: the clock (0: none)."""
        where = f'measurement at {stamp_ns / NS:.3f} s'
        started = estimate_ns is not None
        if stamp_ns in self._pending or stamp_ns == self._last_used_ns:
            return self._say('duplicate', f'second {where}')
        if (started and self._newest_ns is not None  # None: a warm start without measurement history
                and stamp_ns < self._newest_ns - seconds_to_ns(settings.max_input_age)):
            return self._say('too_old', f'{where} is more than {settings.max_input_age} s older than the '
                             f'newest measurement ({self._newest_ns / NS:.3f} s)')
        if started and stamp_ns < estimate_ns:
            return self._say('stale', f'{where} is older than the estimate at {estimate_ns / NS:.3f} s')
        if started and settings.measurement_timing == 'grid' and (stamp_ns - estimate_ns) % self._dt_ns:
            return self._say('misaligned', f'{where} does not fall on the estimate time '
                             f'{estimate_ns / NS:.3f} s plus steps of {settings.time_step} s (time_step? a '
                             'sensor on its own clock needs measurement_timing: any)')
        ahead = seconds_ahead(stamp_ns, now_ns, settings.max_input_age, settings.time_step)
        if ahead:
            return self._say('future', f'{where} is {ahead:.3f} s ahead of the clock')
        return None

    def _say(self, reason: str, detail: str) -> str:
        self._log('warning', f'rejected {detail}')
        return reason

    def offer(self, stamp_ns: int, z: np.ndarray, now_ns: int, estimate_ns: int | None, settings) -> str | None:
        """A measurement: counted, gated, and queued unless refused; None if queued, else the reason."""
        self.received += 1
        reason = self.rejection(stamp_ns, now_ns, estimate_ns, settings)
        if reason is not None:
            self.rejected[reason] += 1
            return reason
        self._check_clock(stamp_ns, now_ns, settings)
        self._put(stamp_ns, np.asarray(z, dtype=float))
        return None

    def offer_unmeasured(self, stamp_ns: int, now_ns: int, estimate_ns: int | None, settings) -> str | None:
        """A sample the sensor could not measure: counted (as not_measured) and gated like a
        measurement; None if it may be queued (:meth:`put_unmeasured`), else the reason."""
        self.not_measured += 1
        reason = self.rejection(stamp_ns, now_ns, estimate_ns, settings)
        if reason is not None:
            self.events[f'not_measured_rejected.{reason}'] += 1
        return reason

    def put_unmeasured(self, stamp_ns: int) -> None:
        """Queue the step of a sample the sensor could not measure (predicted over)."""
        self._put(stamp_ns, None)
        self._last_unmeasured_ns = stamp_ns

    def unreadable(self, reason: str) -> None:
        """Count a measurement message that could not be read (refused by the wrapper)."""
        self.received += 1
        self.rejected[reason] += 1

    def count_repeat(self) -> None:
        """Count a measurement that came again and was answered again (not stepped)."""
        self.received += 1
        self.repeated += 1

    def _put(self, stamp_ns: int, z: np.ndarray | None) -> None:
        self._newest_ns = stamp_ns if self._newest_ns is None else max(self._newest_ns, stamp_ns)
        self._last_arrival = self._wall()
        self._pending[stamp_ns] = z

    def _check_clock(self, stamp_ns: int, now_ns: int, settings) -> None:
        """Note whether measurement stamps and the clock share a time base (within
        max_input_age plus two steps); say so once when they do not."""
        if now_ns <= 0:
            return  # no clock yet: nothing to compare with
        lead = seconds_to_ns(settings.max_input_age + 2 * settings.time_step)
        agrees = abs(now_ns - stamp_ns) <= lead
        if not agrees and self._clock_agrees is not False:
            self.events['stamps_off_the_clock'] += 1
            # far apart: another time base (wall against simulated); near: a process lagging
            cause = ('is use_sim_time set as the sensor stamps?' if abs(now_ns - stamp_ns) > 1000 * NS
                     else 'the clock or the measurements arrive late: a starved CPU or a delayed /clock?')
            self._log('warning', f'measurement stamped {stamp_ns / NS:.3f} s with the clock at '
                      f'{now_ns / NS:.3f} s: not predicting over sensor dropouts ({cause})')
        self._clock_agrees = agrees

    # ---------------------------------------------------------------- start-up and restarts
    def add_history(self, measurements: Mapping[int, np.ndarray]) -> None:
        """Queue what the measurement topic held when the filter joined (not gated: the
        filter has not started)."""
        for stamp_ns, z in sorted(measurements.items()):
            if stamp_ns not in self._pending:
                self._pending[stamp_ns] = np.asarray(z, dtype=float)
                self._from_history.add(stamp_ns)
            self._newest_ns = stamp_ns if self._newest_ns is None else max(self._newest_ns, stamp_ns)
        self.events['history_measurements'] += len(self._from_history)

    def begin(self) -> None:
        """The filter started: forget the history stamps no longer queued."""
        self._from_history = {t for t in self._from_history if t in self._pending}

    def take_fitted(self, stamps: Iterable[int]) -> None:
        """The queued measurements at ``stamps`` started the filter (a least-squares fit): used."""
        for stamp_ns in stamps:
            del self._pending[stamp_ns]
            self.used += 1

    def drop_before(self, stamp_ns: int, why: str) -> None:
        self.drop({t for t in self._pending if t < stamp_ns}, why)

    def drop(self, stamps: Iterable[int], why: str) -> None:
        """Discard queued measurements: counted as dropped (not as rejected), except those of
        the start-up history that the start did not need."""
        for stamp_ns in sorted(stamps):
            del self._pending[stamp_ns]
            if stamp_ns in self._from_history:
                self._from_history.discard(stamp_ns)
                continue
            self.dropped += 1
            self._log('warning', f'dropped the measurement at {stamp_ns / NS:.3f} s: {why}')

    def restart(self) -> None:
        """A new time base: drop everything queued and forget the stamps seen."""
        self._newest_ns = self._last_used_ns = self._last_unmeasured_ns = None
        self._held_z = None
        self.drop(set(self._pending), 'the filter restarted')

    # ---------------------------------------------------------------- steps
    def stepped(self, stamp_ns: int, z: np.ndarray | None) -> None:
        """A step from ``stamp_ns`` took ``z`` (None: predicted over)."""
        if z is None:
            self.dropout_steps += 1
        else:
            self.used += 1
            self._last_used_ns = stamp_ns

    def hold(self, z: np.ndarray | None) -> None:
        """(measurement_timing any) ``z`` is the filter's input from the estimate time on."""
        self._held_z = z

    def take_held(self) -> np.ndarray | None:
        """(measurement_timing any) The held measurement, released (None: none held)."""
        held, self._held_z = self._held_z, None
        return held

    def step_state(self) -> tuple:
        """What a step changes here, for :meth:`restore_step_state` (a step taken again)."""
        return self.used, self._last_used_ns, self.dropout_steps

    def restore_step_state(self, state: tuple) -> None:
        self.used, self._last_used_ns, self.dropout_steps = state
