"""Compiled per-step kernel (numba) for the filters and the spiking network.

One compiled call advances every run of a batch (leading axis = Monte-Carlo run), so a single
ROS estimator (batch of 1) and a 100-run experiment execute the same code. The network algebra
follows the paper without forming an N x N product per step: ``Omega_s r`` is
``D^T (A + lambda I) (D r)``, ``Omega_k r + F_k z`` is ``D^T K (z - C D r)``, and a spike of
neuron i adds the column ``Omega_f[:, i] = -D^T D_i`` of a precomputed Gram matrix.

Constant matrices travel packed in one vector (see :func:`pack_constants`) because every array
argument costs ~0.15 us of call overhead, a large share of a ~5 us step.
"""

from __future__ import annotations

import numba
import numpy as np

GAIN_KALMAN = 0      # K = P C^T R^-1                               (Eq. 5, 19-20)
GAIN_MSIF = 1        # K = C^+ diag(sat(diag(C P C^T + R) / delta))  (Eq. 8-9 corrected, 21-22)
GAIN_SIF = 2         # K = C^+ diag(sat(|z - C x_hat| / delta))      (Eq. 7, 23-24)

RULE_GREEDY = 0        # fire the largest overshoot, reset, repeat until none is above threshold
RULE_ONE_PER_STEP = 1  # at most one spike (the largest overshoot) per step
RULE_ALL_ABOVE = 2     # every neuron above threshold fires once, simultaneously

# Reassociation lets LLVM vectorise the reductions; no-NaN/Inf assumptions stay off so the
# finiteness checks keep working.
_FAST = {'reassoc', 'contract', 'nsz', 'arcp'}

STATUS_OK = 0
STATUS_BAD_INPUT = 1     # non-finite z or u: nothing was changed
STATUS_NON_FINITE = 2    # the state became non-finite: reset before stepping again


def pack_constants(c, c_pinv, q_hat, r_hat_inv, r_hat_diag, delta, state_scale) -> np.ndarray:
    """Concatenate the filter's constant matrices in the order the kernel unpacks them."""
    return np.ascontiguousarray(np.concatenate([
        np.ravel(c), np.ravel(c_pinv), np.ravel(q_hat), np.ravel(r_hat_inv),
        np.ravel(r_hat_diag), np.ravel(delta), np.ravel(state_scale)]).astype(np.float64))


@numba.njit(cache=True)
def _unpack(consts, n, m):
    o = 0
    c = consts[o:o + m * n].reshape((m, n))
    o += m * n
    c_pinv = consts[o:o + n * m].reshape((n, m))
    o += n * m
    q_hat = consts[o:o + n * n].reshape((n, n))
    o += n * n
    r_hat_inv = consts[o:o + m * m].reshape((m, m))
    o += m * m
    r_hat_diag = consts[o:o + m]
    o += m
    delta = consts[o:o + m]
    o += m
    scale = consts[o:o + n]
    return c, c_pinv, q_hat, r_hat_inv, r_hat_diag, delta, scale


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
def estimator_step(gain_law, spiking, spike_rule, propagate_p, use_given_drift, measured, dt,
                   leak, max_spikes, consts, dynamics, drift, z, u, x_hat, P, gain, decoder, gram,
                   thresholds, alive, r, v, noise, spikes, total_spikes):
    """Advance every run by dt. Returns (status, runs whose spike loop hit max_spikes).

    Per run b, with the estimate x_hat at t_k, z_k and u_k:
      nu = z - C x_hat; K from P (Kalman, MSIF) or nu (SIF);
      increment = A_d x_hat + B_d u + K nu (or the given nonlinear drift + K nu): Eq. 3;
      P += dt (J P + P J^T + Q - P C^T R^-1 C P)                         : Eq. 6 (Euler);
      direct filters:  x_hat += dt increment;
      spiking filters (network on x~ = S^-1 x, Eq. 10-15, forward Euler):
        v = (1 - lambda dt) v + dt D^T (S^-1 increment + lambda D r) + noise,
        r = (1 - lambda dt) r, then spikes by ``spike_rule`` (r_i += 1, v -= D^T D_i),
        x_hat = S D r (Eq. 12).
    ``dynamics[b]`` packs [A_d | B_d | J] (n x (2n + m_u)); a leading axis of 1 is shared.
    Without a measurement (``measured`` False: a sensor dropout) K = 0 and z is not read.
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
    c, c_pinv, q_hat, r_hat_inv, r_hat_diag, delta, scale = _unpack(consts, n, m)
    nu = np.empty(m)
    increment = np.empty(n)
    pct = np.empty((n, m))
    pctr = np.empty((n, m))
    jp = np.empty((n, n))
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
        # P C^T and P C^T R^-1 (needed by the Kalman gain and the Riccati step)
        if propagate_p:
            for i in range(n):
                for j in range(m):
                    acc = 0.0
                    for k in range(n):
                        acc += P[b, i, k] * c[j, k]
                    pct[i, j] = acc
            for i in range(n):
                for j in range(m):
                    acc = 0.0
                    for k in range(m):
                        acc += pct[i, k] * r_hat_inv[k, j]
                    pctr[i, j] = acc
        # gain
        if gain_law == GAIN_KALMAN:
            for i in range(n):
                for j in range(m):
                    gain[b, i, j] = pctr[i, j]
        else:
            for j in range(m):
                if gain_law == GAIN_MSIF:
                    pzz = r_hat_diag[j]
                    for k in range(n):
                        pzz += c[j, k] * pct[k, j]
                    ratio = abs(pzz) / delta[j]
                else:
                    ratio = abs(nu[j]) / delta[j]
                sat = ratio if ratio < 1.0 else 1.0
                for i in range(n):
                    gain[b, i, j] = c_pinv[i, j] * sat
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
        # covariance, Eq. 6
        if propagate_p:
            for i in range(n):
                for j in range(n):
                    acc = 0.0
                    for k in range(n):
                        acc += dynamics[bd, i, n + n_u + k] * P[b, k, j]
                    jp[i, j] = acc
            for i in range(n):
                for j in range(i, n):
                    acc = jp[i, j] + jp[j, i] + q_hat[i, j]
                    if measured:
                        for k in range(m):
                            acc -= pctr[i, k] * pct[j, k]
                    value = P[b, i, j] + dt * acc
                    P[b, i, j] = value
                    P[b, j, i] = value
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
