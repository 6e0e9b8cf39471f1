"""A constant gain: the steady-state gain of any law held fixed (``gain_schedule:
steady_state``; constant network weights, what a neuromorphic chip holds)."""

from . import FIXED_GAIN

NAME = 'fixed'
ORDER = 99
FORMULA = 'K = K_ss (the steady state of the law above)'
EQUATION = 'Eq. 6 at its fixed point'
USES_P = False
USES_KALMAN = False
BASE = None
COVARIANCE = 'gain'
KINDS = {}  # a gain schedule of the other laws' kinds, not a kind itself


def reference(p, c, innovation, step, r_hat, delta, constant=None):
    """The constant itself (the steady state of the law it holds)."""
    return constant


def steady_state(ss):
    raise ValueError('the fixed gain is already a steady state: ask the law it holds')


def macs(n: int, m: int) -> int:
    return 0


def gain(b, out, nu, pct, kalman, consts, scratch):
    fixed = consts[FIXED_GAIN]
    n, m = fixed.shape
    for i in range(n):
        for j in range(m):
            out[b, i, j] = fixed[i, j]
