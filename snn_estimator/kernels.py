"""Compiled per-step kernel (numba) for the filters and the spiking network.

One compiled call advances every run of a batch (leading axis = Monte-Carlo run), so a single
ROS estimator (batch of 1) and a 100-run experiment execute the same code. The network algebra
follows the paper without forming an N x N product per step: ``Omega_s r`` is
``D^T (A + lambda I) (D r)``, ``Omega_k r + F_k z`` is ``D^T K (z - C D r)``, and a spike of
neuron i adds the column ``Omega_f[:, i] = -D^T D_i`` of a precomputed Gram matrix.

The step kernel takes ~35 arrays and codes. They are never passed by position from the
estimator: :class:`StepCall` assembles them by parameter name and checks every shape once,
when the estimator is built, against :data:`STEP_SHAPES` (a swapped pair of same-shaped arrays
would otherwise compile and run).
"""

from __future__ import annotations

import inspect

import numba
import numpy as np

GAIN_KALMAN = 0      # K = P C^T R^-1                               (Eq. 5, 19-20)
GAIN_MSIF = 1        # K = C^+ diag(sat(diag(C P C^T + R) / delta))  (Eq. 8-9 corrected, 21-22)
GAIN_SIF = 2         # K = C^+ diag(sat(|z - C x_hat| / delta))      (Eq. 7, 23-24)
GAIN_MSIF_HYBRID = 3  # MSIF on the measured directions, Kalman on the others:
#                       K = C^+ sat(...) + (I - C^+ C) P C^T R^-1    (not in the paper)
GAIN_FIXED = 4       # a constant K (the steady-state gain of any of the above)
GAIN_MSIF_WEIGHTED = 5  # MSIF with the covariance-weighted right inverse of C instead of C^+:
#                         K = P C^T (C P C^T)^-1 diag(sat(diag(C P C^T + R) / delta))  (not in the paper)

COVARIANCE_NONE = 0     # no P (the SIF gain needs none)
COVARIANCE_RICCATI = 1  # P' = J P + P J^T + Q - P C^T R^-1 C P            (Eq. 6)
COVARIANCE_GAIN = 2     # P' = (J - K C) P + P (J - K C)^T + Q + K R K^T    (any gain K)

RULE_GREEDY = 0        # fire the largest overshoot, reset, repeat until none is above threshold
RULE_ONE_PER_STEP = 1  # at most one spike (the largest overshoot) per step
RULE_ALL_ABOVE = 2     # every neuron above threshold fires once, simultaneously

# Reassociation lets LLVM vectorise the reductions; no-NaN/Inf assumptions stay off so the
# finiteness checks keep working.
_FAST = {'reassoc', 'contract', 'nsz', 'arcp'}

STATUS_OK = 0
STATUS_BAD_INPUT = 1     # non-finite z or u: nothing was changed
STATUS_NON_FINITE = 2    # the state became non-finite: reset before stepping again

#: Shape of every array argument of :func:`estimator_step`, in symbols: runs (batch), n
#: (states), m (measurements), nu (inputs), N (neurons, 0 for a non-spiking filter), d (1, or
#: runs: a linear model shares one dynamics block) and w (2 n + nu: the packed dynamics).
STEP_SHAPES = {
    'c': ('m', 'n'), 'c_pinv': ('n', 'm'), 'q_hat': ('n', 'n'), 'r_density': ('m', 'm'),
    'r_density_inv': ('m', 'm'), 'r_hat_diag': ('m',), 'delta': ('m',), 'scale': ('n',),
    'fixed_gain': ('n', 'm'), 'dynamics': ('d', 'n', 'w'), 'drift': ('d', 'n'), 'z': ('runs', 'm'),
    'u': ('runs', 'nu'), 'noise': ('runs', 'N'), 'x_hat': ('runs', 'n'), 'p': ('runs', 'n', 'n'),
    'gain': ('runs', 'n', 'm'), 'decoder': ('runs', 'n', 'N'), 'gram': ('runs', 'N', 'N'),
    'thresholds': ('runs', 'N'), 'alive': ('runs', 'N'), 'r': ('runs', 'N'), 'v': ('runs', 'N'),
    'spikes': ('runs', 'N'), 'total_spikes': ('runs',),
}


