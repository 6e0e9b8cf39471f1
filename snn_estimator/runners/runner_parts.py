"""The gating, start-up and reporting parts of :class:`snn_estimator.runners.filter_runner.FilterRunner`.

Mixins of that one class, split from it for size: they share its state (the queue, the
counters, the estimator) and are not used on their own.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from snn_estimator.catalog import START_MODES
from snn_estimator.filters.estimators import CovarianceLost

from .gates import NS, seconds_ahead, seconds_to_ns
from .initialization import least_squares_start
from .plant_runner import control_in_force

#: How measurement stamps relate to the filter's steps (docs/decisions.md, 31):
#: grid: z_k at t_k steps the filter to t_k + time_step, published at once (a one-step
#: prediction; stamps off the grid are rejected as misaligned);
#: any: z_j is the filter's input from t_j until the next measurement's stamp t_{j+1} (a zero-order
#: hold, as a continuous-time filter or a spiking network sees a sampled sensor): the arrival of z_{j+1}
#: steps the filter over [t_j, t_{j+1}) with dt = t_{j+1} - t_j and publishes x_hat(t_{j+1}).
#: On grid stamps both publish the same estimates at the same stamps. An interval of
#: HOLD_LIMIT steps or more is a dropout: the measurement is held one step, the rest predicted.
HOLD_LIMIT = 2
#: Controls kept for pairing and replay.
CONTROL_MEMORY = 2000


@dataclass
class History:
    """What the topics held when the filter joined: stamp (ns) -> value."""

    measurements: Mapping[int, np.ndarray]
    controls: Mapping[int, np.ndarray]
    #: Estimates an earlier estimator published: stamp -> (x, covariance or None).
    estimates: Mapping[int, tuple]


class Gating:
    """Which measurements the runner takes, and whether their stamps share the clock's time base."""

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
        if (self.started and self._newest_ns is not None  # None: a warm start without measurement history
                and stamp_ns < self._newest_ns - seconds_to_ns(s.max_input_age)):
            return self._say('too_old', f'{where} is more than {s.max_input_age} s older than the '
                             f'newest measurement ({self._newest_ns / NS:.3f} s)')
        if self.started and stamp_ns < self.time_ns:
            return self._say('stale', f'{where} is older than the estimate at {self.time_ns / NS:.3f} s')
        if self.started and s.measurement_timing == 'grid' and (stamp_ns - self.time_ns) % self._dt_ns:
            return self._say('misaligned', f'{where} does not fall on the estimate time '
                             f'{self.time_ns / NS:.3f} s plus steps of {s.time_step} s (time_step? a '
                             'sensor on its own clock needs measurement_timing: any)')
        ahead = self.seconds_ahead(stamp_ns, now_ns)
        if ahead:  # queued, it would make every real measurement 'too_old'
            return self._say('future', f'{where} is {ahead:.3f} s ahead of the clock')
        return None

    def seconds_ahead(self, stamp_ns: int, now_ns: int) -> float:
        """See :func:`snn_estimator.runners.gates.seconds_ahead`."""
        return seconds_ahead(stamp_ns, now_ns, self.settings.max_input_age, self.settings.time_step)

    def _check_time_base(self, stamp_ns: int, now_ns: int) -> None:
        """Note whether measurement stamps and the clock share a time base (within
        max_input_age plus two steps); say so once when they do not."""
        if now_ns <= 0:
            return  # no clock yet: nothing to compare with
        lead = seconds_to_ns(self.settings.max_input_age + 2 * self.settings.time_step)
        agrees = abs(now_ns - stamp_ns) <= lead
        if not agrees and self._clock_agrees is not False:
            self.events['stamps_off_the_clock'] += 1
            # far apart: another time base (wall against simulated); near: a process lagging
            cause = ('is use_sim_time set as the sensor stamps?' if abs(now_ns - stamp_ns) > 1000 * NS
                     else 'the clock or the measurements arrive late: a starved CPU or a delayed /clock?')
            self._log('warning', f'measurement stamped {stamp_ns / NS:.3f} s with the clock at '
                      f'{now_ns / NS:.3f} s: not predicting over sensor dropouts ({cause})')
        self._clock_agrees = agrees


class StartUp:
    """How the runner starts: from an earlier estimator's estimate, a least-squares fit of the
    measurement history, or the parameters at the first measurement."""

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
        measured = [t for t, z in self._pending.items() if z is not None]  # None: the sensor measured nothing
        if not measured or self.estimator.relinearises:  # a fit of z = C x only
            return False
        newest = max(measured)
        stamps = sorted(t for t in measured if t >= newest - window_ns)
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


