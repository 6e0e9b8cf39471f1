"""Compiled per-step kernels (numba) for the filters and the spiking network.

One compiled call advances every run of a batch (leading axis = Monte-Carlo run), so a single
ROS estimator (batch of 1) and a 100-run experiment execute the same code. The network algebra
follows the paper without forming an N x N product per step: ``Omega_s r`` is
``D^T (A + lambda I) (D r)``, ``Omega_k r + F_k z`` is ``D^T K (z - C D r)``, and a spike of
neuron i adds the column ``Omega_f[:, i] = -D^T D_i`` of a precomputed Gram matrix.

:func:`step_kernel` composes one kernel per (gain law, covariance law, integration, spike rule,
drift): the law's piece comes from its module in :mod:`snn_estimator.gains`, the others are
below; nothing is chosen by a code at run time. Each composition is compiled once and kept in
numba's on-disk cache (under a name carrying a hash of the sources it is made of, so an edited
piece is never served stale). Its arguments are packed (:class:`Packed`): the constants, the
filter state and the network state are tuples built and shape-checked in one place; a step
passes those three and its own seven inputs (``measured`` a bool per run). A single estimator
passes the three tuples as one object (:class:`PackedRef`, :func:`step_kernel` with
``packed=True``): numba unboxes it as one pointer instead of ~23 arrays on every call.
"""

from __future__ import annotations

import hashlib
import inspect
import types
from pathlib import Path

import numba
import numpy as np
from numba.core import types as numba_types
from numba.experimental import structref

from snn_estimator import gains

COVARIANCE_LAWS = ('riccati', 'gain', 'none')  # Eq. 6 | the covariance of the gain used | no P
SPIKE_RULES = ('greedy', 'one_per_step', 'all_above', 'synchronous')

# Reassociation lets LLVM vectorise the reductions; no-NaN/Inf assumptions stay off so the
# finiteness checks keep working.
_FAST = {'reassoc', 'contract', 'nsz', 'arcp'}
_jit = numba.njit(fastmath=_FAST)

STATUS_OK = 0
STATUS_BAD_INPUT = 1     # non-finite z or u: nothing was changed
STATUS_NON_FINITE = 2    # the state became non-finite: reset before stepping again
STATUS_COVARIANCE = 3    # a run's P is not positive definite or its gain not finite (``fault``): reset it

#: The packed arguments, in symbols: runs (batch), n (states), m (measurements), nu (inputs), N
#: (neurons, 0 for a non-spiking filter), d (1, or runs: a linear model shares one dynamics
#: block, a linear measurement one C), w (n + nu: the packed dynamics). Names in the order of
#: each tuple; the constants in the order of gains.PIECE_CONSTANTS (the laws' pieces index
#: them). ``c`` and ``c_pinv`` are the measurement Jacobian H and its pseudo-inverse, one shared
#: (1, m, n) for a linear measurement or one per run, re-linearised by the caller each step
#: (written in place: the tuple is not rebuilt). ``q_step`` is the covariance Q_d the
#: process noise of density Q_hat adds over a step, ``r_sample`` the variance R_d = R / dt of a
#: sample whose noise has the density R of Eq. 5-6 (docs/decisions.md, 43). ``fault`` is True
#: for a run whose last step left P not positive definite or its gain not finite.
_CONSTANT_SHAPES = {'c': ('d', 'm', 'n'), 'c_pinv': ('d', 'n', 'm'), 'q_step': ('n', 'n'), 'r_sample': ('m', 'm'),
                    'r_hat_diag': ('m',), 'delta': ('m',), 'scale': ('n',), 'fixed_gain': ('n', 'm'), 'leak': (),
                    'max_spikes': (), 'layer_step': ('m',), 'ticks': (), 'widening': (), 'refractory': (),
                    'slots': ()}
CONSTANTS = tuple((name, _CONSTANT_SHAPES[name]) for name in gains.PIECE_CONSTANTS)
STATE = (('x_hat', ('runs', 'n')), ('p', ('runs', 'n', 'n')), ('gain', ('runs', 'n', 'm')), ('fault', ('runs',)))
NETWORK = (('decoder', ('runs', 'n', 'N')), ('gram', ('runs', 'N', 'N')), ('thresholds', ('runs', 'N')),
           ('alive', ('runs', 'N')), ('r', ('runs', 'N')), ('v', ('runs', 'N')), ('spikes', ('runs', 'N')),
           ('total_spikes', ('runs',)), ('reference', ('runs', 'n')), ('refractory_left', ('runs', 'N')))
INPUTS = (('dynamics', ('d', 'n', 'w')), ('drift', ('d', 'n')), ('z', ('runs', 'm')), ('u', ('runs', 'nu')),
          ('noise', ('runs', 'N')), ('measured', ('runs',)))
_SCALARS = {'leak': float, 'max_spikes': int, 'ticks': int, 'widening': float, 'refractory': int, 'slots': int}
_DTYPES = {'alive': np.bool_, 'fault': np.bool_, 'spikes': np.int64, 'total_spikes': np.int64, 'measured': np.bool_,
           'refractory_left': np.int64}
