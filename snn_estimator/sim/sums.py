"""The readings of a batch of closed-loop runs without their trajectories.

``simulate(..., trajectories=False)`` keeps no trajectory: the compiled loop writes each chunk of
steps into small buffers and :class:`LoopSums` keeps of them what the tables read: each run's
error, NEES and NIS over the metric window, its delta-v, peak thrust, spikes and final state. A
run then costs memory for its window (~40 kB for the 60 s window of the rendezvous), not for its
duration. The same readings from kept trajectories (:meth:`LoopSums.of_trajectories`) are what a
campaign's batch sends back, whichever way it ran; the statistics over them (SimulationResult)
are the trajectories' formulas on the same numbers, the runs that diverged left out.
"""

from __future__ import annotations

import numpy as np


class LoopSums:
    """Per run, over the metric window's samples ``window_start`` .. ``steps`` of ``runs`` runs
    of ``steps`` steps of ``dt``: the error truth - estimate, NEES and NIS (the NIS of steps
    window_start - 1 .. steps - 1); and the run's sum of |u| over steps and axes, largest |u|,
    spikes and final state. Sample k is the time k dt, step k the interval after it (its NIS and
    control)."""

    def __init__(self, runs: int, n: int, steps: int, window_start: int, dt: float, covariance: bool):
        self.runs, self.steps, self.window_start, self.dt = runs, steps, window_start, dt
        #: whether NEES and NIS are kept (a filter with a covariance)
        self.covariance = covariance
        width = self.samples = steps + 1 - window_start
        self.error = np.full((runs, width, n), np.nan)
        self.nees = np.full((runs, width), np.nan) if covariance else None
        self.nis = np.full((runs, width), np.nan) if covariance else None
        self.abs_control = np.zeros(runs)
        self.peak_control = np.zeros(runs)
        self.spikes = np.zeros(runs, dtype=np.int64)
        self.final_state = np.full((runs, n), np.nan)

    @classmethod
    def of_trajectories(cls, result) -> LoopSums:
        """The readings of a SimulationResult that kept its trajectories."""
        runs, samples, n = result.truth.shape
        window = result.window()
        sums = cls(runs, n, samples - 1, window.start, result.scenario.dt, result.nees is not None)
        sums.add_samples(0, result.truth, result.estimate, result.nees)
        sums.add_steps(0, result.control, result.nis, result.spikes_per_step)
        return sums

    def add_samples(self, first: int, truth: np.ndarray, estimate: np.ndarray, nees: np.ndarray | None) -> None:
        """Samples first .. first + len - 1 of every run (arrays (runs, len, ...))."""
        last = first + truth.shape[1]
        if last == self.steps + 1:
            self.final_state[:] = truth[:, -1]
        lo = max(first, self.window_start)
        if lo >= last:
            return
        part, into = slice(lo - first, last - first), slice(lo - self.window_start, last - self.window_start)
        self.error[:, into] = truth[:, part] - estimate[:, part]
        if nees is not None:
            self.nees[:, into] = nees[:, part]

    def add_steps(self, first: int, control: np.ndarray, nis: np.ndarray | None, spikes: np.ndarray | None) -> None:
        """Steps first .. first + len - 1 of every run: controls (runs, len, m_u), NIS and spikes
        per step (runs, len). A NaN control (a run that diverged) makes its totals NaN."""
        self.abs_control += np.abs(control).sum(axis=(1, 2))
        if control.size:
            self.peak_control = np.fmax(self.peak_control, np.abs(control).max(axis=(1, 2)))
            self.peak_control[np.isnan(control).any(axis=(1, 2))] = np.nan
        if spikes is not None:
            self.spikes += spikes.sum(axis=1)
        last = first + control.shape[1]
        lo = max(first, self.window_start - 1, 0)
        if nis is not None and lo < last:
            offset = self.window_start - 1
            self.nis[:, lo - offset:last - offset] = nis[:, lo - first:last - first]

    def delta_v(self) -> np.ndarray:
        return self.abs_control * self.dt


class ChunkSink:
    """Where the compiled loop writes when no trajectory is kept: buffers of ``chunk`` steps
    (~12 kB per run for the rendezvous at the default 64), taken into :class:`LoopSums` after
    each (the kernel computes NEES and NIS only in the window), a diverged run's samples after
    its step discarded first as in the kept trajectories."""

    def __init__(self, sums: LoopSums, n_u: int, spiking: bool, chunk: int = 64):
        runs, n, covariance = sums.runs, sums.error.shape[2], sums.covariance
        chunk = self.chunk = max(1, min(chunk, sums.steps))
        self.sums, self.metrics_from = sums, sums.window_start
        self._covariance, self._spiking = covariance, spiking
        self.outputs = (np.zeros((runs, chunk, n)), np.zeros((runs, chunk, n)),
                        np.zeros((runs, chunk, n if covariance else 0)), np.zeros((runs, chunk if covariance else 0)),
                        np.zeros((runs, chunk if covariance else 0)), np.zeros((runs, chunk, n_u)),
                        np.zeros((runs, chunk if spiking else 0), dtype=np.int64), np.zeros((0, 1), np.int16))

    def offsets(self, first: int) -> tuple[int, int]:
        return 0, 0

    def done(self, first: int, count: int, diverged_at: np.ndarray) -> None:
        """Steps first .. first + count - 1 are in the buffers: discard what came after a run
        diverged (as _Record.discard), then keep the rest."""
        truth, estimate, _, nees, nis, control, spikes, _ = (a[:, :count] if a.ndim > 1 and a.shape[0] else a
                                                             for a in self.outputs)
        for b in np.flatnonzero(diverged_at >= 0):
            step = int(diverged_at[b]) - first  # in this chunk's indices
            for samples in (truth, estimate, nees if self._covariance else None):
                if samples is not None:
                    samples[b, max(step, 0):] = np.nan  # sample first + j + 1 at j: after the step
            control[b, max(step, 0):] = np.nan
            if self._covariance:
                nis[b, max(step, 0):] = np.nan
            if self._spiking:
                spikes[b, max(step, 0):] = 0
        self.sums.add_samples(first + 1, truth, estimate, nees if self._covariance else None)
        self.sums.add_steps(first, control, nis if self._covariance else None, spikes if self._spiking else None)
