"""What a filter holds between steps: the estimate, its covariance, the last gain and the
guard's fault flag of every run (the arrays the step kernel writes in place), where each run
starts, and copies of all that to return to."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

#: rng stream id of the dispersed initial estimate
DISPERSION_STREAM = 5


def covariance_or_error(p: np.ndarray, name: str) -> np.ndarray:
    """``p`` (runs, n, n) if every run's is a covariance (finite, symmetric, positive definite),
    else ValueError: the covariance step keeps P positive definite, so it must start so."""
    if not np.isfinite(p).all():
        raise ValueError(f'{name} must be finite')
    if not np.allclose(p, np.swapaxes(p, 1, 2), rtol=1e-9, atol=0.0):
        raise ValueError(f'{name} must be symmetric')
    try:
        np.linalg.cholesky(p)
    except np.linalg.LinAlgError:
        raise ValueError(f'{name} must be positive definite (a covariance)') from None
    return p


class FilterState:
    """x_hat (runs, n), P (runs, n, n), the gain of the last step (runs, n, m) and the fault
    flag of the covariance guard (runs,): written in place, as the kernel's packed arguments and
    the simulator hold these arrays."""

    def __init__(self, runs: int, n: int, m: int):
        self.x_hat = np.zeros((runs, n))
        self.p = np.zeros((runs, n, n))
        self.gain = np.zeros((runs, n, m))
        self.fault = np.zeros(runs, dtype=np.bool_)

    def put(self, runs, x_hat: np.ndarray, p: np.ndarray | None) -> None:
        """Runs ``runs`` (a bool mask or indices) start again at ``x_hat`` with ``p`` (None:
        keep P): no gain yet, no fault."""
        self.x_hat[runs] = x_hat
        if p is not None:
            self.p[runs] = p
        self.gain[runs] = 0.0
        self.fault[runs] = False

    def arrays(self) -> dict:
        return {'x_hat': self.x_hat, 'p': self.p, 'gain': self.gain, 'fault': self.fault}


def initial_states(settings, seeds: Sequence[int]) -> np.ndarray:
    """The configured start of every run, (runs, n): initial_state, or with
    initial_state_dispersion a draw from N(initial_state, P0) seeded by the run's seed (stream
    5), the same on every call and for a run alone or in a batch."""
    x0 = np.broadcast_to(settings.initial_state, (len(seeds), settings.initial_state.size)).copy()
    if settings.initial_state_dispersion:
        root = np.linalg.cholesky(settings.initial_covariance)
        for b, seed in enumerate(seeds):
            x0[b] += root @ np.random.default_rng([seed, DISPERSION_STREAM]).standard_normal(x0.shape[1])
    return x0


@dataclass(frozen=True)
class EstimatorSnapshot:
    """What a step of an Estimator changes, copied (Estimator.snapshot): opaque to callers,
    restored only into the estimator it was taken from."""

    owner: int
    arrays: dict        # name -> copy of a live array (Estimator's state, H, network)
    counters: tuple     # steps, capped_steps, recovery_spikes, covariance_faults
    noise: tuple        # the membrane-noise generators' states
    chip: Any           # ChipNetwork.snapshot() or None
    call_dt: float | None