#: Arguments whose leading axis is 1 (shared by every run) or runs.
_SHARED_OR_PER_RUN = ('dynamics', 'drift', 'c', 'c_pinv')


@structref.register
class PackedType(numba_types.StructRef):
    """numba's type of :class:`PackedRef`: the three argument tuples of a step kernel."""

    def preprocess_fields(self, fields):
        return tuple((name, numba_types.unliteral(kind)) for name, kind in fields)


class PackedRef(structref.StructRefProxy):
    """The constants, state and network tuples of one filter as one object: a compiled call
    unboxes it as one pointer where the three tuples cost ~1 us per call (their ~23 arrays,
    each checked and wrapped). It holds the same arrays (the kernel writes the filter's)."""

    def __new__(cls, constants: tuple, state: tuple, network: tuple):
        return structref.StructRefProxy.__new__(cls, constants, state, network)


structref.define_proxy(PackedRef, PackedType, ['constants', 'state', 'network'])


#: Constants a step of another dt changes (Estimator.prepare): :meth:`Packed.update` writes them
#: into the packed array (a private copy, made at the start) instead of replacing it, so a filter
#: fed measurements at jittered stamps does not rebuild its :class:`PackedRef` every step.
STEP_CONSTANTS = ('q_step', 'r_sample', 'fixed_gain', 'layer_step')


class Packed:
    """The argument tuples of a step kernel, built by name and shape-checked once.

    ``Packed(dims, **values)`` takes every name of :data:`CONSTANTS`, :data:`STATE` and
    :data:`NETWORK` (ValueError naming a missing, unknown or misshapen one); ``constants``,
    ``state``, ``network`` are the tuples the kernel takes, ``ref`` the three as one
    :class:`PackedRef` (built on first use). The arrays of ``state`` and ``network`` are
    updated in place by the kernel; :meth:`update` writes :data:`STEP_CONSTANTS` in place and
    rebuilds ``constants`` (and ``ref``) for any other.
    """

    def __init__(self, dims: dict, **values):
        names = [name for group in (CONSTANTS, STATE, NETWORK) for name, _ in group]
        missing, unknown = set(names) - set(values), set(values) - set(names)
        if missing or unknown:
            raise ValueError(f'step kernel arguments: missing {sorted(missing)}, unknown {sorted(unknown)}')
        self._dims = dict(dims)
        self._values = {}
        self._ref = None
        self.update(**{name: (np.array(value, copy=True) if name in STEP_CONSTANTS else value)
                       for name, value in values.items()})
        self.state = tuple(self._values[name] for name, _ in STATE)
        self.network = tuple(self._values[name] for name, _ in NETWORK)

    def update(self, **changes) -> None:
        """Set constants by name (settings that change between steps), shape-checked."""
        shapes = dict(CONSTANTS + STATE + NETWORK)
        rebuilt = False
        for name, value in changes.items():
            if name in _SCALARS:
                value = _SCALARS[name](value)
            else:
                self.check(name, value, shapes[name])
            held = self._values.get(name)
            if name in STEP_CONSTANTS and held is not None and held.shape == value.shape:
                held[...] = value
                continue
            self._values[name] = value
            rebuilt = True
        if rebuilt:
            self.constants = tuple(self._values[name] for name, _ in CONSTANTS)
            self._ref = None

    @property
    def ref(self) -> PackedRef:
        """``constants``, ``state`` and ``network`` as one :class:`PackedRef` (the same arrays)."""
        if self._ref is None:
            self._ref = PackedRef(self.constants, self.state, self.network)
        return self._ref

    def check(self, name: str, value, shape) -> None:
        """ValueError unless ``value`` is a C-contiguous array of ``shape`` (symbols of dims)
        with the kernel's dtype."""
        dims = dict(self._dims, d=value.shape[0] if np.ndim(value) else 0)
        expected = tuple(dims[symbol] for symbol in shape)
        if np.shape(value) != expected:
            raise ValueError(f'step kernel argument {name}: shape {np.shape(value)}, expected '
                             f'{expected} ({", ".join(shape)})')
        if name in _SHARED_OR_PER_RUN and value.shape[0] not in (1, self._dims['runs']):
            raise ValueError(f'step kernel argument {name}: leading axis must be 1 or runs')
        if value.dtype != _DTYPES.get(name, np.float64) or not value.flags.c_contiguous:
            raise ValueError(f'step kernel argument {name}: needs a C-contiguous {_DTYPES.get(name, "float64")} array')


# ---------------------------------------------------------------- pieces shared by the laws
@_jit
def _innovation(b, measured, z, c, x_hat, nu):
    """nu = z - C x_hat (0 without a measurement)."""
    n = x_hat.shape[1]
    for j in range(nu.shape[0]):
        acc = z[b, j] if measured else 0.0
        if measured:
            for k in range(n):
                acc -= c[j, k] * x_hat[b, k]
        nu[j] = acc


