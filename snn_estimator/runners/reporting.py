"""What a :class:`~snn_estimator.runners.filter_runner.FilterRunner` reports for diagnostics:
its parts' public counters, the estimator's, and the wall time of its steps. No ROS."""

from __future__ import annotations

from collections import Counter

import numpy as np

#: Step times kept: beyond STEP_TIMES_KEPT the oldest half is dropped; the report uses the newest 1000.
STEP_TIMES_KEPT = 2000


class RunnerReport:
    """Reads the runner's parts (never writes them) and times the filter's steps."""

    def __init__(self, estimator, measurement_queue, control_book, provisional_log, recovery, events: Counter):
        self._estimator = estimator
        self._measurements = measurement_queue
        self._controls = control_book
        self._provisional = provisional_log
        self._recovery = recovery
        self._events = events  # the runner's own (starts, restarts, re-initialisations) and its wrapper's
        self._step_seconds: list[float] = []

    def step_took(self, seconds: float) -> None:
        """A filter step took ``seconds`` of wall time."""
        self._step_seconds.append(seconds)
        if len(self._step_seconds) > STEP_TIMES_KEPT:
            del self._step_seconds[:STEP_TIMES_KEPT // 2]

    def events(self) -> dict:
        """Every part's events and the runner's, by name."""
        return {**self._events, **self._measurements.events, **self._controls.events, **self._provisional.events}

    def reinitialisations(self) -> int:
        return sum(v for k, v in self._events.items() if k.startswith('reinitialisations.'))

    def values(self) -> dict:
        """Counters for diagnostics: measurements received = rejected + used + dropped + pending +
        repeated."""
        est, queue, book, provisional = self._estimator, self._measurements, self._controls, self._provisional
        steps = est.steps
        times = np.asarray(self._step_seconds[-1000:]) * 1e6
        values = {
            'filter': est.kind, 'neurons': est.neuron_count, 'steps': steps,
            'measurements_received': queue.received,
            'measurements_used': queue.used, 'measurements_dropped': queue.dropped,
            'measurements_repeated': queue.repeated,
            'not_measured': queue.not_measured,
            'measurements_pending': queue.measured_pending,
            'spikes_total': est.total_spikes,
            'spike_fraction': (est.total_spikes / (steps * est.neuron_count)
                               if steps and est.neuron_count else 0.0),
            'silenced_neurons': len(est.silenced),
            'step_time_us_last': float(times[-1]) if times.size else 0.0,
            'step_time_us_median': float(np.median(times)) if times.size else 0.0,
            'controls_missing': book.missing, 'dropout_steps': queue.dropout_steps,
            'applied_received': book.applied_received, 'provisional_held': provisional.held_count,
            **{key: provisional.events[key] for key in ('provisional_steps', 'provisional_corrected',
                                                        'provisional_unconfirmed')},
        }
        values['measurements_rejected'] = sum(queue.rejected.values())
        values.update({f'measurements_rejected.{k}': v for k, v in sorted(queue.rejected.items())})
        values['controls_rejected'] = sum(book.rejected.values())
        values.update({f'controls_rejected.{k}': v for k, v in sorted(book.rejected.items())})
        values.update(sorted(self.events().items()))
        values['reinitialisations'] = self.reinitialisations()
        values['reset_storms'] = self._recovery.storms
        return values

    def problems(self) -> list[str]:
        """What a diagnostics status should warn about."""
        problems = []
        rejected = sum(self._measurements.rejected.values()) + sum(self._controls.rejected.values())
        if rejected:
            problems.append(f'{rejected} inputs rejected')
        if self._controls.missing:
            problems.append(f'{self._controls.missing} controls missing')
        if self._measurements.dropout_steps:
            problems.append(f'{self._measurements.dropout_steps} steps without measurement')
        reinit = self.reinitialisations()
        if reinit:
            problems.append(f'{reinit} re-initialisations')
        if self._recovery.storms:
            problems.append(f'{self._recovery.storms} reset storms')
        return problems
