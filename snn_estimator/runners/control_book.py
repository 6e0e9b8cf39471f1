"""The control of each filter step, from the controls that came: the controller's u_k, the
plant's reports of what it applied, and the plant's rule for a missing one. No ROS.

The control of the step from t_k, by :meth:`ControlBook.step_control`:

1. once a plant reports the controls it stepped with (``applied_control``), its report for t_k
   (final); before any report, the controller's u_k (final);
2. the report not here yet (late or lost): the controller's u_k, taken provisionally when the
   runner may (snn_estimator.runners.provisional), else final and counted as ``applied_missing``;
3. no control at all: the one in force by the plant's rule
   (:func:`snn_estimator.runners.plant_runner.control_in_force`: the last one used while younger
   than control_validity, else zero thrust), counted as missing; an expiry is counted per step
   (``controls_expired``) and logged once.

A control pairs with a step when its stamp lies within half a step of the step's.
"""

from __future__ import annotations

from collections import Counter
from typing import Callable, Iterable, Mapping

import numpy as np

from .gates import NS, seconds_to_ns
from .plant_runner import control_in_force

#: Controls kept for pairing and replay.
CONTROL_MEMORY = 2000


class ControlBook:
    """The controls by stamp, the plant's reports of what it applied, and the control in force."""

    def __init__(self, time_step: float, n_input: int, log: Callable[[str, str], None] | None = None):
        self._dt_ns = seconds_to_ns(time_step)
        self._n_input = n_input
        self._log = log or (lambda level, message: None)
        self._commanded: dict[int, np.ndarray] = {}  # the controller's, by stamp
        self._applied: dict[int, np.ndarray] = {}    # what the plant reports it stepped with, by stamp
        self._plant_reports = False  # a plant reports its applied controls: they settle the steps
        self._last_used: dict[int, np.ndarray] = {}  # stamp -> u: the newest control a step used
        self._expired = False  # the last one used expired (logged once)
        #: controls refused, by reason
        self.rejected = Counter()
        #: controls_expired, applied_missing (steps, see the module docstring)
        self.events = Counter()
        #: steps without a control of their own (the one in force used)
        self.missing = 0
        #: the plant's reports received
        self.applied_received = 0

    @property
    def plant_reports(self) -> bool:
        """A plant has reported the control it applied (from then on its reports settle the steps)."""
        return self._plant_reports

    # ---------------------------------------------------------------- inputs
    def offer(self, stamp_ns: int, u: np.ndarray, start_ns: int | None) -> str | None:
        """The controller's u stamped ``stamp_ns``; None if kept, else the reason it was refused
        (counted): ``before_init``, before the filter's start at ``start_ns``."""
        if start_ns is not None and stamp_ns < start_ns:
            self.rejected['before_init'] += 1
            self._log('warning', f'rejected control at {stamp_ns / NS:.3f} s: it predates the start '
                      f'at {start_ns / NS:.3f} s')
            return 'before_init'
        self._commanded[stamp_ns] = np.asarray(u, dtype=float)
        if len(self._commanded) > CONTROL_MEMORY:
            del self._commanded[min(self._commanded)]
        return None

    def offer_applied(self, stamp_ns: int, u: np.ndarray, start_ns: int | None) -> str | None:
        """The plant's report that it stepped with ``u`` from ``stamp_ns``; None if kept, else the
        reason it was refused (counted): ``applied_before_init``."""
        if start_ns is not None and stamp_ns < start_ns:
            self.rejected['applied_before_init'] += 1
            return 'applied_before_init'
        self.applied_received += 1
        self._applied[stamp_ns] = np.asarray(u, dtype=float)
        if len(self._applied) > CONTROL_MEMORY:
            del self._applied[min(self._applied)]
        self._plant_reports = True
        return None

    def unreadable(self, reason: str) -> None:
        """Count a control message that could not be read (refused by the wrapper)."""
        self.rejected[reason] += 1

    def add_history(self, controls: Mapping[int, np.ndarray]) -> None:
        """The controls the control topic held when the filter joined (those here win)."""
        for stamp_ns, u in controls.items():
            self._commanded.setdefault(stamp_ns, np.asarray(u, dtype=float))

    # ---------------------------------------------------------------- the control of a step
    def final(self, stamp_ns: int) -> np.ndarray | None:
        """The control that settles the step from ``stamp_ns``: the plant's report once a plant
        reports them, else the controller's; None: not here yet."""
        return self._stamped(self._applied if self._plant_reports else self._commanded, stamp_ns)

    def commanded(self, stamp_ns: int) -> np.ndarray | None:
        """The controller's control for the step from ``stamp_ns`` (None: none came)."""
        return self._stamped(self._commanded, stamp_ns)

    def _stamped(self, controls: dict, stamp_ns: int) -> np.ndarray | None:
        u = controls.get(stamp_ns)
        if u is not None:
            return u
        for control_ns, value in controls.items():
            if abs(control_ns - stamp_ns) * 2 < self._dt_ns:
                return value
        return None

    def before_report(self, stamp_ns: int, provisional: bool) -> bool:
        """The step from ``stamp_ns`` would be taken before the plant's report of it: a plant
        reports, its report is not here, and the runner takes such steps (``provisional``)."""
        return provisional and self._plant_reports and self.final(stamp_ns) is None

    def can_step(self, stamp_ns: int, provisional: bool) -> bool:
        """The step from ``stamp_ns`` can be taken now: its control is final, or it can be taken
        provisionally with the controller's."""
        if self.final(stamp_ns) is not None:
            return True
        return provisional and self._plant_reports and self.commanded(stamp_ns) is not None

    def step_control(self, stamp_ns: int, provisional: bool, validity_ns: int) -> tuple[np.ndarray, bool]:
        """(u, final) of the step from ``stamp_ns`` (see the module docstring); final False: taken
        before the plant's report (``provisional`` allows it). The step is taken: u becomes the
        control in force."""
        u, final = self.final(stamp_ns), True
        if u is None and self._plant_reports:
            u = self.commanded(stamp_ns)
            if provisional:
                final = False
            else:
                self.events['applied_missing'] += 1
        if u is None:
            u = self.in_force(stamp_ns, validity_ns)
            self.missing += 1
            self._log('warning', f'no control for t = {stamp_ns / NS:.3f} s: using the one in force')
        else:
            self._last_used, self._expired = {stamp_ns: u}, False
        return u, final

    def in_force(self, stamp_ns: int, validity_ns: int) -> np.ndarray:
        """The control the plant applied from ``stamp_ns`` when none stamped for it came: the
        last one used while younger than ``validity_ns``, else zero thrust (the plant's rule)."""
        u, stamp = control_in_force(self._last_used, stamp_ns, validity_ns, self._n_input)
        if stamp is None and self._last_used:
            self.events['controls_expired'] += 1
            if not self._expired:
                self._log('warning', f'the control of t = {max(self._last_used) / NS:.3f} s expired at t = '
                          f'{stamp_ns / NS:.3f} s: predicting with zero thrust, as the plant applies')
            self._expired = True
        return u

    def controls_over(self, stamps: Iterable[int], validity_ns: int) -> list[np.ndarray]:
        """The control of each step from ``stamps`` (in order), the one in force where none came
        (for a least-squares start; nothing counted)."""
        known, last_used = [], dict(self._last_used)
        for stamp_ns in stamps:
            u = self.final(stamp_ns)
            if u is None:
                u = control_in_force(last_used, stamp_ns, validity_ns, self._n_input)[0]
            else:
                last_used = {stamp_ns: u}
            known.append(u)
        return known

    # ---------------------------------------------------------------- forgetting
    def forget_used(self, stamp_ns: int, held_from: int | None = None) -> None:
        """After the step from ``stamp_ns``: drop the controls of the steps up to it, but those of
        the steps from ``held_from`` on (held steps may be taken again)."""
        cut = stamp_ns if held_from is None else min(stamp_ns, held_from - self._dt_ns // 2 - 1)
        self._commanded = {t: v for t, v in self._commanded.items() if t > cut}
        self._applied = {t: v for t, v in self._applied.items() if t > cut}

    def keep_from(self, stamp_ns: int) -> None:
        """The filter starts at ``stamp_ns``: drop the controls before it."""
        self._commanded = {t: u for t, u in self._commanded.items() if t >= stamp_ns}
        self._applied = {t: u for t, u in self._applied.items() if t >= stamp_ns}

    def restart(self) -> None:
        """A new time base: forget the controls and whether a plant reports (the control in
        force stays until a step uses another)."""
        self._commanded.clear()
        self._applied.clear()
        self._plant_reports = False

    def step_state(self) -> tuple:
        """What a step changes here, for :meth:`restore_step_state` (a step taken again)."""
        return dict(self._last_used), self._expired, self.missing, Counter(self.events)

    def restore_step_state(self, state: tuple) -> None:
        last_used, self._expired, self.missing, events = state
        self._last_used, self.events = dict(last_used), Counter(events)