class StepCall:
    """The argument list of :func:`estimator_step`, assembled by parameter name.

    ``StepCall(dims, **arrays_and_codes)`` checks that every parameter is given, none is
    unknown and each array has its :data:`STEP_SHAPES` shape for ``dims`` (ValueError naming the
    argument otherwise). ``call(**changes)`` replaces some arguments (by name) and runs the
    kernel; the arrays the kernel updates in place (x_hat, p, gain, r, v, spikes, ...) are the
    ones given at construction.
    """

    def __init__(self, dims: dict, **values):
        names = tuple(inspect.signature(estimator_step.py_func).parameters)
        missing, unknown = set(names) - set(values), set(values) - set(names)
        if missing or unknown:
            raise ValueError(f'estimator_step arguments: missing {sorted(missing)}, unknown {sorted(unknown)}')
        self._dims = dict(dims)
        for name, value in values.items():
            self._check(name, value)
        self._index = {name: i for i, name in enumerate(names)}
        self._args = [values[name] for name in names]

    def _check(self, name: str, value) -> None:
        shape = STEP_SHAPES.get(name)
        if shape is None:
            return
        dims = dict(self._dims, d=value.shape[0] if np.ndim(value) else 0)
        expected = tuple(dims[symbol] for symbol in shape)
        if np.shape(value) != expected:
            raise ValueError(f'estimator_step argument {name}: shape {np.shape(value)}, expected '
                             f'{expected} ({", ".join(shape)})')
        if name in ('dynamics', 'drift') and value.shape[0] not in (1, self._dims['runs']):
            raise ValueError(f'estimator_step argument {name}: leading axis must be 1 or runs')

    def slot(self, name: str) -> int:
        """Position of argument ``name`` (for :meth:`set_slots` on the hot path)."""
        return self._index[name]

    def update(self, **changes) -> None:
        """Replace arguments by name, shape-checked (settings that change between steps)."""
        for name, value in changes.items():
            self._check(name, value)
            self._args[self._index[name]] = value

    def set_slots(self, values) -> None:
        """Replace arguments by the positions :meth:`slot` gave, without checks: the per-step
        inputs, whose shapes the estimator has already checked."""
        args = self._args
        for index, value in values:
            args[index] = value

    def __call__(self):
        return estimator_step(*self._args)


@numba.njit(cache=True, fastmath=_FAST)
def _fire(b, spike_rule, max_spikes, gram, thresholds, alive, r, v, spikes):
    """Emit the spikes of run b by ``spike_rule``; a spike of i adds 1 to r_i and subtracts
    row i of the Gram matrix D^T D from v (Omega_f, Eq. 18). Returns (spikes, hit the cap)."""
    neurons = v.shape[1]
    best = -1
    best_over = 0.0
    for i in range(neurons):
        if alive[b, i]:
            over = v[b, i] - thresholds[b, i]
            if over > best_over:
                best_over = over
                best = i
    count = 0
    if spike_rule == RULE_ALL_ABOVE:
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
    limit = 1 if spike_rule == RULE_ONE_PER_STEP else max_spikes
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
    return count, spike_rule == RULE_GREEDY and best >= 0


