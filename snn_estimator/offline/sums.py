"""The readings of a batch of closed-loop runs without their trajectories.

``simulate(..., trajectories=False)`` keeps no trajectory: the compiled loop writes each chunk of
steps into small buffers and :class:`LoopSums` folds them into what the tables read (the RMSE and
the mean error over the metric window, NEES and NIS per window step summed over runs, delta-v,
peak thrust, spikes and the final state per run), so a run costs memory for its chunk buffers, not
for its duration. The same sums from kept trajectories (:meth:`LoopSums.of_trajectories`) are what
a campaign's batch sends back, whichever way it ran.
"""

from __future__ import annotations

import numpy as np


class LoopSums:
    """Sums over runs and the metric window's samples (``window_start`` .. ``steps``), and per-run
    totals, of ``runs`` runs of ``steps`` steps of ``dt``; samples are times, sample k at k dt,
    step k the interval [k dt, (k + 1) dt) (its NIS and control)."""

    def __init__(self, runs: int, n: int, steps: int, window_start: int, dt: float, covariance: bool):
        self.runs, self.steps, self.window_start, self.dt = runs, steps, window_start, dt
        #: whether NEES and NIS are summed (a filter with a covariance)
        self.covariance = covariance
        width = steps + 1 - window_start
        self.samples = width
        self.sum_sq = np.zeros(n)
        self.sum_error = np.zeros((width, n))       # per window sample, summed over runs
        self.nees_sum = np.zeros(width)
        self.nis_sum = np.zeros(width)               # steps window_start - 1 .. steps - 1
        self.abs_control = np.zeros(runs)            # sum over steps and axes of |u|
        self.peak_control = np.zeros(runs)           # largest |u| on any axis
        self.spikes = np.zeros(runs, dtype=np.int64)
        self.final_state = np.full((runs, n), np.nan)

    @classmethod
    def of_trajectories(cls, result) -> LoopSums:
        """The sums of a SimulationResult that kept its trajectories."""
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
        part = slice(lo - first, last - first)
        error = truth[:, part] - estimate[:, part]
        self.sum_sq += np.sum(error * error, axis=(0, 1))
        self.sum_error[lo - self.window_start:last - self.window_start] += error.sum(axis=0)
        if nees is not None:
            self.nees_sum[lo - self.window_start:last - self.window_start] += nees[:, part].sum(axis=0)

    def add_steps(self, first: int, control: np.ndarray, nis: np.ndarray | None, spikes: np.ndarray | None) -> None:
        """Steps first .. first + len - 1 of every run: controls (runs, len, m_u), NIS and spikes
        per step (runs, len)."""
        self.abs_control += np.abs(control).sum(axis=(1, 2))
        if control.size:
            np.maximum(self.peak_control, np.abs(control).max(axis=(1, 2)), out=self.peak_control)
        if spikes is not None:
            self.spikes += spikes.sum(axis=1)
        last = first + control.shape[1]
        lo = max(first, self.window_start - 1, 0)
        if nis is not None and lo < last:
            offset = self.window_start - 1
            self.nis_sum[lo - offset:last - offset] += nis[:, lo - first:last - first].sum(axis=0)

    def rmse(self) -> np.ndarray:
        return np.sqrt(self.sum_sq / (self.runs * self.samples))

    def mean_error(self) -> np.ndarray:
        return np.mean(np.abs(self.sum_error / self.runs), axis=0)

    def delta_v(self) -> np.ndarray:
        return self.abs_control * self.dt


class ChunkSink:
    """Where the compiled loop writes when no trajectory is kept: buffers of ``chunk`` steps
    (~12 kB per run for the rendezvous at the default 64), folded into :class:`LoopSums` after
    each (the kernel computes NEES and NIS only in the window)."""

    def __init__(self, sums: LoopSums, n_u: int, spiking: bool, chunk: int = 64):
        runs, n, covariance = sums.runs, sums.sum_sq.size, sums.covariance
        chunk = self.chunk = max(1, min(chunk, sums.steps))
        self.sums, self.metrics_from = sums, sums.window_start
        self._covariance, self._spiking = covariance, spiking
        self.outputs = (np.zeros((runs, chunk, n)), np.zeros((runs, chunk, n)),
                        np.zeros((runs, chunk, n if covariance else 0)), np.zeros((runs, chunk if covariance else 0)),
                        np.zeros((runs, chunk if covariance else 0)), np.zeros((runs, chunk, n_u)),
                        np.zeros((runs, chunk if spiking else 0), dtype=np.int64), np.zeros((0, 1), np.int16))

    def offsets(self, first: int) -> tuple[int, int]:
        return 0, 0

    def done(self, first: int, count: int) -> None:
        truth, estimate, _, nees, nis, control, spikes, _ = self.outputs
        self.sums.add_samples(first + 1, truth[:, :count], estimate[:, :count],
                              nees[:, :count] if self._covariance else None)
        self.sums.add_steps(first, control[:, :count], nis[:, :count] if self._covariance else None,
                            spikes[:, :count] if self._spiking else None)