@_jit
def _p_terms(b, bd, measured, dt, dynamics, p, c, consts, pct, kalman, scratch):
    """P C^T (the laws that read P but not the Kalman gain)."""
    n, m = pct.shape
    for i in range(n):
        for j in range(m):
            acc = 0.0
            for k in range(n):
                acc += p[b, i, k] * c[j, k]
            pct[i, j] = acc


@_jit
def _kalman_terms(b, bd, measured, dt, dynamics, p, c, consts, pct, kalman, scratch):
    """P C^T and the Kalman gain of the sampled step as a rate (docs/decisions.md, 43):
    K = (I / dt + A_d) P C^T (C P C^T + R_d)^-1 = Phi K_d / dt, with K_d the discrete Kalman
    gain of a sample of variance R_d = R / dt; K -> P C^T R^-1 (Eq. 5) as dt -> 0. NaN when
    C P C^T + R_d is not positive definite (the step reports it)."""
    _p_terms(b, bd, measured, dt, dynamics, p, c, consts, pct, kalman, scratch)
    n, m = pct.shape
    if not measured:
        for i in range(n):
            for j in range(m):
                kalman[i, j] = 0.0
        return
    r_sample, factor, k_d = consts[gains.R_SAMPLE], scratch[4], scratch[11]
    for j in range(m):  # C P C^T + R_d = L D L^T: L D below the diagonal, 1 / D on it
        pivot = r_sample[j, j]
        for k in range(n):
            pivot += c[j, k] * pct[k, j]
        for k in range(j):
            pivot -= factor[j, k] * factor[j, k] * factor[k, k]
        if not pivot > 0.0:
            for q in range(n):
                for r in range(m):
                    kalman[q, r] = np.nan
            return
        factor[j, j] = 1.0 / pivot
        for i in range(j + 1, m):
            acc = r_sample[i, j]
            for k in range(n):
                acc += c[i, k] * pct[k, j]
            for k in range(j):
                acc -= factor[i, k] * factor[j, k] * factor[k, k]
            factor[i, j] = acc
    for i in range(n):  # K_d = P C^T (L D L^T)^-1, row by row: forward, scale, back
        for j in range(m):
            acc = pct[i, j]
            for k in range(j):
                acc -= factor[j, k] * factor[k, k] * k_d[i, k]
            k_d[i, j] = acc
        for j in range(m - 1, -1, -1):
            acc = k_d[i, j] * factor[j, j]
            for k in range(j + 1, m):
                acc -= factor[k, j] * factor[j, j] * k_d[i, k]
            k_d[i, j] = acc
    for i in range(n):
        for j in range(m):
            acc = k_d[i, j] / dt
            for k in range(n):
                acc += dynamics[bd, i, k] * k_d[k, j]
            kalman[i, j] = acc


@_jit
def _no_p_terms(b, bd, measured, dt, dynamics, p, c, consts, pct, kalman, scratch):
    """A law and covariance that read no P."""


@_jit
def _linear_increment(b, bd, dynamics, drift, x_hat, u, gain, nu, increment):
    """A_d x_hat + B_d u + K nu (the right-hand side of Eq. 3)."""
    n, n_u, m = x_hat.shape[1], u.shape[1], nu.shape[0]
    for i in range(n):
        acc = 0.0
        for k in range(n):
            acc += dynamics[bd, i, k] * x_hat[b, k]
        for k in range(n_u):
            acc += dynamics[bd, i, n + k] * u[b, k]
        for j in range(m):
            acc += gain[b, i, j] * nu[j]
        increment[i] = acc


@_jit
def _drift_increment(b, bd, dynamics, drift, x_hat, u, gain, nu, increment):
    """The given nonlinear drift + K nu (a direct filter on a nonlinear model)."""
    n, m = x_hat.shape[1], nu.shape[0]
    for i in range(n):
        acc = drift[b, i]
        for j in range(m):
            acc += gain[b, i, j] * nu[j]
        increment[i] = acc


@numba.njit
def _positive_definite(p, b, factor):
    """P of run b is symmetric positive definite: every pivot of its L D L^T factorisation is
    positive and finite (Cholesky's test without square roots). Compiled without fast-math and
    run on the stored P, as _row_finite. ``factor`` holds L D below its diagonal and 1 / D on it."""
    n = p.shape[1]
    for j in range(n):
        pivot = p[b, j, j]
        for k in range(j):
            pivot -= factor[j, k] * factor[j, k] * factor[k, k]
        if not (pivot > 0.0 and np.isfinite(pivot)):
            return False
        factor[j, j] = 1.0 / pivot
        for i in range(j + 1, n):
            acc = p[b, i, j]
            for k in range(j):
                acc -= factor[i, k] * factor[j, k] * factor[k, k]
            factor[i, j] = acc
    return True


@numba.njit
def _gain_finite(gain, b):
    """Every entry of run b's gain finite (no fast-math, as _row_finite)."""
    for i in range(gain.shape[1]):
        for j in range(gain.shape[2]):
            if not np.isfinite(gain[b, i, j]):
                return False
    return True


