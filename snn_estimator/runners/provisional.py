"""Provisional steps: the estimate at once with the controller's u_k, corrected when the plant
reports another control (docs/decisions.md, 22b). A part of
:class:`snn_estimator.runners.filter_runner.FilterRunner`.

Since issue 23 the runner predicts with the control the plant reports it applied
(``applied_control``), which a realtime plant publishes when it steps t_k -> t_{k+1}: one tick
after z_k, so an estimate that waits for it is one step late. With provisional steps (the
default, ``RunnerSettings.provisional_steps``) a step whose report is not here yet is taken at
once with the controller's u_k (or the control in force when none came) and published; the
runner keeps what redoing it needs, a :class:`Held` step: z_k, the control used and a checkpoint
from before the step (the estimator's snapshot, the recovery's data, the runner's step
counters). When the plant's report comes:

* equal to the control used: the step is final and its checkpoint dropped;
* different (the plant stepped with another control: u_k came after its realtime tick, or none
  came and the one in force expired): the runner returns to the checkpoint, takes that step again
  with the applied control and every later held step in order (each with its own report if it is
  here, else provisionally again), publishes the corrected estimates again under their stamps
  (``republish``) and counts ``provisional_corrected``. The result is exactly that of waiting for
  the report.

A step stays held while any earlier held step is not final (correcting that one redoes the later
ones). At most :data:`PROVISIONAL_LIMIT` steps are held: beyond it the oldest is accepted as
applied (a lost report must not grow memory), counted as ``provisional_unconfirmed``; so is every
held step when something outside the steps changes the filter (``set_state``, a reset request, a
retune: :meth:`ProvisionalSteps.settle`), which a rollback must not undo. A time-base restart or a
new start forgets them. Off the grid (``measurement_timing: any``) the runner waits for the
report as before.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Steps held at most before the oldest is accepted as applied: a report later than this many
#: steps is taken as lost. The controller and the estimator answer a repeated stamp from their
#: last 8 answers (scenario_nodes.runtime.Answers), so a corrected estimate is at most that old.
PROVISIONAL_LIMIT = 8


@dataclass
class Held:
    """A step taken before its control was final, or after one that was: what redoing it needs."""

    stamp_ns: int
    z: np.ndarray | None
    #: the state before the step: estimator snapshot, recovery snapshot, runner counters
    estimator: Any
    recovery: Any
    runner: tuple
    events_before: Counter
    u: np.ndarray | None = None
    final: bool = False
    counted: Counter = field(default_factory=Counter)  # what the step added to the runner's events


class ProvisionalSteps:
    """The runner's held steps (see the module docstring)."""

    #: the runner's fields a step changes (beside the estimator, the recovery and the events)
    _STEP_FIELDS = ('time_ns', '_high_nis', '_reset_requested', 'measurements_used', '_last_measurement_ns',
                    'dropout_steps', 'controls_missing', '_held', '_expired')

    @property
    def provisional_held(self) -> int:
        """Steps held for their plant's report (or for an earlier one's)."""
        return len(self._provisional)

    def _provisional_on(self) -> bool:
        return self.settings.provisional_steps and self.on_grid and self._plant_reports

    def _can_step(self, stamp_ns: int) -> bool:
        """The step from ``stamp_ns`` can be taken now: its control is final, or it can be taken
        provisionally with the controller's."""
        if self._control_for(stamp_ns) is not None:
            return True
        return self._provisional_on() and self._stamped(self._controls, stamp_ns) is not None

    def _control_of_step(self, stamp_ns: int) -> tuple[np.ndarray | None, bool]:
        """(u, final) for the step from ``stamp_ns``: the plant's report (final); before the plant
        reports any, the controller's u_k (final); else, the report not here (late or lost), the
        controller's u_k, provisional, or without provisional steps final and counted as
        applied_missing. u None: no control at all (the caller takes the one in force)."""
        u = self._control_for(stamp_ns)
        if u is not None or not self._plant_reports:
            return u, True
        u = self._stamped(self._controls, stamp_ns)
        if self._provisional_on():
            return u, False
        self.events['applied_missing'] += 1
        return u, True

    def _forget_controls(self, stamp_ns: int) -> None:
        """After the step from ``stamp_ns``: drop the controls of the steps before, but those of
        held steps (they may be taken again)."""
        cut = stamp_ns
        if self._provisional:
            cut = min(stamp_ns, self._provisional[0].stamp_ns - self._dt_ns // 2 - 1)
        self._controls = {t: v for t, v in self._controls.items() if t > cut}
        self._applied = {t: v for t, v in self._applied.items() if t > cut}

    def _checkpoint(self, stamp_ns: int, z: np.ndarray | None) -> Held | None:
        """Before the step from ``stamp_ns``: a Held step if it is provisional (no report yet) or
        follows one that is, else None."""
        if not self._provisional and not (self._provisional_on() and self._control_for(stamp_ns) is None):
            return None
        return Held(stamp_ns, None if z is None else np.array(z, dtype=float), self.estimator.snapshot(),
                    self.recovery.snapshot(), tuple(getattr(self, name) for name in self._STEP_FIELDS),
                    Counter(self.events))

    def _hold(self, held: Held, u: np.ndarray, final: bool) -> None:
        """After the step: keep ``held`` with the control it used, then release what is final."""
        held.u, held.final = np.array(u, dtype=float), final
        held.counted = self.events - held.events_before
        held.events_before = None
        if not final and not self._replaying:
            self.events['provisional_steps'] += 1  # each step taken before its report, once
        self._provisional.append(held)
        self._release()

    def _release(self) -> None:
        """Drop the held steps that can no longer change: final ones at the front, and the oldest
        beyond PROVISIONAL_LIMIT (accepted as applied)."""
        held = self._provisional
        while len(held) > PROVISIONAL_LIMIT:
            self._accept(held.pop(0), 'no report within the limit')
        while held and held[0].final:
            held.pop(0)

    def _accept(self, held: Held, why: str) -> None:
        if not held.final:
            self.events['provisional_unconfirmed'] += 1
            self._log('warning', f'the control of t = {held.stamp_ns * 1e-9:.3f} s is taken as applied ({why})')

    def settle(self, why: str = 'the filter is changed') -> None:
        """Accept every held step as it is (before something outside the steps changes the
        filter, which a rollback must not undo)."""
        for held in self._provisional:
            self._accept(held, why)
        self._provisional.clear()

    def _report(self, stamp_ns: int, u: np.ndarray) -> None:
        """The plant's report for ``stamp_ns``: confirms its held step, or corrects it."""
        index = next((i for i, held in enumerate(self._provisional)
                      if abs(held.stamp_ns - stamp_ns) * 2 < self._dt_ns), None)  # as _stamped pairs them
        if index is None or self._provisional[index].final:
            return
        if np.array_equal(u, self._provisional[index].u):
            self._provisional[index].final = True
            self._release()
        else:
            self._correct(index)

    def _correct(self, index: int) -> None:
        """The step held at ``index`` used another control than the plant applied: back to its
        checkpoint, then that step and every later held one again, in order, republished."""
        redo = self._provisional[index:]
        del self._provisional[index:]
        first = redo[0]
        self.estimator.restore(first.estimator)
        self.recovery.restore(first.recovery)
        for name, value in zip(self._STEP_FIELDS, first.runner):
            setattr(self, name, value)
        for held in redo:
            self.events.subtract(held.counted)
        for key in [key for key, count in self.events.items() if count <= 0]:
            del self.events[key]
        self.events['provisional_corrected'] += 1
        self._log('info', f'at t = {first.stamp_ns * 1e-9:.3f} s the plant applied another control than the '
                  f'estimate used: {len(redo)} step(s) taken again')
        self._replaying = True
        try:
            for held in redo:
                if not self.started:
                    break
                self._step(held.z, held.stamp_ns)
        finally:
            self._replaying = False
        self._release()