@numba.njit(cache=True, fastmath=_FAST)
def fire_only(spike_rule, max_spikes, decoder, gram, thresholds, alive, r, v, scale, spikes,
              total_spikes, x_hat):
    """The fast time scale alone: let every run spike until its coding error is below
    threshold (used right after neurons are lost), then decode x_hat = S D r."""
    runs, n, neurons = decoder.shape
    emitted = 0
    for b in range(runs):
        for i in range(neurons):
            spikes[b, i] = 0
        count, _ = _fire(b, spike_rule, max_spikes, gram, thresholds, alive, r, v, spikes)
        total_spikes[b] += count
        emitted += count
        for k in range(n):
            acc = 0.0
            for i in range(neurons):
                acc += decoder[b, k, i] * r[b, i]
            x_hat[b, k] = scale[k] * acc
    return emitted


@numba.njit(cache=True, fastmath=_FAST)
def estimator_step(gain_law, covariance_law, spiking, spike_rule, use_given_drift, measured, dt, leak,
                   max_spikes, c, c_pinv, q_hat, r_density, r_density_inv, r_hat_diag, delta, scale,
                   fixed_gain, dynamics, drift, z, u, noise, x_hat, p, gain, decoder, gram, thresholds,
                   alive, r, v, spikes, total_spikes):
    """Advance every run by dt. Returns (status, runs whose spike loop hit max_spikes).

    Per run b, with the estimate x_hat at t_k, z_k and u_k:
      nu = z - C x_hat; K by ``gain_law`` from P, nu or fixed_gain;
      increment = A_d x_hat + B_d u + K nu (or the given nonlinear drift + K nu): Eq. 3;
      P by ``covariance_law`` (forward Euler): Eq. 6, or the covariance of the gain used;
      direct filters:  x_hat += dt increment;
      spiking filters (network on x~ = S^-1 x, Eq. 10-15, forward Euler):
        v = (1 - lambda dt) v + dt D^T (S^-1 increment + lambda D r) + noise,
        r = (1 - lambda dt) r, then spikes by ``spike_rule`` (r_i += 1, v -= D^T D_i),
        x_hat = S D r (Eq. 12).
    R in Eq. 5-6 is ``r_density`` (see config.gain_noise_density); P^zz of Eq. 9 uses the
    per-sample ``r_hat_diag``. ``dynamics[b]`` packs [A_d | B_d | J] (n x (2n + nu)); a leading
    axis of 1 is shared. Without a measurement (``measured`` False: a sensor dropout) K = 0 and
    z is not read.
    """
    runs, n = x_hat.shape
    m = z.shape[1]
    n_u = u.shape[1]
    for b in range(runs):
        for j in range(m):
            if measured and not np.isfinite(z[b, j]):
                return STATUS_BAD_INPUT, 0
        for j in range(n_u):
            if not np.isfinite(u[b, j]):
                return STATUS_BAD_INPUT, 0
    uses_p = (gain_law == GAIN_KALMAN or gain_law == GAIN_MSIF or gain_law == GAIN_MSIF_HYBRID
              or gain_law == GAIN_MSIF_WEIGHTED)
    nu = np.empty(m)
    increment = np.empty(n)
    pct = np.empty((n, m))
    pctr = np.empty((n, m))
    cpctr = np.empty((m, m))
    cpc = np.empty((m, m))
    sats = np.empty(m)
    jp = np.empty((n, n))
    closed = np.empty((n, n))
    drive = np.empty(n)
    input_current = np.empty(decoder.shape[2])
    decay = 1.0 - leak * dt
    capped = 0
    status = STATUS_OK
    for b in range(runs):
        bd = 0 if dynamics.shape[0] == 1 else b
        # innovation
        for j in range(m):
            acc = z[b, j] if measured else 0.0
            if measured:
                for k in range(n):
                    acc -= c[j, k] * x_hat[b, k]
            nu[j] = acc
        # P C^T and P C^T R^-1 (the Kalman gain and Eq. 6's measurement term)
        if uses_p or covariance_law == COVARIANCE_RICCATI:
            for i in range(n):
                for j in range(m):
                    acc = 0.0
                    for k in range(n):
                        acc += p[b, i, k] * c[j, k]
                    pct[i, j] = acc
            for i in range(n):
                for j in range(m):
                    acc = 0.0
                    for k in range(m):
                        acc += pct[i, k] * r_density_inv[k, j]
                    pctr[i, j] = acc
        # gain
        if gain_law == GAIN_KALMAN:
            for i in range(n):
                for j in range(m):
                    gain[b, i, j] = pctr[i, j]
        elif gain_law == GAIN_FIXED:
            for i in range(n):
                for j in range(m):
                    gain[b, i, j] = fixed_gain[i, j]
        else:
            for j in range(m):
                if gain_law == GAIN_SIF:
                    ratio = abs(nu[j]) / delta[j]
                else:
                    pzz = r_hat_diag[j]
                    for k in range(n):
                        pzz += c[j, k] * pct[k, j]
                    ratio = abs(pzz) / delta[j]
                sat = ratio if ratio < 1.0 else 1.0
                sats[j] = sat
                for i in range(n):
                    gain[b, i, j] = c_pinv[i, j] * sat
            if gain_law == GAIN_MSIF_WEIGHTED:  # columns of P C^T (C P C^T)^-1 times sat_j
                for k in range(m):
                    for j in range(m):
                        acc = 0.0
                        for i in range(n):
                            acc += c[k, i] * pct[i, j]
                        cpc[k, j] = acc
                weighted = pct @ np.linalg.inv(cpc)
                for j in range(m):
                    for i in range(n):
                        gain[b, i, j] = weighted[i, j] * sats[j]
            if gain_law == GAIN_MSIF_HYBRID:  # + (I - C^+ C) P C^T R^-1 = pctr - C^+ (C pctr)
                for k in range(m):
                    for j in range(m):
                        acc = 0.0
                        for i in range(n):
                            acc += c[k, i] * pctr[i, j]
                        cpctr[k, j] = acc
                for i in range(n):
                    for j in range(m):
                        acc = pctr[i, j]
                        for k in range(m):
                            acc -= c_pinv[i, k] * cpctr[k, j]
                        gain[b, i, j] += acc
        if not measured:
            for i in range(n):
                for j in range(m):
                    gain[b, i, j] = 0.0
        # right-hand side of Eq. 3
        for i in range(n):
            if use_given_drift:
                acc = drift[b, i]
            else:
                acc = 0.0
                for k in range(n):
                    acc += dynamics[bd, i, k] * x_hat[b, k]
                for k in range(n_u):
                    acc += dynamics[bd, i, n + k] * u[b, k]
            for j in range(m):
                acc += gain[b, i, j] * nu[j]
            increment[i] = acc
        # covariance
        if covariance_law == COVARIANCE_RICCATI:  # Eq. 6
            for i in range(n):
                for j in range(n):
                    acc = 0.0
                    for k in range(n):
                        acc += dynamics[bd, i, n + n_u + k] * p[b, k, j]
                    jp[i, j] = acc
            for i in range(n):
                for j in range(i, n):
                    acc = jp[i, j] + jp[j, i] + q_hat[i, j]
                    if measured:
                        for k in range(m):
                            acc -= pctr[i, k] * pct[j, k]
                    value = p[b, i, j] + dt * acc
                    p[b, i, j] = value
                    p[b, j, i] = value
        elif covariance_law == COVARIANCE_GAIN:  # (J - K C) P + P (J - K C)^T + Q + K R K^T
            for i in range(n):
                for k in range(n):
                    acc = dynamics[bd, i, n + n_u + k]
                    for j in range(m):
                        acc -= gain[b, i, j] * c[j, k]
                    closed[i, k] = acc
            for i in range(n):
                for j in range(n):
                    acc = 0.0
                    for k in range(n):
                        acc += closed[i, k] * p[b, k, j]
                    jp[i, j] = acc
            for i in range(n):
                for j in range(i, n):
                    acc = jp[i, j] + jp[j, i] + q_hat[i, j]
                    for k in range(m):
                        for q in range(m):
                            acc += gain[b, i, k] * r_density[k, q] * gain[b, j, q]
                    value = p[b, i, j] + dt * acc
                    p[b, i, j] = value
                    p[b, j, i] = value
        if not spiking:
            for i in range(n):
                x_hat[b, i] += dt * increment[i]
                if not np.isfinite(x_hat[b, i]):
                    status = STATUS_NON_FINITE
            continue
        # spiking network
        neurons = decoder.shape[2]
        for k in range(n):  # x_hat holds S D r from the end of the previous step
            drive[k] = dt * (increment[k] + leak * x_hat[b, k]) / scale[k]
        for i in range(neurons):
            input_current[i] = noise[b, i]
        for k in range(n):  # D^T drive, row by row so the inner loop is contiguous
            weight = drive[k]
            for i in range(neurons):
                input_current[i] += decoder[b, k, i] * weight
        for i in range(neurons):
            v[b, i] = v[b, i] * decay + input_current[i]
            r[b, i] *= decay
            spikes[b, i] = 0
        count, hit_cap = _fire(b, spike_rule, max_spikes, gram, thresholds, alive, r, v, spikes)
        if hit_cap:
            capped += 1
        total_spikes[b] += count
        for k in range(n):
            acc = 0.0
            for i in range(neurons):
                acc += decoder[b, k, i] * r[b, i]
            value = scale[k] * acc
            x_hat[b, k] = value
            if not np.isfinite(value):
                status = STATUS_NON_FINITE
    return status, capped


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


