"""Progress of the long commands (experiments, campaigns, neuromorphic, benches): done of total,
rate and ETA on one line of stderr, redrawn at most every ``interval`` s; silent when stderr is
not a terminal (a log, CI, a pipe), so logs hold only the commands' own output.

While a progress line is open on a terminal, ``sys.stdout`` and ``sys.stderr`` are wrapped so
that anything the command prints first erases the line (it is drawn again at the next step):
a loop's own ``print`` calls stay clean, and a hook is one line.

    with Progress(total=len(items), what='runs', label='bench') as progress:
        for item in items:
            ...
            progress.advance()

or ``for item in track(items, what='cells', label='sweep'): ...``.
"""

from __future__ import annotations

import sys
import time


def eta_text(seconds: float | None) -> str:
    """``H:MM:SS`` (``--:--:--`` when not known yet)."""
    if seconds is None:
        return '-:--:--'
    seconds = int(round(seconds))
    return f'{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}'


class Progress:
    """``label  done/total what  rate what/s  ETA h:mm:ss  [note]`` on ``stream`` (stderr).

    ``enabled`` None: only when the stream is a terminal. ``clock`` is for tests."""

    def __init__(self, total: int, what: str = 'runs', label: str = '', stream=None,
                 enabled: bool | None = None, interval: float = 0.2, clock=time.perf_counter):
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = _is_terminal(self.stream) if enabled is None else enabled
        self.total, self.what, self.label = int(total), what, label
        self.done = 0
        self.note = ''
        self._clock = clock
        self._started = clock()
        self._interval = interval
        self._drawn = None  # time of the last draw; None: nothing on the line yet
        self._saved = None  # (stdout, stderr) while open

    def restart(self, total: int | None = None, done: int = 0) -> None:
        """Count again from ``done`` (e.g. cells already finished) with a new clock."""
        if total is not None:
            self.total = int(total)
        self.done = done
        self._started = self._clock()

    def advance(self, n: int = 1, note: str | None = None) -> None:
        self.done += n
        if note is not None:
            self.note = note
        self.draw(force=self.done >= self.total)

    def rate(self) -> float:
        elapsed = self._clock() - self._started
        return self.done / elapsed if elapsed > 0 else 0.0

    def eta(self) -> float | None:
        rate = self.rate()
        return (self.total - self.done) / rate if rate > 0 else None

    def line(self) -> str:
        head = f'{self.label}  ' if self.label else ''
        note = f'  {self.note}' if self.note else ''
        return (f'{head}{self.done}/{self.total} {self.what}  {self.rate():.1f} {self.what}/s  '
                f'ETA {eta_text(self.eta())}{note}')

    def draw(self, force: bool = False) -> None:
        if not self.enabled:
            return
        now = self._clock()
        if force or self._drawn is None or now - self._drawn >= self._interval:
            self.stream.write('\r' + self.line().ljust(78) + '\x1b[K')
            self.stream.flush()
            self._drawn = now

    def say(self, text: str) -> None:
        """A line of its own (the progress line is redrawn after it); silent like the rest."""
        if self.enabled:
            self.stream.write(('\r\x1b[K' if self._drawn is not None else '') + text + '\n')
            self.stream.flush()
            self._drawn = None

    def close(self) -> None:
        """End the line (the last state stays on screen) and unwrap the streams."""
        if self._saved is not None:
            sys.stdout, sys.stderr = self._saved
            self._saved = None
        if self.enabled:
            self.draw(force=True)
            self.stream.write('\n')
            self.stream.flush()
            self._drawn = None

    def clear(self) -> None:
        """Erase the progress line (before other output)."""
        if self._drawn is not None:
            self.stream.write('\r\x1b[K')
            self.stream.flush()
            self._drawn = None

    def open(self) -> Progress:
        """Draw the line and let other output erase it first (see the module); ``close`` undoes it."""
        if self.enabled and self._saved is None:
            self._saved = (sys.stdout, sys.stderr)
            sys.stdout, sys.stderr = _Clearing(sys.stdout, self), _Clearing(sys.stderr, self)
        self.draw(force=True)
        return self

    def __enter__(self) -> Progress:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()


def track(items, what: str = 'items', label: str = '', total: int | None = None, **kwargs):
    """Yield from ``items``, advancing a :class:`Progress` after each."""
    items = list(items) if total is None and not hasattr(items, '__len__') else items
    with Progress(len(items) if total is None else total, what, label, **kwargs) as progress:
        for item in items:
            yield item
            progress.advance()


class _Clearing:
    """A stream that erases the progress line before writing."""

    def __init__(self, stream, progress: Progress):
        self._stream, self._progress = stream, progress

    def write(self, text):
        if text:
            self._progress.clear()
        return self._stream.write(text)

    def __getattr__(self, name):
        return getattr(self._stream, name)


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False