@_jit
def _joseph(b, bd, measured, dt, dynamics, p, rates, consts, scratch):
    """P <- (Phi - G C) P (Phi - G C)^T + G R_d G^T + Q_d with G = dt ``rates`` (zero without a
    measurement) and Phi = I + dt A_d: the exact covariance of the sampled step
    x <- Phi x + Gamma u + G (z - C x) (Joseph's form, symmetric positive definite by
    construction at any dt; docs/decisions.md, 43). Returns whether P stayed positive definite."""
    c, q_step, r_sample = consts[gains.C], consts[gains.Q_STEP], consts[gains.R_SAMPLE]
    product, closed, weighted = scratch[7], scratch[8], scratch[11]
    n, m = p.shape[1], c.shape[0]
    for i in range(n):  # Phi - G C, with G = dt rates
        for k in range(n):
            closed[i, k] = dt * dynamics[bd, i, k]
        closed[i, i] += 1.0
        if measured:
            for j in range(m):
                weight = dt * rates[i, j]
                for k in range(n):
                    closed[i, k] -= weight * c[j, k]
    for i in range(n):  # (Phi - G C) P, row by row so the inner loop is contiguous
        for j in range(n):
            product[i, j] = 0.0
        for k in range(n):
            weight = closed[i, k]
            for j in range(n):
                product[i, j] += weight * p[b, k, j]
    if measured:
        for i in range(n):
            for j in range(m):
                acc = 0.0
                for k in range(m):
                    acc += rates[i, k] * r_sample[k, j]
                weighted[i, j] = dt * dt * acc
    for i in range(n):
        for j in range(i, n):
            acc = q_step[i, j]
            for k in range(n):
                acc += product[i, k] * closed[j, k]
            if measured:
                for k in range(m):
                    acc += weighted[i, k] * rates[j, k]
            p[b, i, j] = acc
            p[b, j, i] = acc
    return _positive_definite(p, b, product)


@_jit
def _riccati(b, bd, measured, dt, dynamics, p, gain, consts, pct, kalman, scratch):
    """Eq. 6 as a sampled step: the covariance of the Kalman gain (whatever gain the state
    takes; Decision 3), in Joseph's form."""
    return _joseph(b, bd, measured, dt, dynamics, p, kalman, consts, scratch)


@_jit
def _gain_covariance(b, bd, measured, dt, dynamics, p, gain, consts, pct, kalman, scratch):
    """The covariance of the gain K the state takes, in Joseph's form."""
    return _joseph(b, bd, measured, dt, dynamics, p, gain[b], consts, scratch)


@_jit
def _no_covariance(b, bd, measured, dt, dynamics, p, gain, consts, pct, kalman, scratch):
    """The SIF gain needs no P."""
    return True


# ---------------------------------------------------------------- spike rules (Eq. 18)
@_jit
def _largest_overshoot(b, thresholds, alive, v):
    best = -1
    best_over = 0.0
    for i in range(v.shape[1]):
        if alive[b, i]:
            over = v[b, i] - thresholds[b, i]
            if over > best_over:
                best_over = over
                best = i
    return best


@_jit
def _fire_in_turn(b, limit, gram, thresholds, alive, r, v, spikes):
    """Fire the largest overshoot, subtract its Gram row, repeat (at most ``limit`` spikes).
    Returns (spikes, another neuron is still above threshold)."""
    neurons = v.shape[1]
    best = _largest_overshoot(b, thresholds, alive, v)
    count = 0
    while best >= 0 and count < limit:
        fired = best
        r[b, fired] += 1.0
        spikes[b, fired] += 1
        count += 1
        best = -1
        best_over = 0.0
        for j in range(neurons):
            value = v[b, j] - gram[b, fired, j]
            v[b, j] = value
            if alive[b, j]:
                over = value - thresholds[b, j]
                if over > best_over:
                    best_over = over
                    best = j
    return count, best >= 0


@_jit
def _fire_greedy(b, max_spikes, gram, thresholds, alive, r, v, spikes):
    """Largest overshoot first until none is above threshold (cap max_spikes). Returns
    (spikes, hit the cap)."""
    return _fire_in_turn(b, max_spikes, gram, thresholds, alive, r, v, spikes)


@_jit
def _fire_one_per_step(b, max_spikes, gram, thresholds, alive, r, v, spikes):
    """At most one spike (the largest overshoot) per step."""
    count, _ = _fire_in_turn(b, 1, gram, thresholds, alive, r, v, spikes)
    return count, False


@_jit
def _fire_all_above(b, max_spikes, gram, thresholds, alive, r, v, spikes):
    """Every neuron above threshold fires once, simultaneously."""
    neurons = v.shape[1]
    count = 0
    for i in range(neurons):
        if alive[b, i] and v[b, i] > thresholds[b, i]:
            spikes[b, i] += 1
            count += 1
    if count > 0:
        for i in range(neurons):
            if spikes[b, i]:
                r[b, i] += 1.0
                for j in range(neurons):
                    v[b, j] -= gram[b, i, j]
    return count, False


