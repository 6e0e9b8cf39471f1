"""Driving the truth from a message stream: start handshake, lockstep and realtime stepping,
resend and timeouts, no ROS.

The plant owns simulated time. :class:`PlantRunner` decides when it steps and with which
control; the node only converts messages, runs the timers and publishes:

* start (:class:`StartGate`): the scenario (x0, the clock) starts once the loop is there and
  ``start_delay`` wall seconds have passed; what is missing is said every ``notice_period`` s;
* lockstep: publish x_k at t_k, wait for the control stamped t_k, step, repeat. A state whose
  control does not come within ``resend_period`` wall seconds is sent again (a sample lost on
  a best-effort link); after ``control_timeout`` the step is taken with the control in force
  (counted as a timeout). Controls that come early are kept for their step;
* realtime (:meth:`PlantRunner.tick` on a wall-clock timer): step with the control stamped for
  this step, or, when it is late, the control in force (counted as late);
* the control in force at t (:func:`control_in_force`, the estimator uses the same rule): the
  newest control stamped at or before t if it is younger than ``control_validity``, else zero
  thrust (a dead controller's last command does not fly the chaser away).

Stamps are integer nanoseconds; ``publish(stamp_ns, resend)`` is called for every sample (the
plant then holds x at ``stamp_ns``); ``applied(stamp_ns, u)`` for every step, with the control
it stepped with from ``stamp_ns`` (before the truth of the step's end: the estimator predicts
with it, so estimate and truth agree on what was applied even when a control came after the
realtime plant's tick); ``finished()`` after the last step: after ``duration``, after the
step that brings the truth where ``stop(x)`` says so (the approach: at the port), or after
the step from the stamp given to :meth:`PlantRunner.end_after` (an end announced by a peer).
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .gates import NS, seconds_to_ns

#: Steps at the start during which the lockstep plant waits for controls without a timeout.
STARTUP_STEPS = 10


@dataclass(frozen=True)
class PlantSettings:
    """How the plant steps. Times in seconds (simulated unless said wall)."""

    time_step: float
    mode: str = 'lockstep'
    #: Simulated time to run (0: until stopped).
    duration: float = 0.0
    start_time: float = 0.0
    #: lockstep: wall s to wait for a step's control before stepping with the control in force.
    control_timeout: float = 1.0
    #: lockstep: wall s without a step's control after which the state is sent again.
    resend_period: float = 0.25
    #: Simulated s a control stays in force after its stamp (then zero thrust).
    control_validity: float = 0.5
    #: Wall s between two notices of what the plant waits for.
    notice_period: float = 5.0

    def __post_init__(self):
        if self.mode not in ('lockstep', 'realtime'):
            raise ValueError(f"mode must be lockstep or realtime; got {self.mode!r}")
        if not self.time_step > 0:
            raise ValueError(f'time_step must be > 0; got {self.time_step}')
        if not self.control_validity > 0:
            raise ValueError(f'control_validity must be > 0 s; got {self.control_validity}')


def control_in_force(controls: dict, t_ns: int, validity_ns: int, n_input: int) -> tuple[np.ndarray, int | None]:
    """The control applied over the step from ``t_ns`` when none is stamped for it: the newest
    of ``controls`` (stamp ns -> u) stamped at or before ``t_ns`` while younger than
    ``validity_ns``, else zero thrust. Returns (u, its stamp or None for zero)."""
    older = [s for s in controls if s <= t_ns]
    if older:
        newest = max(older)
        if t_ns - newest < validity_ns:
            return controls[newest], newest
    return np.zeros(n_input), None


class StartGate:
    """When the scenario may start: once nothing is missing for ``start_delay`` wall seconds;
    says what is missing every ``notice_period`` s."""

    def __init__(self, start_delay: float, notice_period: float, log: Callable[[str, str], None],
                 wall_clock: Callable[[], float] = time.monotonic):
        self.start_delay, self.notice_period = start_delay, notice_period
        self._log, self._wall = log, wall_clock
        self._complete_since = None
        self._notice_at = wall_clock()

    def check(self, missing: list[str]) -> bool:
        """True when the scenario may start, given what the loop still lacks (empty: nothing)."""
        now = self._wall()
        if missing:
            self._complete_since = None
            if now - self._notice_at > self.notice_period:
                self._log('info', f"waiting for {', '.join(missing)} before the first step")
                self._notice_at = now
            return False
        self._complete_since = self._complete_since if self._complete_since is not None else now
        return now - self._complete_since >= self.start_delay


class PlantRunner:
    """Steps ``plant`` (a :class:`snn_estimator.plant.truth.Plant` or a Basilisk plant with its
    interface) from stamped controls (see the module docstring)."""

    def __init__(self, plant, settings: PlantSettings, publish: Callable[[int, bool], None],
                 finished: Callable[[], None] = lambda: None, log: Callable[[str, str], None] | None = None,
                 wall_clock: Callable[[], float] = time.monotonic,
                 applied: Callable[[int, np.ndarray], None] = lambda stamp_ns, u: None,
                 stop: Callable[[np.ndarray], bool] | None = None):
        self.plant, self.settings = plant, settings
        self._stop = stop
        #: Why the run ended: 'duration', 'stop' (the truth met ``stop``), 'requested' (end_after); None: running.
        self.ended_by: str | None = None
        self._end_ns: int | None = None
        self._publish, self._on_finished, self._applied = publish, finished, applied
        self._log = log or (lambda level, message: None)
        self._wall = wall_clock
        self._dt_ns = seconds_to_ns(settings.time_step)
        self._validity_ns = (seconds_to_ns(settings.control_validity) if np.isfinite(settings.control_validity)
                             else 2 ** 62)
        self.t_ns = self.start_ns = seconds_to_ns(settings.start_time)
        self.total_steps = (int(round(settings.duration / settings.time_step))
                            if settings.duration > 0 else None)
        self.lockstep = settings.mode == 'lockstep'
        self.paused = False
        self.started = False
        self.step = 0
        self._controls: dict[int, np.ndarray] = {}  # received, by stamp (early ones and the newest)
        self._held = None  # lockstep: the control of a step that came while paused
        self._expired = False  # stepping with zero thrust: the newest control expired
        self._expired_before = 0  # zero-thrust steps before the current outage
        self._sent_at = 0.0
        self._waiting_since = None
        self.started_wall = self.finished_wall = None
        self.finished_unix = 0.0
        self.counts = Counter()  # timeouts, late controls, controls received, truth published/resent

    # ---------------------------------------------------------------- state
    @property
    def finished(self) -> bool:
        """The last step is done: no more steps, whatever the mode."""
        return self.finished_wall is not None

    def begin(self) -> None:
        """Start the scenario: publish x0 at the start time."""
        if not self.started:
            self.started = True
            self._send()

    # ---------------------------------------------------------------- inputs
    def control(self, stamp_ns: int, u: np.ndarray) -> tuple[str, str] | None:
        """Offer u stamped ``stamp_ns``; None if taken, else (reason, detail) of its rejection."""
        if stamp_ns < self.start_ns:
            return 'before_init', (f'control stamped {stamp_ns / NS:.3f} s, before the start at '
                                   f'{self.start_ns / NS:.3f} s')
        self.counts['controls_received'] += 1
        if self.finished:
            return None
        u = np.asarray(u, dtype=float)
        if not self.lockstep:  # kept by stamp: the step from t_k applies u_k, as in lockstep
            self._keep(stamp_ns, u)
            return None
        if abs(stamp_ns - self.t_ns) * 2 < self._dt_ns and self._waiting_since is not None:
            self._keep(stamp_ns, u)
            if self.paused:
                self._held = u  # applied on resume
            else:
                self._advance(u)
        elif stamp_ns < self.t_ns:
            return 'stale', f'control stamped {stamp_ns / NS:.3f} s, plant at {self.t_ns / NS:.3f} s'
        else:  # ahead of the plant (it paused or held a control): use it at its step
            self._keep(stamp_ns, u)
        return None

    def _keep(self, stamp_ns: int, u: np.ndarray) -> None:
        self._controls[stamp_ns] = u
        self._prune()
        if self._expired:
            self._expired = False
            if self.counts['expired_control_steps'] - self._expired_before >= 10:  # not every late control
                self._log('info', f'controls are back at t = {stamp_ns / NS:.3f} s after '
                          f"{self.counts['expired_control_steps'] - self._expired_before} zero-thrust steps")
            self._expired_before = self.counts['expired_control_steps']

    def _prune(self) -> None:
        """Forget controls before the plant's time, except the newest of them (it may still
        be in force)."""
        for t in sorted(t for t in self._controls if t <= self.t_ns)[:-1]:
            del self._controls[t]

    def end_after(self, stamp_ns: int) -> None:
        """End the run after the step from ``stamp_ns`` (at once if the plant has taken it)."""
        if self.finished:
            return
        self._end_ns = stamp_ns if self._end_ns is None else min(self._end_ns, stamp_ns)
        if self.started and self.t_ns > self._end_ns:
            self._finish('requested')

    def set_paused(self, paused: bool) -> None:
        """Hold simulated time (lockstep: a control that came while paused is applied on resume)."""
        self.paused = bool(paused)
        self._log('info', f"{'paused' if paused else 'resumed'} at t = {self.t_ns / NS:.3f} s")
        if not paused and self._held is not None and self.lockstep:
            held, self._held = self._held, None
            self._advance(held)

    # ---------------------------------------------------------------- timers
    def watchdog(self) -> None:
        """lockstep, every few tens of wall ms: resend, start-up notices, control timeouts."""
        if self._waiting_since is None or self.finished or self.paused:
            if self.paused and self._waiting_since is not None:
                self._waiting_since = self._wall()
            return
        s = self.settings
        now = self._wall()
        waited = now - self._waiting_since
        if now - self._sent_at > s.resend_period:
            # a sample lost on a best-effort link would stall the lockstep loop: send it again;
            # every node answers a repeated input with its answer to it (docs/decisions.md, 21)
            self.counts['truth_resent'] += 1
            self._send(resend=True)
        if self.step < STARTUP_STEPS:  # processes still warming up: no timeouts yet
            if waited > s.notice_period:
                self._log('info', f"waiting for the control of t = {self.t_ns / NS:.1f} s on 'control' "
                          '(are the other nodes running?)')
                self._waiting_since = self._wall()
            return
        if waited > s.control_timeout:
            self.counts['control_timeouts'] += 1
            self._log('warning', f'no control for t = {self.t_ns / NS:.3f} s within {s.control_timeout} s: '
                      f"stepping with the control in force ({self.counts['control_timeouts']} timeouts so far)")
            self._advance(self._in_force())

    def tick(self) -> None:
        """realtime, every time_step / real_time_factor wall s: step with the control stamped
        for this step (the one the estimator pairs with z_k), or the one in force if it is late."""
        if not self.started or self.finished or self.paused:
            return
        due = [t for t in self._controls if abs(t - self.t_ns) * 2 < self._dt_ns]
        if due:
            u = self._controls[due[0]]
        else:
            u = self._in_force()
            self.counts['late_controls'] += self.step >= 1  # the first step may come before any control
        self._advance(u)

    def _in_force(self) -> np.ndarray:
        """The control in force at the plant's time; zero thrust once the newest one expired
        (counted per step, logged once per outage)."""
        u, stamp = control_in_force(self._controls, self.t_ns, self._validity_ns, self.plant.model.n_input)
        if stamp is None:
            self.counts['expired_control_steps'] += 1
            newest = max(self._controls, default=None)
            if not self._expired and newest is not None:  # before the first control: nothing to say
                self._log('warning', f'the control of t = {newest / NS:.3f} s expired at t = '
                          f'{self.t_ns / NS:.3f} s (control_validity {self.settings.control_validity} s): '
                          'zero thrust until controls come again')
            self._expired = newest is not None
        return u

    # ---------------------------------------------------------------- stepping
    def _advance(self, u: np.ndarray) -> None:
        """Step with ``u``; lockstep: go on at once with controls that came early for later steps."""
        while True:
            if self.started_wall is None:
                self.started_wall = self._wall()
            saturated = int(self.plant.saturated_steps[0])
            self.plant.step(u, self.settings.time_step)
            if self.plant.saturated_steps[0] > saturated:
                self._log('warning', f'thrust limit: commanded {np.array2string(u, precision=4)} m/s^2, '
                          f'applied {np.array2string(self.plant.applied[0], precision=4)} m/s^2')
            self._applied(self.t_ns, u)
            self.step += 1
            self.t_ns += self._dt_ns
            self._prune()
            self._send()
            ended = ('duration' if self.total_steps is not None and self.step >= self.total_steps else
                     'stop' if self._stop is not None and self._stop(self.plant.x[0]) else
                     'requested' if self._end_ns is not None and self.t_ns > self._end_ns else None)
            if ended is not None:
                self._finish(ended)
                return
            early = [t for t in self._controls if abs(t - self.t_ns) * 2 < self._dt_ns]
            if not (early and self.lockstep and not self.paused):
                return
            u = self._controls[early[0]]

    def _send(self, resend: bool = False) -> None:
        self._publish(self.t_ns, resend)
        self.counts['truth_published'] += 1
        self._sent_at = self._wall()
        if not resend:
            self._waiting_since = self._sent_at

    def _finish(self, why: str) -> None:
        self.ended_by = why
        self.finished_wall = self._wall()
        self.finished_unix = time.time()  # when stepping ended, for tools outside the process
        self._waiting_since = None
        self._on_finished()

    # ---------------------------------------------------------------- reporting
    def values(self) -> dict:
        end = self.finished_wall or self._wall()
        wall = (end - self.started_wall) if self.started_wall else 0.0
        sim = self.step * self.settings.time_step
        c = self.counts
        return {
            'steps': self.step, 'sim_time': sim, 'wall_time': wall,
            'real_time_factor': sim / wall if wall > 0 else 0.0,
            'control_timeouts': c['control_timeouts'], 'controls_received': c['controls_received'],
            'truth_published': c['truth_published'], 'truth_resent': c['truth_resent'],
            'late_controls': c['late_controls'], 'expired_control_steps': c['expired_control_steps'],
            'saturated_steps': int(self.plant.saturated_steps[0]),
            'range': float(np.linalg.norm(self.plant.x[0, :3])), 'done': self.finished,
            'ended_by': self.ended_by or '',
            'finished_unix_time': self.finished_unix,
        }

    def problems(self) -> list[str]:
        timeouts, expired = self.counts['control_timeouts'], self.counts['expired_control_steps']
        problems = [f'{timeouts} control timeouts'] if timeouts else []
        if expired:
            problems.append(f'{expired} steps with zero thrust (control expired)')
        return problems
