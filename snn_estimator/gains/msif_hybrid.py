"""MSIF on the measured directions, Kalman on the others (not in the paper; docs/decisions.md,
16): K = C^+ sat(...) + (I - C^+ C) K_kalman, K_kalman the sampled Kalman gain (Eq. 5; 43)."""

import numpy as np

from . import C_PINV, C, msif, sampled_kalman

NAME = 'msif_hybrid'
ORDER = 3
FORMULA = 'K = C^+ sat(...) + (I - C^+ C) K_kalman'
EQUATION = 'Eq. 5 and 8-9 (not in the paper)'
USES_P = True
USES_KALMAN = True
#: The MSIF piece runs first; this one adds the Kalman rows.
BASE = 'msif'
#: The covariance its filters propagate: riccati (Eq. 6) | gain (that of the gain used) | none.
COVARIANCE = 'gain'
#: Its filter kinds: the direct filter, then its spiking twin: name -> (label, summary).
KINDS = {'emsif_hybrid': ('EMSIF-H', 'EMSIF on the measured states, Kalman gain on the unmeasured ones'),
         'snn_emsif_hybrid': ('SNN-EMSIF-H', 'spiking twin of emsif_hybrid')}


def reference(p, c, innovation, step, r_hat, delta):
    kalman = sampled_kalman(p, c, step)                                    # Eq. 5
    c_pinv = np.linalg.pinv(c)
    p_zz = c @ p @ c.T + r_hat                                             # Eq. 9
    sliding = c_pinv @ np.diag(np.minimum(np.diag(p_zz) / delta, 1.0))     # Eq. 8
    return sliding + (np.eye(c.shape[1]) - c_pinv @ c) @ kalman


def steady_state(ss):
    return msif.steady_state(ss) + (np.eye(ss.c.shape[1]) - ss.c_pinv @ ss.c) @ ss.kalman


def macs(n: int, m: int) -> int:
    return msif.macs(n, m) + 2 * m * m * n     # + (I - C^+ C) P C^T R^-1


def gain(b, out, nu, pct, kalman, consts, scratch):
    """Adds kalman - C^+ (C kalman) to the MSIF gain in ``out``."""
    c, c_pinv = consts[C], consts[C_PINV]
    cpctr = scratch[4]
    n, m = c_pinv.shape
    for k in range(m):
        for j in range(m):
            acc = 0.0
            for i in range(n):
                acc += c[k, i] * kalman[i, j]
            cpctr[k, j] = acc
    for i in range(n):
        for j in range(m):
            acc = kalman[i, j]
            for k in range(m):
                acc -= c_pinv[i, k] * cpctr[k, j]
            out[b, i, j] += acc