#: How each rule fires in a step. The synchronous rule steps in its own template
#: (:func:`_synchronous_template`, ticks inside the step); its entry here serves the fire-only
#: kernel (the network settling right after neurons are lost): one tick, every neuron above its
#: threshold at once, no global comparison either.
_FIRE = {'greedy': _fire_greedy, 'one_per_step': _fire_one_per_step, 'all_above': _fire_all_above,
         'synchronous': _fire_all_above}


# ---------------------------------------------------------------- integration
@numba.njit
def _row_finite(x_hat, b):
    """Every x_hat[b, :] finite. Compiled without fast-math and run on the stored row: with the
    _FAST flags an isfinite right after the arithmetic that made the value is folded to True
    (numba 0.68), and a NaN estimate went unreported."""
    for i in range(x_hat.shape[1]):
        if not np.isfinite(x_hat[b, i]):
            return False
    return True


@_jit
def _direct(b, dt, increment, noise, consts, state, network, scratch):
    """x_hat += dt increment. Returns (finite, spikes, capped)."""
    x_hat = state[0]
    for i in range(x_hat.shape[1]):
        x_hat[b, i] += dt * increment[i]
    return _row_finite(x_hat, b), 0, False


# ---------------------------------------------------------------- network codings
@_jit
def _state_drive(b, dt, increment, leak, scale, x_hat, reference, gain, nu, drive):
    """The paper's coding: the network holds x~ = S^-1 x_hat (Eq. 12), drive = dt S^-1
    (increment + lambda x_hat) (Eq. 14)."""
    for k in range(x_hat.shape[1]):  # x_hat holds S D r from the end of the previous step
        drive[k] = dt * (increment[k] + leak * x_hat[b, k]) / scale[k]


@_jit
def _state_decode(b, k, acc, scale, reference):
    """x_hat = S D r (Eq. 12)."""
    return scale[k] * acc


@_jit
def _deviation_drive(b, dt, increment, leak, scale, x_hat, reference, gain, nu, drive):
    """The deviation coding (docs/decisions.md, 13b): the network holds e~ = S^-1 (x_hat - x_pred),
    drive = dt S^-1 (K nu + lambda e); the prediction x_pred advances off the network by the
    rest of the increment, dt (A_d x_hat + B_d u) (or the drift f)."""
    m = nu.shape[0]
    for k in range(x_hat.shape[1]):
        correction = 0.0
        for j in range(m):
            correction += gain[b, k, j] * nu[j]
        deviation = x_hat[b, k] - reference[b, k]
        drive[k] = dt * (correction + leak * deviation) / scale[k]
        reference[b, k] += dt * (increment[k] - correction)


@_jit
def _deviation_decode(b, k, acc, scale, reference):
    """x_hat = x_pred + S D r."""
    return reference[b, k] + scale[k] * acc


_CODING = {'state': (_state_drive, _state_decode), 'deviation': (_deviation_drive, _deviation_decode)}


@_jit
def _input_current(b, drive, noise, decoder, out):
    """A step's input to every neuron: D^T drive + the step's membrane noise."""
    for i in range(out.shape[0]):
        out[i] = noise[b, i]
    for k in range(decoder.shape[1]):  # row by row so the inner loop is contiguous
        weight = drive[k]
        for i in range(out.shape[0]):
            out[i] += decoder[b, k, i] * weight


def _read_out_template(b, decoder, r, scale, reference, x_hat):
    """x_hat = S D r (Eq. 12), through the coding's ``_decode`` (plus x_pred for the deviation):
    the read-out every spike rule ends with."""
    for k in range(decoder.shape[1]):
        acc = 0.0
        for i in range(decoder.shape[2]):
            acc += decoder[b, k, i] * r[b, i]
        x_hat[b, k] = _decode(b, k, acc, scale, reference)


def _spiking_template(b, dt, increment, noise, consts, state, network, scratch):
    """The network on x~ = S^-1 x (Eq. 10-15, forward Euler), or on the deviation from the
    prediction (network_coding, the ``_drive`` and ``_decode`` pieces):
    v = (1 - lambda dt) v + D^T drive + noise, r = (1 - lambda dt) r, then spikes by the rule
    (r_i += 1, v -= D^T D_i), x_hat = S D r (Eq. 12; plus x_pred for the deviation)."""
    scale, leak, max_spikes = consts[gains.SCALE], consts[gains.LEAK], consts[gains.MAX_SPIKES]
    x_hat, gain = state[0], state[2]
    decoder, gram, thresholds, alive, r, v, spikes, total_spikes, reference = network[:9]
    drive, input_current = scratch[9], scratch[10]
    neurons = decoder.shape[2]
    decay = 1.0 - leak * dt
    _drive(b, dt, increment, leak, scale, x_hat, reference, gain, scratch[0], drive)
    _input_current(b, drive, noise, decoder, input_current)
    for i in range(neurons):
        v[b, i] = v[b, i] * decay + input_current[i]
        r[b, i] *= decay
        spikes[b, i] = 0
    count, hit_cap = _fire(b, max_spikes, gram, thresholds, alive, r, v, spikes)
    total_spikes[b] += count
    _read_out(b, decoder, r, scale, reference, x_hat)
    return _row_finite(x_hat, b), count, hit_cap


