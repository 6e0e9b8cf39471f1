"""What a simulation returns: the trajectories (or the metric window's sums), and the statistics
the tables read: RMSE, |mean error|, final range, delta-v, spikes, NEES/NIS consistency.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.stats

from snn_estimator.catalog import TWIN_OF

from .scenarios import Scenario
from .sums import LoopSums


@dataclass
class SimulationResult:
    """Trajectories of a (batched) closed-loop run; arrays have a leading runs axis."""

    kind: str
    scenario: Scenario
    time: np.ndarray            # (steps + 1,)
    truth: np.ndarray           # (runs, steps + 1, n)
    estimate: np.ndarray        # (runs, steps + 1, n)
    covariance_diag: np.ndarray | None  # (runs, steps + 1, n)
    control: np.ndarray         # (runs, steps, m_u)
    spikes_per_step: np.ndarray | None  # (runs, steps)
    raster: np.ndarray | None   # (steps, N) spikes per neuron per step for run 0
    neuron_count: int
    wall_time: float
    capped_steps: int = 0
    extra: dict = field(default_factory=dict)
    #: e^T P^-1 e per run and time (e = truth - estimate, P the filter's covariance), shape
    #: (runs, steps + 1); None for filters without a covariance.
    nees: np.ndarray | None = None
    #: nu^T (C P C^T + R_hat)^-1 nu of each measurement against the prior estimate, (runs,
    #: steps); None without a covariance.
    nis: np.ndarray | None = None
    #: The readings without the trajectories (simulate(..., trajectories=False); then truth,
    #: estimate, covariance_diag, control, NEES, NIS and the raster are None): sums.LoopSums.
    kept_sums: LoopSums | None = None
    #: The step at which each run diverged (its state or control went non-finite), -1 for a run
    #: that did not; its samples after that step are NaN (None: not recorded).
    diverged_at: np.ndarray | None = None

    @property
    def runs(self) -> int:
        return self.kept_sums.runs if self.truth is None else self.truth.shape[0]

    @property
    def diverged(self) -> np.ndarray:
        """True for each run that diverged, shape (runs,). The statistics below (RMSE, mean
        error, spikes, NEES/NIS) are over the other runs; per-run arrays keep NaN for it."""
        if self.diverged_at is None:
            return np.zeros(self.runs, dtype=bool)
        return self.diverged_at >= 0

    def _kept(self, per_run: np.ndarray) -> np.ndarray:
        """``per_run`` (leading runs axis) without the runs that diverged (as it is if none did)."""
        diverged = self.diverged
        return per_run[~diverged] if diverged.any() else per_run

    @property
    def sums(self) -> LoopSums:
        """The metric window's samples and the per-run totals (sums.LoopSums): kept as such, or
        taken from the trajectories."""
        return self.kept_sums if self.truth is None else LoopSums.of_trajectories(self)

    def _without_trajectories(self, what: str, seconds: float | None = None) -> bool:
        """True when only the window was kept (then ``seconds`` must be the metric window)."""
        if self.truth is not None:
            return False
        if seconds is not None and abs(seconds - self.scenario.metric_window) > 1e-9:
            raise ValueError(f'{what} over {seconds} s needs the trajectories (kept: the metric window of '
                             f'{self.scenario.metric_window} s): simulate(..., trajectories=True)')
        return True

    @property
    def error(self) -> np.ndarray:
        if self.truth is None:
            raise ValueError('this run kept no trajectories: simulate(..., trajectories=True)')
        return self.truth - self.estimate

    def window(self, seconds: float | None = None) -> slice:
        seconds = self.scenario.metric_window if seconds is None else seconds
        count = int(round(seconds / self.scenario.dt))
        return slice(self.time.size - count, self.time.size)

    def rmse(self, seconds: float | None = None) -> np.ndarray:
        """Ordinary RMSE per state over the final window: sqrt(mean over runs and time of e^2)."""
        if self._without_trajectories('rmse', seconds):
            e = self._kept(self.kept_sums.error)
        else:
            e = self._kept(self.error)[:, self.window(seconds)]
        return np.sqrt(np.mean(e * e, axis=(0, 1)))

    def mean_error(self, seconds: float | None = None) -> np.ndarray:
        """Time average over the final window of |mean over runs of e(t)| per state."""
        if self._without_trajectories('mean_error', seconds):
            e = self._kept(self.kept_sums.error)
        else:
            e = self._kept(self.error)[:, self.window(seconds)]
        return np.mean(np.abs(e.mean(axis=0)), axis=0)

    def rmse_history(self) -> np.ndarray:
        """RMSE over runs at each time, shape (steps + 1, n)."""
        return np.sqrt(np.mean(self._kept(self.error) ** 2, axis=0))

    @property
    def spike_fraction(self) -> float | None:
        """Spikes emitted / (N x steps), averaged over runs (Fig. 7: 17%)."""
        if self.truth is None and self.neuron_count:
            spikes = self._kept(self.kept_sums.spikes)
            return float(spikes.sum() / (spikes.shape[0] * self.kept_sums.steps * self.neuron_count))
        if self.spikes_per_step is None:
            return None
        spikes = self._kept(self.spikes_per_step)
        steps = spikes.shape[1]
        return float(spikes.sum() / (spikes.shape[0] * steps * self.neuron_count))

    def final_range(self) -> np.ndarray:
        """Distance of the chaser from where the controller steers it (the target, or the
        scenario's setpoint) at the end, per run, m (NaN for a run that diverged)."""
        aim = np.zeros(3) if self.scenario.setpoint is None else self.scenario.setpoint[:3]
        final = self.kept_sums.final_state if self.truth is None else self.truth[:, -1]
        return np.linalg.norm(final[:, :3] - aim, axis=1)

    def delta_v(self) -> np.ndarray:
        """Velocity change the thrusters delivered, per run, m/s: sum over steps of
        |u_x| + |u_y| + |u_z| times dt (one thruster pair per axis: propellant goes as this;
        NaN for a run that diverged)."""
        if self.control is None:
            return self.kept_sums.delta_v()
        return np.abs(self.control).sum(axis=(1, 2)) * self.scenario.dt

    def consistency(self, seconds: float | None = None) -> dict:
        """Average NEES and NIS over the final window against their 95 % chi-square bounds
        (:func:`consistency_check`); empty for a filter without a covariance."""
        sensor = self.scenario.sensor
        dof = self.scenario.model.n_meas if sensor is None else sensor.dim
        if self._without_trajectories('consistency', seconds):
            if not self.kept_sums.covariance:
                return {}
            nees, nis = self._kept(self.kept_sums.nees), self._kept(self.kept_sums.nis)
        else:
            if self.nees is None:
                return {}
            window = self.window(seconds)
            nees = self._kept(self.nees)[:, window]
            nis = self._kept(self.nis)[:, window.start - 1:window.stop - 1]
        runs = nees.shape[0]
        if sensor is not None:  # steps without a measurement have no NIS (NaN): average the others
            nis = nis[:, np.isfinite(nis).all(axis=0)]
        return {'nees': consistency_check(nees.mean(axis=0), runs, self.scenario.model.n_state),
                'nis': consistency_check(nis.mean(axis=0), runs, dof)}


def consistency_check(per_step: np.ndarray, runs: int, dof: int) -> dict:
    """Judge a filter's covariance from the per-step average over ``runs`` runs of its NEES
    (dof = states) or NIS (dof = measurements): each step's average is compared with
    chi2(runs dof)/runs at 2.5 % and 97.5 % (Bar-Shalom et al., Sec. 5.4). Returns the time
    average, the bounds, the share of steps inside them and a verdict: consistent (>= 90 % of
    steps inside), overconfident (the +-3 sigma the filter publishes is too narrow: mostly
    above) or conservative (mostly below)."""
    per_step = np.asarray(per_step, dtype=float)
    low, high = (scipy.stats.chi2.ppf(q, runs * dof) / runs for q in (0.025, 0.975))
    inside = float(np.mean((per_step >= low) & (per_step <= high)))
    above = float(np.mean(per_step > high))
    verdict = ('consistent' if inside >= 0.9 else
               'overconfident' if above > 0.5 * (1.0 - inside) else 'conservative')
    return {'average': float(per_step.mean()), 'dof': dof, 'bounds': [float(low), float(high)],
            'fraction_inside': inside, 'verdict': verdict}


def normalised_squares(errors: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """e^T P^-1 e per run: ``errors`` (runs, d), ``covariances`` (runs, d, d). A covariance
    that cannot be inverted gives inf (an overconfident filter, not a crash)."""
    try:
        solved = np.linalg.solve(covariances, errors[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return np.full(errors.shape[0], np.inf)
    return np.einsum('bi,bi->b', errors, solved)


def twin_of(kind: str) -> str | None:
    """The non-spiking filter a spiking filter implements (None for a non-spiking kind)."""
    return TWIN_OF.get(kind)


#: Contact conditions are read where the chaser first comes within this range of the target, m
#: (docs/decisions.md, 49).
CONTACT_RANGE = 1.0


def contact_conditions(truth: np.ndarray, within: float = CONTACT_RANGE) -> dict | None:
    """Where one run's truth ``(steps, 6)`` first comes within ``within`` m of the target: the
    step, the closing speed (the velocity toward the target, m/s) and the offset from the docking
    axis (LVLH x, along which the close sensors look back: hypot(y, z), m); None if it never does
    (docs/decisions.md, 49)."""
    truth = np.asarray(truth, dtype=float)
    ranges = np.linalg.norm(truth[:, :3], axis=1)
    inside = np.flatnonzero(ranges < within)
    if not inside.size:
        return None
    k = int(inside[0])
    position, velocity = truth[k, :3], truth[k, 3:6]
    closing = -float(velocity @ position) / ranges[k] if ranges[k] > 0.0 else float(np.linalg.norm(velocity))
    return {'step': k, 'closing_speed_m_s': closing, 'axis_offset_m': float(np.hypot(position[1], position[2]))}

