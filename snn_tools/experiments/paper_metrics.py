"""The quantitative claims the paper makes in words, as functions of recorded arrays.

* :func:`transient_metrics`: Fig. 2's claims about the estimation error of a filter started
  away from the truth (Sec. 3.1): when it enters its +-3 sigma bound, when it first crosses
  zero, the overshoot after that crossing, and when it settles.
* :func:`noise_floor`: what the time-averaged |mean error| reading gives for zero-mean noise
  alone, sqrt(2/pi) sigma / sqrt(runs) (E|X| of a Gaussian mean of ``runs`` draws).
"""

from __future__ import annotations

import math

import numpy as np

#: A filter has settled once |e| stays below this fraction of |e(0)| (the paper: "converged to
#: almost zero"; with x_hat0 = [0, 0] against x0 = [2, 2] that is 0.1).
SETTLE_FRACTION = 0.05


def noise_floor(rmse, runs: int):
    """|mean over ``runs`` runs| of zero-mean errors with standard deviation ``rmse``, averaged
    over time: sqrt(2/pi) rmse / sqrt(runs) (0.080 rmse at 100 runs)."""
    return math.sqrt(2.0 / math.pi) / math.sqrt(runs) * np.asarray(rmse, dtype=float)


def transient_metrics(time: np.ndarray, error: np.ndarray, sigma: np.ndarray | None,
                      settle_fraction: float = SETTLE_FRACTION) -> dict:
    """Fig. 2's readings of one run's error e(t) of one state (shape (T,)), with the filter's
    standard deviation sigma(t) (None: no covariance).

    * ``enter_3sigma_s``: first time |e| <= 3 sigma (None if never, or without sigma);
    * ``zero_crossing_s``: first time e changes sign (None if never);
    * ``overshoot``: the largest |e| between the first zero crossing and the next one (or the
      end): how far the error swings past zero (0 without a crossing);
    * ``settle_s``: the first time after which |e| stays below settle_fraction |e(0)|
      (None if it never does).
    """
    time = np.asarray(time, dtype=float)
    error = np.asarray(error, dtype=float)
    out = {'enter_3sigma_s': None, 'zero_crossing_s': None, 'overshoot': 0.0, 'settle_s': None}
    if sigma is not None:
        inside = np.flatnonzero(np.abs(error) <= 3.0 * np.asarray(sigma, dtype=float))
        if inside.size:
            out['enter_3sigma_s'] = float(time[inside[0]])
    signs = np.sign(error)
    flips = np.flatnonzero(signs[1:] * signs[:-1] < 0) + 1
    if flips.size:
        first = flips[0]
        out['zero_crossing_s'] = float(time[first])
        end = flips[1] if flips.size > 1 else error.size
        out['overshoot'] = float(np.abs(error[first:end]).max())
    band = settle_fraction * abs(error[0])
    outside = np.flatnonzero(np.abs(error) > band)
    if outside.size == 0:
        out['settle_s'] = float(time[0])
    elif outside[-1] + 1 < error.size:
        out['settle_s'] = float(time[outside[-1] + 1])
    return out


def median_metrics(result, state: int) -> dict:
    """Medians over the runs of :func:`transient_metrics` for state ``state`` of a
    SimulationResult; a metric missing in a run counts as +inf (reported as None when more than
    half the runs miss it)."""
    sigma = (np.sqrt(np.clip(result.covariance_diag[..., state], 0.0, None))
             if result.covariance_diag is not None else None)
    per_run = [transient_metrics(result.time, result.error[b, :, state],
                                 None if sigma is None else sigma[b])
               for b in range(result.error.shape[0])]
    out = {}
    for name in per_run[0]:
        values = np.array([math.inf if m[name] is None else m[name] for m in per_run])
        median = float(np.median(values))
        out[name] = None if not math.isfinite(median) else round(median, 4)
    return out
