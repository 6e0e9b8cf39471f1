"""The modified sliding innovation filter gain K = C^+ diag(sat(diag(P^zz) / delta)),
P^zz = C P C^T + R_hat (Eq. 8-9, Eq. 9 corrected; the network's Eq. 21-22).

The boundary layer delta is fixed (the paper) or variable (``boundary_layer_mode``,
docs/decisions.md 48): after Gadsden & Habibi's variable boundary layer (JDSMC 135(1), 2013),
delta_j = P^zz_jj dt (C P C^T + R_d)_jj / (C P C^T)_jj each step, so that inside the layer
(P^zz_jj < delta_j) the saturation is (C P C^T)_jj / (C P C^T + R_d)_jj / dt: the gain corrects
by the Kalman gain of the sampled step, K_d = P C^T (C P C^T + R_d)^-1 (decision 43; per
component, exact where C P C^T and R_d are diagonal), C K dt = C K_d for C^+ here and K dt =
K_d for the weighted inverse (msif_weighted.py). Outside the layer it saturates at 1 as Eq. 8
does. The fixed layer's floor R_hat / delta disappears: the gain decays as P does.
"""

import numpy as np

from . import C_PINV, DELTA, LAYER_STEP, R_HAT_DIAG, R_SAMPLE, C

NAME = 'msif'
ORDER = 1
FORMULA = 'K = C^+ sat(diag(C P C^T + R_hat) / delta)'
EQUATION = 'Eq. 8-9, 21-22'
USES_P = True
USES_KALMAN = False
BASE = None
#: Takes boundary_layer_mode variable (module docstring); the other laws ignore it.
VARIABLE_LAYER = True
#: The covariance its filters propagate: riccati (Eq. 6) | gain (that of the gain used) | none.
COVARIANCE = 'riccati'
#: Its filter kinds: the direct filter, then its spiking twin: name -> (label, summary).
KINDS = {'emsif': ('EMSIF', 'extended modified sliding innovation filter as printed (Eq. 8-9)'),
         'snn_emsif': ('SNN-EMSIF', 'SNN-EMSIF (Eq. 21-22)')}


def reference(p, c, innovation, step, r_hat, delta, mode='fixed'):
    return np.linalg.pinv(c) @ np.diag(saturations(p, c, step, r_hat, delta, mode))  # Eq. 8


def saturations(p, c, step, r_hat, delta, mode='fixed'):
    """sat(diag(P^zz) / delta) of Eq. 8, delta fixed or the variable layer (module docstring)."""
    p_zz = np.diag(c @ p @ c.T + r_hat)                                   # Eq. 9 (corrected)
    if mode == 'variable':
        cpc = np.diag(c @ p @ c.T)
        delta = p_zz * step.dt * (cpc + np.diag(step.r_sample)) / cpc      # Gadsden & Habibi's layer
    return np.minimum(p_zz / delta, 1.0)


def steady_state(ss):
    """The MSIF gain at P_ss."""
    innovation_variance = np.diag(ss.c @ ss.p @ ss.c.T + ss.r_hat)
    return ss.c_pinv @ np.diag(np.minimum(innovation_variance / ss.delta, 1.0))


def macs(n: int, m: int) -> int:
    return m * n + n * m                       # diag(C P C^T) (Eq. 9), C^+ sat(.) (Eq. 8)


def gain(b, out, nu, pct, kalman, consts, scratch):
    """C^+ sat(P^zz_jj / delta_j), the saturations kept in scratch[6] for the laws built on it;
    delta_j the variable layer where layer_step[j] (the step dt) is not 0."""
    c, c_pinv, r_hat_diag, delta = consts[C], consts[C_PINV], consts[R_HAT_DIAG], consts[DELTA]
    layer_step, r_sample = consts[LAYER_STEP], consts[R_SAMPLE]
    sats = scratch[6]
    n, m = c_pinv.shape
    for j in range(m):
        pzz = r_hat_diag[j]
        for k in range(n):
            pzz += c[j, k] * pct[k, j]
        if layer_step[j] > 0.0:  # P^zz_jj / delta_j with delta_j = P^zz_jj dt (cpc + R_d,jj) / cpc
            cpc = 0.0
            for k in range(n):
                cpc += c[j, k] * pct[k, j]
            ratio = cpc / ((cpc + r_sample[j, j]) * layer_step[j]) if cpc > 0.0 else 0.0
        else:
            ratio = abs(pzz) / delta[j]
        sat = ratio if ratio < 1.0 else 1.0
        sats[j] = sat
        for i in range(n):
            out[b, i, j] = c_pinv[i, j] * sat
