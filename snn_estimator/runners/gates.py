"""Input gates on stamps, written once for every node (no ROS).

Each node of the loop takes a stream of stamped inputs that arrive late, twice, from the
future or from a restarted time base. The rules are the same everywhere:

* without a running clock (it reads 0), a stamp far before the last one means the time base
  restarted (a restarted plant, a bag played in a loop): start over (with a clock, old stamps
  are only late inputs; the clock's own jump says when it restarts);
* a stamp not newer than the last is the same input again (a lockstep resend) or a straggler;
* an input stamped further ahead of the clock than ``max_input_age`` plus two steps is refused:
  accepted, it would make every real input look old (an estimate is stamped a step ahead, and
  /clock may arrive after the message it precedes, hence the two steps);
* an input further behind the clock than ``max_input_age`` is too old to act on.
"""

from __future__ import annotations

from typing import Callable

NS = 1_000_000_000


def seconds_to_ns(seconds: float) -> int:
    return int(round(seconds * NS))


def seconds_ahead(stamp_ns: int, now_ns: int, max_input_age: float, time_step: float) -> float:
    """How far ``stamp_ns`` lies ahead of the clock when that is more than ``max_input_age``
    plus two steps; 0 when it is not, or without a clock (now_ns <= 0)."""
    lead = seconds_to_ns(max_input_age + 2 * time_step)
    return (stamp_ns - now_ns) / NS if now_ns > 0 and stamp_ns > now_ns + lead else 0.0


class NewestFirst:
    """The gate of a stream where only the newest input counts (the sensor's truths, the
    controller's estimates). :meth:`classify` says what an input is:

    * 'new' (accepted; it becomes the last), 'restarted' (accepted after a time-base restart),
    * 'repeat' (stamp not newer than the last: a resend, or a straggler),
    * 'too_old' (more than max_input_age behind the clock), 'future' (see the module docstring).
    The age checks apply only when ``max_input_age`` is given.
    """

    def __init__(self, time_jump_threshold: float, max_input_age: float | None = None,
                 time_step: float = 0.1):
        self.time_jump_threshold = time_jump_threshold
        self.max_input_age = max_input_age
        self.time_step = time_step
        self.last_ns: int | None = None

    def classify(self, stamp_ns: int, clock: Callable[[], int]) -> str:
        """``clock()`` reads the simulated clock in ns (0: none yet); it is read only when a
        rule needs it (the gate runs for every input)."""
        far_back = (self.last_ns is not None
                    and stamp_ns < self.last_ns - seconds_to_ns(self.time_jump_threshold))
        checks_age = self.max_input_age is not None
        now_ns = clock() if far_back or checks_age else 0
        restarted = far_back and now_ns <= 0
        if restarted:
            self.last_ns = None
        if self.last_ns is not None and stamp_ns <= self.last_ns:
            return 'repeat'
        if self.max_input_age is not None:
            if now_ns > 0 and stamp_ns < now_ns - seconds_to_ns(self.max_input_age):
                return 'too_old'
            if seconds_ahead(stamp_ns, now_ns, self.max_input_age, self.time_step):
                return 'future'
        self.last_ns = stamp_ns
        return 'restarted' if restarted else 'new'

    def reset(self) -> None:
        """Forget the last stamp (the clock jumped back)."""
        self.last_ns = None
