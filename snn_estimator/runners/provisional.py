"""Provisional steps: the estimate at once with the controller's u_k, corrected when the plant
reports another control (docs/decisions.md, 22b). No ROS.

Since issue 23 the runner predicts with the control the plant reports it applied
(``applied_control``), which a realtime plant publishes when it steps t_k -> t_{k+1}: one tick
after z_k, so an estimate that waits for it is one step late. With provisional steps (the
default, ``RunnerSettings.provisional_steps``) a step whose report is not here yet is taken at
once with the controller's u_k (or the control in force when none came) and published; the
runner keeps what redoing it needs in a :class:`ProvisionalLog`, as a :class:`HeldStep`: z_k,
the control used and a checkpoint from before the step (the runner's and its parts' state,
which the log does not look into). When the plant's report comes (:meth:`ProvisionalLog.report`):

* equal to the control used: the step is final and released;
* different (the plant stepped with another control: u_k came after its realtime tick, or none
  came and the one in force expired): the log hands back that step and every later held one;
  the runner returns to the first one's checkpoint, takes them again in order (each with its
  own report if it is here, else provisionally again), publishes the corrected estimates again
  under their stamps (``republish``) and counts ``provisional_corrected``. The result is exactly
  that of waiting for the report.

A step stays held while any earlier held step is not final (correcting that one redoes the later
ones). At most :data:`PROVISIONAL_LIMIT` steps are held: beyond it the oldest is accepted as
applied (a lost report must not grow memory), counted as ``provisional_unconfirmed``; so is every
held step when something outside the steps changes the filter (``set_state``, a reset request, a
retune: :meth:`ProvisionalLog.settle`), which a rollback must not undo. A time-base restart or a
new start forgets them (:meth:`ProvisionalLog.forget`). Off the grid (``measurement_timing: any``)
the runner waits for the report as before.
"""

from __future__ import annotations

from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator

import numpy as np

from .gates import seconds_to_ns

#: Steps held at most before the oldest is accepted as applied: a report later than this many
#: steps is taken as lost. The controller and the estimator answer a repeated stamp from their
#: last 8 answers (scenario_nodes.runtime.Answers), so a corrected estimate is at most that old.
PROVISIONAL_LIMIT = 8


@dataclass(frozen=True)
class HeldStep:
    """A step taken before its control was final, or after one that was: what redoing it needs."""

    stamp_ns: int
    z: np.ndarray | None
    #: the runner's state from before the step (it restores it; opaque here)
    checkpoint: Any
    u: np.ndarray
    final: bool
    #: the runner's events the step added (taken off again when the step is redone)
    counted: Counter = field(default_factory=Counter)

    def confirmed(self) -> HeldStep:
        """The same step, its control confirmed by the plant's report."""
        return HeldStep(self.stamp_ns, self.z, self.checkpoint, self.u, True, self.counted)


class ProvisionalLog:
    """The held steps, oldest first, and whether they are being taken again (see the module docstring)."""

    def __init__(self, time_step: float, log: Callable[[str, str], None] | None = None):
        self._dt_ns = seconds_to_ns(time_step)
        self._log = log or (lambda level, message: None)
        self._held: list[HeldStep] = []
        self._replaying = False
        #: provisional_steps (taken before their report, once each), provisional_corrected,
        #: provisional_unconfirmed
        self.events = Counter()

    @property
    def held_count(self) -> int:
        """Steps held for their plant's report (or for an earlier one's)."""
        return len(self._held)

    @property
    def oldest_stamp(self) -> int | None:
        """Stamp of the oldest held step (None: none held); its controls must be kept."""
        return self._held[0].stamp_ns if self._held else None

    @property
    def replaying(self) -> bool:
        """Held steps are being taken again (their estimates are corrections)."""
        return self._replaying

    @contextmanager
    def replay(self) -> Iterator[None]:
        """While the runner takes the steps :meth:`report` handed back again."""
        self._replaying = True
        try:
            yield
        finally:
            self._replaying = False

    def hold(self, step: HeldStep) -> None:
        """Keep ``step`` (just taken), then release what is final."""
        if not step.final and not self._replaying:
            self.events['provisional_steps'] += 1  # each step taken before its report, once
        self._held.append(step)
        self.release()

    def release(self) -> None:
        """Drop the held steps that can no longer change: final ones at the front, and the oldest
        beyond PROVISIONAL_LIMIT (accepted as applied)."""
        held = self._held
        while len(held) > PROVISIONAL_LIMIT:
            self._accept(held.pop(0), 'no report within the limit')
        while held and held[0].final:
            held.pop(0)

    def _accept(self, step: HeldStep, why: str) -> None:
        if not step.final:
            self.events['provisional_unconfirmed'] += 1
            self._log('warning', f'the control of t = {step.stamp_ns * 1e-9:.3f} s is taken as applied ({why})')

    def settle(self, why: str = 'the filter is changed') -> None:
        """Accept every held step as it is (before something outside the steps changes the
        filter, which a rollback must not undo)."""
        for step in self._held:
            self._accept(step, why)
        self._held.clear()

    def forget(self) -> None:
        """Drop every held step, uncounted (a new start or time base)."""
        self._held.clear()

    def report(self, stamp_ns: int, u: np.ndarray) -> list[HeldStep]:
        """The plant's report that it applied ``u`` from ``stamp_ns``: confirms its held step
        (returns []), or, when it differs from the control used, removes that step and every
        later one and returns them, to be taken again from the first one's checkpoint."""
        index = next((i for i, step in enumerate(self._held)
                      if abs(step.stamp_ns - stamp_ns) * 2 < self._dt_ns), None)  # as ControlBook pairs them
        if index is None or self._held[index].final:
            return []
        if np.array_equal(u, self._held[index].u):
            self._held[index] = self._held[index].confirmed()
            self.release()
            return []
        redo = self._held[index:]
        del self._held[index:]
        self.events['provisional_corrected'] += 1
        self._log('info', f'at t = {redo[0].stamp_ns * 1e-9:.3f} s the plant applied another control than the '
                  f'estimate used: {len(redo)} step(s) taken again')
        return redo