def _synchronous_template(b, dt, increment, noise, consts, state, network, scratch):
    """The local, synchronous rule (spike_rule synchronous; docs/decisions.md, 58): the step is
    T = ``ticks`` chip ticks. The step's input D^T drive + noise (as :func:`_spiking_template`)
    is spread evenly over them; each tick every neuron leaks by (1 - lambda dt)^(1/T) (r too)
    and integrates 1/T of it, then every live neuron fires whose potential exceeds its own
    threshold (1 + w) T_i, unless it fired within the last ``refractory`` ticks or the tick t
    (0..T-1 in the step) is not its slot ((t + i) mod K = 0, K = ``slots``). Nothing compares
    neurons. After the tick, each spike adds its Omega_f column (v -= D^T D_i: the lateral
    effects and its own reset by subtraction of ||D_i||^2) and r_i += 1. At most ``max_spikes``
    spikes per step: beyond, a tick's later neurons (by index) do not fire and the cap is
    reported. x_hat = S D r (Eq. 12) at the end of the step. Returns (finite, spikes, capped)."""
    scale, leak, max_spikes = consts[gains.SCALE], consts[gains.LEAK], consts[gains.MAX_SPIKES]
    ticks, widening = consts[gains.TICKS], consts[gains.WIDENING]
    refractory, slots = consts[gains.REFRACTORY], consts[gains.SLOTS]
    x_hat, gain = state[0], state[2]
    decoder, gram, thresholds, alive, r, v, spikes, total_spikes, reference, refractory_left = network
    drive, input_current = scratch[9], scratch[10]
    neurons = decoder.shape[2]
    decay = (1.0 - leak * dt) ** (1.0 / ticks)
    share = 1.0 / ticks
    widened = 1.0 + widening
    _drive(b, dt, increment, leak, scale, x_hat, reference, gain, scratch[0], drive)
    _input_current(b, drive, noise, decoder, input_current)
    for i in range(neurons):
        spikes[b, i] = 0
    fired = np.zeros(neurons, dtype=np.bool_)
    count = 0
    hit_cap = False
    for tick in range(ticks):
        fired_any = False
        for i in range(neurons):
            value = v[b, i] * decay + input_current[i] * share
            v[b, i] = value
            r[b, i] *= decay
            fire = (alive[b, i] and refractory_left[b, i] == 0 and (tick + i) % slots == 0
                    and value > widened * thresholds[b, i])
            if fire and count >= max_spikes:
                fire = False
                hit_cap = True
            if fire:
                count += 1
                fired_any = True
                refractory_left[b, i] = refractory
            elif refractory_left[b, i] > 0:
                refractory_left[b, i] -= 1
            fired[i] = fire
        if fired_any:
            for i in range(neurons):
                if fired[i]:
                    r[b, i] += 1.0
                    spikes[b, i] += 1
                    for j in range(neurons):
                        v[b, j] -= gram[b, i, j]
    total_spikes[b] += count
    _read_out(b, decoder, r, scale, reference, x_hat)
    return _row_finite(x_hat, b), count, hit_cap


# ---------------------------------------------------------------- the step
#: The pieces the templates below call, given by :func:`_specialise` as their globals (the
#: templates are never compiled as written).
_terms = _gain = _increment = _covariance = _integrate = _fire = _drive = _decode = _read_out = _step = None


