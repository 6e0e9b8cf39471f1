"""MSIF with the covariance-weighted right inverse of C instead of C^+ (not in the paper):
K = P C^T (C P C^T)^-1 diag(sat(diag(C P C^T + R_hat) / delta)).

(C P C^T)^-1 is the inverse, or the pseudo-inverse where C P C^T is singular (the determinant
of its correlation matrix below SINGULAR_CORRELATION): fused sensors that measure the same angles
(a camera and a LIDAR, measurements.stacked) make rows of C dependent, and a sensor absent this
step makes its rows zero; the pseudo-inverse is then the weighted inverse on the rows that carry
information. One sensor always takes the inverse (its numbers unchanged to the bit)."""

import numpy as np

from . import C, msif

NAME = 'msif_weighted'
ORDER = 4
FORMULA = 'K = P C^T (C P C^T)^-1 sat(...)'
EQUATION = 'Eq. 8-9 (not in the paper)'
USES_P = True
USES_KALMAN = False
#: The MSIF piece runs first (its saturations); this one replaces C^+ by P C^T (C P C^T)^-1.
BASE = 'msif'
#: Takes boundary_layer_mode variable through the MSIF piece's saturations (msif.py).
VARIABLE_LAYER = True
#: The covariance its filters propagate: riccati (Eq. 6) | gain (that of the gain used) | none.
COVARIANCE = 'gain'
#: Its filter kinds: the direct filter, then its spiking twin: name -> (label, summary).
KINDS = {'emsif_weighted': ('EMSIF-W', 'EMSIF with the covariance-weighted inverse P C^T (C P C^T)^-1 for C^+'),
         'snn_emsif_weighted': ('SNN-EMSIF-W', 'spiking twin of emsif_weighted')}


#: det(C P C^T) / prod(diag(C P C^T)) (the determinant of its correlation matrix, 1 for
#: independent rows, 0 for dependent ones) at or below which the pseudo-inverse is taken.
SINGULAR_CORRELATION = 1e-12


def _inverse(cpc):
    """The inverse of C P C^T, or its pseudo-inverse where it is singular (module docstring)."""
    diagonal = np.prod(np.diag(cpc))
    if diagonal <= 0.0 or abs(np.linalg.det(cpc)) <= SINGULAR_CORRELATION * diagonal:
        return np.linalg.pinv(cpc)
    return np.linalg.inv(cpc)


def reference(p, c, innovation, step, r_hat, delta, mode='fixed'):
    saturation = np.diag(msif.saturations(p, c, step, r_hat, delta, mode))  # Eq. 8-9, delta fixed or variable
    return p @ c.T @ _inverse(c @ p @ c.T) @ saturation


def steady_state(ss):
    saturation = np.diag(np.minimum(np.diag(ss.c @ ss.p @ ss.c.T + ss.r_hat) / ss.delta, 1.0))
    return ss.p @ ss.c.T @ _inverse(ss.c @ ss.p @ ss.c.T) @ saturation


def macs(n: int, m: int) -> int:
    return msif.macs(n, m) + 2 * m * m * n + m ** 3 + n * m  # P C^T (C P C^T)^-1


def gain(b, out, nu, pct, kalman, consts, scratch):
    """Columns of P C^T (C P C^T)^-1 times the MSIF saturations."""
    c = consts[C]
    sats, cpc = scratch[6], scratch[5]
    n, m = pct.shape
    for k in range(m):
        for j in range(m):
            acc = 0.0
            for i in range(n):
                acc += c[k, i] * pct[i, j]
            cpc[k, j] = acc
    if not np.isfinite(cpc).all():  # a run whose P overflowed: a NaN gain (the step reports it), no exception
        for j in range(m):
            for i in range(n):
                out[b, i, j] = np.nan
        return
    diagonal = 1.0  # the inverse, or the pseudo-inverse where C P C^T is singular (_inverse)
    for k in range(m):
        diagonal *= cpc[k, k]
    if diagonal <= 0.0 or abs(np.linalg.det(cpc)) <= 1e-12 * diagonal:  # SINGULAR_CORRELATION
        weighted = pct @ np.linalg.pinv(cpc)
    else:
        weighted = pct @ np.linalg.inv(cpc)
    for j in range(m):
        for i in range(n):
            out[b, i, j] = weighted[i, j] * sats[j]
