"""The modified sliding innovation filter gain K = C^+ diag(sat(diag(P^zz) / delta)),
P^zz = C P C^T + R_hat (Eq. 8-9, Eq. 9 corrected; the network's Eq. 21-22)."""

import numpy as np

from . import C_PINV, DELTA, R_HAT_DIAG, C

NAME = 'msif'
ORDER = 1
FORMULA = 'K = C^+ sat(diag(C P C^T + R_hat) / delta)'
EQUATION = 'Eq. 8-9, 21-22'
USES_P = True
USES_KALMAN = False
BASE = None
#: The covariance its filters propagate: riccati (Eq. 6) | gain (that of the gain used) | none.
COVARIANCE = 'riccati'
#: Its filter kinds: the direct filter, then its spiking twin: name -> (label, summary).
KINDS = {'emsif': ('EMSIF', 'extended modified sliding innovation filter as printed (Eq. 8-9)'),
         'snn_emsif': ('SNN-EMSIF', 'SNN-EMSIF (Eq. 21-22)')}


def reference(p, c, innovation, step, r_hat, delta):
    p_zz = c @ p @ c.T + r_hat                                            # Eq. 9 (corrected)
    return np.linalg.pinv(c) @ np.diag(np.minimum(np.diag(p_zz) / delta, 1.0))  # Eq. 8


def steady_state(ss):
    """The MSIF gain at P_ss."""
    innovation_variance = np.diag(ss.c @ ss.p @ ss.c.T + ss.r_hat)
    return ss.c_pinv @ np.diag(np.minimum(innovation_variance / ss.delta, 1.0))


def macs(n: int, m: int) -> int:
    return m * n + n * m                       # diag(C P C^T) (Eq. 9), C^+ sat(.) (Eq. 8)


def gain(b, out, nu, pct, kalman, consts, scratch):
    """C^+ sat(P^zz_jj / delta_j), the saturations kept in scratch[6] for the laws built on it."""
    c, c_pinv, r_hat_diag, delta = consts[C], consts[C_PINV], consts[R_HAT_DIAG], consts[DELTA]
    sats = scratch[6]
    n, m = c_pinv.shape
    for j in range(m):
        pzz = r_hat_diag[j]
        for k in range(n):
            pzz += c[j, k] * pct[k, j]
        ratio = abs(pzz) / delta[j]
        sat = ratio if ratio < 1.0 else 1.0
        sats[j] = sat
        for i in range(n):
            out[b, i, j] = c_pinv[i, j] * sat