def _step_template(consts, state, network, measured, dt, dynamics, drift, z, u, noise):
    """Advance every run by dt. Returns (status, runs whose spike loop hit max_spikes).

    Per run b, with x_hat at t_k, z_k and u_k: nu = z - C x_hat; K by the law's piece (a rate:
    Phi K_d / dt for the Kalman law); increment = A_d x_hat + B_d u + K nu (or the nonlinear
    drift + K nu): Eq. 3; P by the covariance piece (the sampled step in Joseph's form,
    docs/decisions.md, 43); then x_hat += dt increment, directly or by the network. R_d =
    ``r_sample`` is a sample's variance; P^zz of Eq. 9 uses ``r_hat_diag``. ``dynamics[b]``
    packs [A_d | B_d] (Phi = I + dt A_d), C and C^+ are H(x_hat) and its pseudo-inverse; a
    leading axis of 1 is shared. A nonlinear h arrives as the linear measurement residual(z,
    h(x_hat)) + H x_hat, so nu is the wrapped residual (Eq. 3-4) and F_k z + Omega_k r =
    D^T K nu (Eq. 14). A run not ``measured`` has K = 0 and its z is not read. A run whose P is
    not positive definite after the step, or whose gain is not finite, is marked in ``fault``
    (STATUS_COVARIANCE, the cause, takes precedence over a non-finite state, STATUS_NON_FINITE).
    """
    c_all, c_pinv_all = consts[gains.C], consts[gains.C_PINV]
    x_hat, p, gain, fault = state
    runs, n = x_hat.shape
    m = z.shape[1]
    for b in range(runs):
        for j in range(m):
            if measured[b] and not np.isfinite(z[b, j]):
                return STATUS_BAD_INPUT, 0
        for j in range(u.shape[1]):
            if not np.isfinite(u[b, j]):
                return STATUS_BAD_INPUT, 0
    nu = np.empty(m)
    increment = np.empty(n)
    pct = np.empty((n, m))
    kalman = np.empty((n, m))
    scratch = (nu, increment, pct, kalman, np.empty((m, m)), np.empty((m, m)), np.empty(m), np.empty((n, n)),
               np.empty((n, n)), np.empty(n), np.empty(network[0].shape[2]), np.empty((n, m)))
    capped = 0
    status = STATUS_OK
    for b in range(runs):
        bd = 0 if dynamics.shape[0] == 1 else b
        bc = 0 if c_all.shape[0] == 1 else b
        c = c_all[bc]
        run_consts = (c, c_pinv_all[bc]) + consts[2:]
        measured_b = measured[b]
        _innovation(b, measured_b, z, c, x_hat, nu)
        _terms(b, bd, measured_b, dt, dynamics, p, c, run_consts, pct, kalman, scratch)
        _gain(b, gain, nu, pct, kalman, run_consts, scratch)
        if not measured_b:
            for i in range(n):
                for j in range(m):
                    gain[b, i, j] = 0.0
        _increment(b, bd, dynamics, drift, x_hat, u, gain, nu, increment)
        healthy = _covariance(b, bd, measured_b, dt, dynamics, p, gain, run_consts, pct, kalman, scratch)
        fault[b] = not (healthy and _gain_finite(gain, b))
        finite, _, hit_cap = _integrate(b, dt, increment, noise, run_consts, state, network, scratch)
        if hit_cap:
            capped += 1
        if fault[b]:
            status = STATUS_COVARIANCE
        elif not finite and status == STATUS_OK:
            status = STATUS_NON_FINITE
    return status, capped


def _packed_template(packed, measured, dt, dynamics, drift, z, u, noise):
    """The step kernel ``_step`` called with a :class:`PackedRef` for its three tuples."""
    return _step(packed.constants, packed.state, packed.network, measured, dt, dynamics, drift, z, u, noise)


def _fire_only_template(max_spikes, network, scale, x_hat):
    """The fast time scale alone: let every run spike until its coding error is below
    threshold (used right after neurons are lost), then decode x_hat = S D r (plus the
    prediction ``reference`` for the deviation coding). ``network``: the :data:`NETWORK` tuple."""
    decoder, gram, thresholds, alive, r, v, spikes, total_spikes, reference = network[:9]
    runs, n, neurons = decoder.shape
    emitted = 0
    for b in range(runs):
        for i in range(neurons):
            spikes[b, i] = 0
        count, _ = _fire(b, max_spikes, gram, thresholds, alive, r, v, spikes)
        total_spikes[b] += count
        emitted += count
        _read_out(b, decoder, r, scale, reference, x_hat)
    return emitted


def _sources_digest() -> str:
    """A hash of every source a composed kernel is made of: this file and the files of the laws'
    compiled pieces, whole, so that a helper a gain calls counts too (numba's cache checks only
    the file of the function it caches)."""
    digest = hashlib.sha256(Path(__file__).read_bytes() + Path(gains.__file__).read_bytes())
    for law in gains.laws().values():
        digest.update(Path(inspect.getsourcefile(law.gain)).read_bytes())
    return digest.hexdigest()[:12]


#: A hash of the sources every composed kernel is made of (the name it is cached under carries it).
DIGEST = _sources_digest()
_KERNELS: dict = {}


def _specialise(template, name: str, **pieces):
    """``template`` compiled with ``pieces`` as its globals, cached on disk as ``name``: a
    module-level function for numba's cache (a closure would compile in every process)."""
    key = (template.__name__, name)
    kernel = _KERNELS.get(key)
    if kernel is None:
        function = types.FunctionType(template.__code__, {**globals(), **pieces}, template.__name__)
        function.__qualname__ = f'{name}_{DIGEST}'
        function.__doc__ = template.__doc__
        kernel = _KERNELS[key] = numba.njit(cache=True, fastmath=_FAST)(function)
    return kernel


def _law_piece(law: str):
    """The compiled gain piece of ``law`` (after its base law's piece, if it builds on one)."""
    module = gains.law(law)
    own = _jit(module.gain)
    if module.BASE is None:
        return own
    base = _law_piece(module.BASE)

    @_jit
    def chained(b, out, nu, pct, kalman, consts, scratch):
        base(b, out, nu, pct, kalman, consts, scratch)
        own(b, out, nu, pct, kalman, consts, scratch)
    return chained


