"""Which peers of a node are gone: an input (truth, measurement, estimate, control, the clock)
not seen for a while. No ROS.

Each node feeds :meth:`PeerWatch.saw` with every input and calls :meth:`PeerWatch.check`
from a wall-clock timer; a peer silent for ``timeout`` wall seconds is *missing* (logged once,
diagnostics WARN), for ``error_factor`` times that *gone* (ERROR); when it comes back that is
logged once and the level clears. Wall time, because the clock itself may be what stopped (a
dead plant stops simulated time in every node).
"""

from __future__ import annotations

import time
from typing import Callable, Iterable

OK, WARN, ERROR = 0, 1, 2
LEVEL_NAMES = {OK: 'OK', WARN: 'WARN', ERROR: 'ERROR'}


class PeerWatch:
    """The inputs of one node and how long each has been silent."""

    def __init__(self, inputs: Iterable[str], timeout: float = 2.0, error_factor: float = 5.0,
                 log: Callable[[str, str], None] | None = None, wall_clock: Callable[[], float] = time.monotonic):
        if not timeout > 0:
            raise ValueError(f'peer_timeout must be > 0 s; got {timeout}')
        self.timeout, self.error_timeout = timeout, timeout * error_factor
        self._log = log or (lambda level, message: None)
        self._wall = wall_clock
        self._last = {name: None for name in inputs}  # None: never seen (nothing to miss yet)
        self.levels = {name: OK for name in self._last}
        self.outages = {name: 0 for name in self._last}

    def saw(self, name: str) -> None:
        """An input ``name`` arrived."""
        now = self._wall()
        if self.levels[name] != OK:
            self._log('info', f"'{name}' is back after {now - self._last[name]:.1f} s")
            self.levels[name] = OK
        self._last[name] = now

    def check(self) -> bool:
        """Raise the level of silent inputs; True when a level changed (diagnostics due)."""
        now, changed = self._wall(), False
        for name, last in self._last.items():
            if last is None:
                continue
            silent = now - last
            level = ERROR if silent > self.error_timeout else WARN if silent > self.timeout else OK
            if level > self.levels[name]:
                if self.levels[name] == OK:
                    self.outages[name] += 1
                    self._log('warning', f"no '{name}' for {silent:.1f} s: is its publisher gone?")
                else:
                    self._log('error', f"no '{name}' for {silent:.1f} s")
                self.levels[name] = level
                changed = True
        return changed

    @property
    def level(self) -> int:
        return max(self.levels.values(), default=OK)

    def problems(self) -> list[str]:
        now = self._wall()
        return [f"no '{name}' for {now - self._last[name]:.1f} s" for name, level in self.levels.items() if level]

    def values(self) -> dict:
        values = {f'peer.{name}': LEVEL_NAMES[level] for name, level in self.levels.items()}
        values.update({f'peer_outages.{name}': n for name, n in self.outages.items()})
        return values