def warm_up() -> None:
    """Compile (or load from numba's on-disk cache) every kernel with the argument types the
    estimators use, on a throwaway one-state filter: a node calls this at start-up so that its
    first step is not its slowest, and ``make`` calls it at install to fill the cache."""
    n = m = nu = neurons = 1
    zeros = np.zeros
    step = StepCall(
        {'runs': 1, 'n': n, 'm': m, 'nu': nu, 'N': neurons, 'w': 2 * n + nu},
        gain_law=GAIN_KALMAN, covariance_law=COVARIANCE_RICCATI, spiking=True, spike_rule=RULE_GREEDY,
        use_given_drift=False, measured=True, dt=0.1, leak=0.0, max_spikes=10, c=np.ones((m, n)),
        c_pinv=np.ones((n, m)), q_hat=zeros((n, n)), r_density=np.ones((m, m)), r_density_inv=np.ones((m, m)),
        r_hat_diag=np.ones(m), delta=np.ones(m), scale=np.ones(n), fixed_gain=zeros((n, m)),
        dynamics=zeros((1, n, 2 * n + nu)), drift=zeros((1, n)), z=zeros((1, m)), u=zeros((1, nu)),
        noise=zeros((1, neurons)), x_hat=zeros((1, n)), p=np.ones((1, n, n)), gain=zeros((1, n, m)),
        decoder=np.ones((1, n, neurons)), gram=np.ones((1, neurons, neurons)), thresholds=np.ones((1, neurons)),
        alive=np.ones((1, neurons), dtype=np.bool_), r=zeros((1, neurons)), v=zeros((1, neurons)),
        spikes=zeros((1, neurons), dtype=np.int64), total_spikes=zeros(1, dtype=np.int64))
    step()
    fire_only(RULE_GREEDY, 10, np.ones((1, n, neurons)), np.ones((1, neurons, neurons)), np.ones((1, neurons)),
              np.ones((1, neurons), dtype=np.bool_), zeros((1, neurons)), zeros((1, neurons)), np.ones(n),
              zeros((1, neurons), dtype=np.int64), zeros(1, dtype=np.int64), zeros((1, n)))
    innovation_nis(zeros((1, m)), zeros((1, n)), np.ones((m, n)), np.ones((1, n, n)), np.ones((m, m)), True)
