"""The sliding innovation filter gain K = C^+ diag(sat(|z - C x_hat| / delta)) (Eq. 7; the
network's SNN-EMSIF*, Eq. 23-24): no covariance needed."""

import math

import numpy as np

from . import C_PINV, DELTA

NAME = 'sif'
ORDER = 2
FORMULA = 'K = C^+ sat(|z - C x_hat| / delta)'
EQUATION = 'Eq. 7, 23-24'
USES_P = False
USES_KALMAN = False
BASE = None
#: The covariance its filters propagate: riccati (Eq. 6) | gain (that of the gain used) | none.
COVARIANCE = 'none'
#: Its filter kinds: the direct filter, then its spiking twin: name -> (label, summary).
KINDS = {'esif': ('ESIF', 'extended sliding innovation filter (Eq. 7)'),
         'snn_emsif_star': ('SNN-EMSIF*', 'SNN-EMSIF* (Eq. 23-24)')}


def reference(p, c, innovation, step, r_hat, delta):
    return np.linalg.pinv(c) @ np.diag(np.minimum(np.abs(innovation) / delta, 1.0))  # Eq. 7


def steady_state(ss):
    """C^+ diag(E[sat(|nu_j| / delta_j)]), nu ~ N(0, C P_ss C^T + R_hat): the mean of Eq. 7's
    saturation over the innovations the filter expects."""
    import scipy.special
    delta = ss.delta
    sigma = np.sqrt(np.diag(ss.c @ ss.p @ ss.c.T + ss.r_hat))
    inside = 2.0 * sigma / math.sqrt(2.0 * math.pi) * (1.0 - np.exp(-delta ** 2 / (2.0 * sigma ** 2)))
    mean_saturation = inside / delta + scipy.special.erfc(delta / (sigma * math.sqrt(2.0)))
    return ss.c_pinv @ np.diag(mean_saturation)


def macs(n: int, m: int) -> int:
    return n * m                               # C^+ sat(|nu| / delta) (Eq. 7)


def gain(b, out, nu, pct, kalman, consts, scratch):
    c_pinv, delta = consts[C_PINV], consts[DELTA]
    n, m = c_pinv.shape
    for j in range(m):
        ratio = abs(nu[j]) / delta[j]
        sat = ratio if ratio < 1.0 else 1.0
        for i in range(n):
            out[b, i, j] = c_pinv[i, j] * sat