class Reporting:
    """The runner's counters for diagnostics."""

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
            'not_measured': self.not_measured,
            'measurements_pending': sum(1 for z in self._pending.values() if z is not None),
            'spikes_total': est.total_spikes,
            'spike_fraction': (est.total_spikes / (steps * est.neuron_count)
                               if steps and est.neuron_count else 0.0),
            'silenced_neurons': len(est.silenced),
            'step_time_us_last': float(times[-1]) if times.size else 0.0,
            'step_time_us_median': float(np.median(times)) if times.size else 0.0,
            'controls_missing': self.controls_missing, 'dropout_steps': self.dropout_steps,
            'applied_received': self.applied_received, 'provisional_held': self.provisional_held,
            **{key: self.events[key] for key in ('provisional_steps', 'provisional_corrected',
                                                 'provisional_unconfirmed')},
        }
        values['measurements_rejected'] = sum(self.rejected.values())
        values.update({f'measurements_rejected.{k}': v for k, v in sorted(self.rejected.items())})
        values['controls_rejected'] = sum(self.control_rejected.values())
        values.update({f'controls_rejected.{k}': v for k, v in sorted(self.control_rejected.items())})
        values.update(sorted(self.events.items()))
        values['reinitialisations'] = sum(v for k, v in self.events.items() if k.startswith('reinitialisations.'))
        values['reset_storms'] = self.recovery.storms
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
        reinit = sum(v for k, v in self.events.items() if k.startswith('reinitialisations.'))
        if reinit:
            problems.append(f'{reinit} re-initialisations')
        if self.recovery.storms:
            problems.append(f'{self.recovery.storms} reset storms')
        return problems


class HeldMeasurements:
    """measurement_timing any (docs/decisions.md, 31): each measurement is the filter's input
    from its stamp until the next one's; the runner steps over that interval when the next
    one comes."""

    def _advance_to(self, stamp_ns: int) -> None:
        """(measurement_timing any) Step from the estimate time to ``stamp_ns`` with the held
        measurement as input, in equal steps of at most time_step (each a valid step: the one
        checked at configure, or shorter). An interval of HOLD_LIMIT time steps or more is a
        dropout: the measurement is held for one time step and the rest predicted."""
        dt_ns = self._dt_ns
        interval = stamp_ns - self.time_ns
        held, self._held_z = self._held_z, None
        span = interval if interval < HOLD_LIMIT * dt_ns else dt_ns
        self._steps_over(held, span)
        if self.started and self.time_ns < stamp_ns:
            self._steps_over(None, stamp_ns - self.time_ns)

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
        end = self.time_ns + span_ns
        for k in range(count):
            if not self.started:
                return
            last = k == count - 1
            # a held measurement is answered once, at the end of its interval; predictions
            # are published every step (as the grid runner's)
            self._step(z, self.time_ns, end - self.time_ns if last else span_ns // count,
                       continued=k > 0 and z is not None, publish=last or z is None)

    def _filter_step(self, z: np.ndarray | None, u: np.ndarray, dt: float, stamp_ns: int) -> None:
        """A filter step; a non-finite state or an indefinite P re-initialises it (never published)."""
        try:
            self.estimator.step(z, u, dt)
        except CovarianceLost as error:
            self._reinitialise(z, stamp_ns, str(error), 'covariance_lost')
        except FloatingPointError as error:
            self._reinitialise(z, stamp_ns, str(error), 'non_finite_state')

    def _continue_hold(self, z: np.ndarray, stamp_ns: int, dt_ns: int, publish: bool) -> None:
        """A later part of a held measurement's interval (measurement_timing any): the same z,
        the control in force, no new measurement counted."""
        u = self._control_for(stamp_ns)
        if u is None:
            u = self._in_force(stamp_ns)
        self._filter_step(z, u, dt_ns / NS, stamp_ns)
        self.time_ns = stamp_ns + dt_ns
        if publish:
            self._publish(self.time_ns)


class Controls:
    """The control of each step: the controller's u_k, the one the plant reports it applied
    (applied_control) once it reports them, or the one in force by the plant's rule."""

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

    def applied(self, stamp_ns: int, u: np.ndarray) -> str | None:
        """Offer the control the plant reports it stepped with from ``stamp_ns``; None if
        accepted, else the rejection reason. From the first one on, a step predicts with the
        plant's report: taken provisionally with the controller's u_k until it comes, corrected
        if it differs (snn_estimator.runners.provisional), or, without provisional steps, waiting
        for it (as long as it waits for a control)."""
        if self.start_ns is not None and stamp_ns < self.start_ns:
            self.control_rejected['applied_before_init'] += 1
            return 'applied_before_init'
        self.applied_received += 1
        u = self._applied[stamp_ns] = np.asarray(u, dtype=float)
        if len(self._applied) > CONTROL_MEMORY:
            del self._applied[min(self._applied)]
        self._plant_reports = True
        if self._provisional:
            self._report(stamp_ns, u)
        if self.started:
            self._process()
        return None

    def _control_for(self, stamp_ns: int) -> np.ndarray | None:
        """The control of the step from ``stamp_ns`` that settles it: the plant's report of
        what it applied once a plant reports them, else the controller's; None: not here yet."""
        return self._stamped(self._applied if self._plant_reports else self._controls, stamp_ns)

    def _stamped(self, controls: dict, stamp_ns: int) -> np.ndarray | None:
        u = controls.get(stamp_ns)
        if u is not None:
            return u
        for control_ns, value in controls.items():
            if abs(control_ns - stamp_ns) * 2 < self._dt_ns:
                return value
        return None

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