def step_kernel(law: str, covariance: str, spiking: bool, spike_rule: str = 'greedy', drift: bool = False,
                coding: str = 'state', packed: bool = False):
    """The step kernel of one combination: gain ``law`` (a module of snn_estimator.gains),
    ``covariance`` (riccati | gain | none), network or direct integration (``spike_rule`` only
    matters for a network), and whether the filter integrates a given nonlinear ``drift`` (a
    direct filter on a nonlinear model, or a network with network_drive: nonlinear), and what a
    network codes (``coding``: state, the paper's; deviation, x_hat - x_pred).
    Called as ``kernel(constants, state, network, measured, dt, dynamics, drift, z, u, noise)``,
    ``measured`` a bool per run; with ``packed`` as ``kernel(ref, measured, dt, ...)``, ``ref``
    a :class:`PackedRef` of the three tuples (the same kernel inside)."""
    if packed:
        kernel = step_kernel(law, covariance, spiking, spike_rule, drift, coding)
        name = kernel.py_func.__qualname__.rsplit('_', 1)[0]  # step_<law>_... without the digest
        return _specialise(_packed_template, f'packed_{name}', _step=kernel)
    if covariance not in COVARIANCE_LAWS:
        raise ValueError(f'unknown covariance law {covariance!r}; choose one of {", ".join(COVARIANCE_LAWS)}')
    if spike_rule not in _FIRE:
        raise ValueError(f'unknown spike rule {spike_rule!r}; choose one of {", ".join(_FIRE)}')
    if coding not in _CODING:
        raise ValueError(f'unknown network coding {coding!r}; choose one of {", ".join(_CODING)}')
    module = gains.law(law)
    tag = '' if coding == 'state' else f'_{coding}'
    mode = (f'spiking_{spike_rule}{tag}' + ('_drift' if drift else '')) if spiking else ('drift' if drift else 'linear')
    name = f'step_{law}_{covariance}_{mode}'
    if (_step_template.__name__, name) in _KERNELS:
        return _KERNELS[(_step_template.__name__, name)]
    drive, decode = _CODING[coding]
    template = _synchronous_template if spike_rule == 'synchronous' else _spiking_template
    integrate = (_specialise(template, f'network_{spike_rule}{tag}', _fire=_FIRE[spike_rule], _drive=drive,
                             _read_out=_read_out(coding)) if spiking else _direct)
    terms = (_kalman_terms if module.USES_KALMAN or covariance == 'riccati' else
             _p_terms if module.USES_P else _no_p_terms)
    return _specialise(
        _step_template, name, _terms=terms, _gain=_law_piece(law),
        _increment=_drift_increment if drift else _linear_increment,
        _covariance={'riccati': _riccati, 'gain': _gain_covariance, 'none': _no_covariance}[covariance],
        _integrate=integrate)


def entry_point(kernel, args: tuple):
    """The compiled entry point of ``kernel`` for the types of ``args`` (after a call with them),
    or ``kernel`` itself if there is none. Calling it skips numba's per-call dispatch, which
    resolves the type of each of the ~30 arrays in the step kernel's packed tuples on every call
    (~3 us of an ~11 us SNN-EMSIF step, docs/performance.md). The entry point does not check
    types (a non-contiguous or integer array would be read wrongly), so a caller must pass the
    same types on every call: :meth:`snn_estimator.filters.estimators.Estimator.step` builds
    them (C-contiguous float64 z and u, the Packed tuples, a float dt, a bool array per run)."""
    overloads = getattr(kernel, 'overloads', None)  # none under NUMBA_DISABLE_JIT=1 (debugging)
    compiled = overloads.get(tuple(numba.typeof(a) for a in args)) if overloads is not None else None
    return compiled.entry_point if compiled is not None else kernel


def compile_for(kernel, *args) -> None:
    """Compile ``kernel`` for the types of ``args`` (or load it from the cache), without a call."""
    kernel.compile(tuple(numba.typeof(a) for a in args))


def fire_kernel(spike_rule: str, coding: str = 'state'):
    """``kernel(max_spikes, network, scale, x_hat)`` (``network`` the :data:`NETWORK` tuple): the
    spikes of ``spike_rule`` alone (see _fire_only_template)."""
    tag = '' if coding == 'state' else f'_{coding}'
    return _specialise(_fire_only_template, f'fire_only_{spike_rule}{tag}', _fire=_FIRE[spike_rule],
                       _read_out=_read_out(coding))


def _read_out(coding: str):
    """The compiled read-out of ``coding`` (x_hat from the rates, Eq. 12)."""
    return _specialise(_read_out_template, f'read_out_{coding}', _decode=_CODING[coding][1])


@numba.njit(cache=True)
def innovation_nis(z, x_hat, c, p, r, has_covariance):
    """Normalised innovation squared ``nu^T S^-1 nu`` per run, ``nu = z - C x_hat``,
    ``S = C P C^T + R`` (``S = R`` without a covariance). Compiled: the ROS estimator checks it
    every step, and the batched numpy version cost twice the filter step itself."""
    out = np.empty(z.shape[0])
    for b in range(z.shape[0]):
        nu = z[b] - c @ x_hat[b]
        s = c @ p[b] @ c.T + r if has_covariance else r
        out[b] = nu @ np.linalg.solve(s, nu)
    return out
