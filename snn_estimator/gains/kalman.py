"""The Kalman gain K = P C^T R^-1 (Eq. 5; the network's Eq. 19-20)."""

import numpy as np

NAME = 'kalman'
ORDER = 0
FORMULA = 'K = P C^T R^-1'
EQUATION = 'Eq. 5, 19-20'
#: The piece reads P C^T and P C^T R^-1.
USES_P = True
BASE = None
#: The covariance its filters propagate: riccati (Eq. 6) | gain (that of the gain used) | none.
COVARIANCE = 'riccati'
#: Its filter kinds: the direct filter, then its spiking twin: name -> (label, summary).
KINDS = {'ekf': ('EKF', 'extended Kalman filter (Eq. 3-6)'), 'snn_ekf': ('SNN-EKF', 'SNN-EKF (Eq. 14-20)')}


def reference(p, c, innovation, density, r_hat, delta):
    """Eq. 5 with R the density of Eq. 5-6."""
    return p @ c.T @ np.linalg.inv(density)


def steady_state(ss):
    """P_ss C^T R^-1."""
    return ss.kalman


def macs(n: int, m: int) -> int:
    """Nothing beyond P C^T R^-1, which every law using P shares."""
    return 0


def gain(b, out, nu, pct, pctr, consts, scratch):
    """K = P C^T R^-1 (already formed as ``pctr``)."""
    n, m = pctr.shape
    for i in range(n):
        for j in range(m):
            out[b, i, j] = pctr[i, j]
