"""The Kalman gain K = P C^T R^-1 (Eq. 5; the network's Eq. 19-20), taken as the gain of the
sampled step, Phi P C^T (C P C^T + R_d)^-1 / dt (docs/decisions.md, 43), its limit as dt -> 0."""

from . import sampled_kalman

NAME = 'kalman'
ORDER = 0
FORMULA = 'K = P C^T R^-1'
EQUATION = 'Eq. 5, 19-20'
#: The piece reads P C^T and the sampled Kalman gain.
USES_P = True
USES_KALMAN = True
BASE = None
#: The covariance its filters propagate: riccati (Eq. 6) | gain (that of the gain used) | none.
COVARIANCE = 'riccati'
#: Its filter kinds: the direct filter, then its spiking twin: name -> (label, summary).
KINDS = {'ekf': ('EKF', 'extended Kalman filter (Eq. 3-6)'), 'snn_ekf': ('SNN-EKF', 'SNN-EKF (Eq. 14-20)')}


def reference(p, c, innovation, step, r_hat, delta):
    """Eq. 5 for a sampled step (``step``: gains.SampledStep)."""
    return sampled_kalman(p, c, step)


def steady_state(ss):
    """The sampled Kalman gain at P_ss."""
    return ss.kalman


def macs(n: int, m: int) -> int:
    """Nothing beyond P C^T R^-1, which every law using P shares."""
    return 0


def gain(b, out, nu, pct, kalman, consts, scratch):
    """K, the sampled Kalman gain (already formed as ``kalman`` by the kernel)."""
    n, m = kalman.shape
    for i in range(n):
        for j in range(m):
            out[b, i, j] = kalman[i, j]
