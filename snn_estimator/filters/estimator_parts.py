"""The state-setting and measurement parts of :class:`snn_estimator.filters.estimators.Estimator`.

Mixins of that one class, split from it for size: they share its arrays (estimates, covariances,
the network, the kernel's packed constants) and are not used on their own.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from . import kernels

#: rng stream id of the dispersed initial estimate
DISPERSION_STREAM = 5


@dataclass(frozen=True)
class EstimatorSnapshot:
    """What a step of an Estimator changes, copied (:meth:`EstimatorState.snapshot`): opaque to
    callers, restored only into the estimator it was taken from."""

    owner: int
    arrays: dict        # name -> copy of the live array (EstimatorState._live_arrays)
    counters: tuple     # steps, capped_steps, recovery_spikes, covariance_faults
    noise: tuple        # the membrane-noise generators' states
    chip: Any           # ChipNetwork.snapshot() or None
    call_dt: float | None


def _covariance_or_error(p: np.ndarray, name: str) -> np.ndarray:
    """``p`` (runs, n, n) if every run's is a covariance (finite, symmetric, positive definite),
    else ValueError: the covariance step keeps P positive definite, so it must start so."""
    if not np.isfinite(p).all():
        raise ValueError(f'{name} must be finite')
    if not np.allclose(p, np.swapaxes(p, 1, 2), rtol=1e-9, atol=0.0):
        raise ValueError(f'{name} must be symmetric')
    try:
        np.linalg.cholesky(p)
    except np.linalg.LinAlgError:
        raise ValueError(f'{name} must be positive definite (a covariance)') from None
    return p


class EstimatorState:
    """Where an Estimator starts and what it holds: initial states, reset, encoding a state into
    the network, replacing the state, silencing neurons."""

    def initial_states(self) -> np.ndarray:
        """The configured start of every run, (runs, n): initial_state, or with
        initial_state_dispersion a draw from N(initial_state, P0) seeded by the run's seed
        (stream 5), the same on every call and for a run alone or in a batch."""
        s = self.settings
        x0 = np.broadcast_to(s.initial_state, (self.runs, s.initial_state.size)).copy()
        if s.initial_state_dispersion:
            root = np.linalg.cholesky(s.initial_covariance)
            for b, seed in enumerate(self.seeds):
                x0[b] += root @ np.random.default_rng([seed, DISPERSION_STREAM]).standard_normal(x0.shape[1])
        return x0

    def reset(self, x_hat0=None, P0=None) -> None:
        """Restart from ``x_hat0`` (default: :meth:`initial_states`) and ``P0``; silenced
        neurons stay silent.

        Spiking filters set rates r >= 0 that decode to x_hat0 (non-negative least squares)
        and potentials v = D^T (x~0 - D r), i.e. zero coding error.
        """
        n = self.model.n_state
        x0 = self.initial_states() if x_hat0 is None else np.asarray(x_hat0, dtype=float)
        x0 = np.broadcast_to(x0, (self.runs, n)).astype(float)
        if not np.isfinite(x0).all():
            raise ValueError('x_hat0 must be finite')
        p0 = self.settings.initial_covariance if P0 is None else np.asarray(P0, dtype=float)
        p0 = _covariance_or_error(np.broadcast_to(p0, (self.runs, n, n)), 'P0')
        # in place: the kernel's packed arguments and the offline simulator hold these arrays
        self._p[:] = p0
        self._x_hat[:] = x0
        self._gain[:] = 0.0
        self._fault[:] = False
        self.steps = self.capped_steps = self.recovery_spikes = 0
        #: Runs whose P stopped being positive definite (or gain finite) in a step, summed over steps.
        self.covariance_faults = 0
        if self.spiking:
            self._network.clear()
            for b in range(self.runs):
                self.encode(x0[b], run=b)
        if self._linearize:
            self._c[:] = 0.0
            self._relinearize(None, self._none_measured)

    def restart(self, runs) -> None:
        """Restart the runs ``runs`` (indices, or a bool per run) from their configured start
        (:meth:`initial_states`, P0) and leave every other run exactly as it is; the step and
        spike counters go on. The offline simulator restarts a run that diverged so that the
        batch can go on stepping (the run's later samples are discarded). Not available on the
        chip network (ValueError)."""
        if self._chip is not None:
            raise ValueError('restart() is not available on the chip network: reset() restarts every run')
        chosen = np.zeros(self.runs, dtype=bool)
        chosen[np.asarray(runs).reshape(-1)] = True
        starts = self.initial_states()
        self._p[chosen] = self.settings.initial_covariance
        self._x_hat[chosen] = starts[chosen]
        self._gain[chosen] = 0.0
        self._fault[chosen] = False
        if self.spiking:
            for b in np.flatnonzero(chosen):  # its rates and potentials (and prediction) anew
                self.encode(starts[b], run=b)

    def retire(self, runs) -> None:
        """Restart the runs ``runs`` (as :meth:`restart`) and, on a spiking filter, silence every
        neuron of theirs for good: a run that diverged flies on unmeasured and its samples are
        discarded, so its network need not fire. Without this a run that diverged at its spike
        cap (membrane noise, a bad gain) would keep hitting the cap, at ~cap x N operations per
        step, for the rest of the batch."""
        self.restart(runs)
        if self.spiking:
            chosen = np.zeros(self.runs, dtype=bool)
            chosen[np.asarray(runs).reshape(-1)] = True
            net = self._network
            net.alive[chosen] = False
            net.r[chosen] = 0.0
            net.v[chosen] = 0.0

    def _live_arrays(self) -> dict:
        """The arrays a step writes: estimate, covariance, gain, H (and its pseudo-inverse) of a
        nonlinear measurement, and the network's rates, potentials, spikes and prediction."""
        arrays = {'x_hat': self._x_hat, 'p': self._p, 'gain': self._gain, 'fault': self._fault}
        if self._linearize:
            arrays.update(c=self._c, c_pinv=self._c_pinv)
        if self.spiking:
            net = self._network
            arrays.update(r=net.r, v=net.v, spikes=net.spikes, total_spikes=net.total_spikes,
                          reference=net.reference)
        return arrays

    def snapshot(self) -> EstimatorSnapshot:
        """Everything a step changes (estimate, covariance, gain, the network's r, v, spikes,
        total spikes and prediction, the chip network's state, the membrane-noise generators,
        the step counters), copied: :meth:`restore` returns the filter to it bit for bit, so a
        step can be taken again with another control. Settings, silenced neurons and the
        decoder are not part of it (retune and silence between the two are not undone)."""
        rngs = tuple(g.bit_generator.state for g in self._network.noise_rngs) if self.spiking else ()
        return EstimatorSnapshot(
            owner=id(self), arrays={name: array.copy() for name, array in self._live_arrays().items()},
            counters=(self.steps, self.capped_steps, self.recovery_spikes, self.covariance_faults), noise=rngs,
            chip=self._chip.snapshot() if self._chip is not None else None, call_dt=self._call_dt)

    def restore(self, snapshot: EstimatorSnapshot) -> None:
        """Return to ``snapshot`` (taken from this estimator by :meth:`snapshot`), in place:
        the kernel's packed arguments keep holding the same arrays."""
        if not isinstance(snapshot, EstimatorSnapshot) or snapshot.owner != id(self):
            raise ValueError('restore takes a snapshot() of this estimator')
        if self._chip is not None:  # first: reloading an unprepared chip writes x_hat
            self._chip.restore(snapshot.chip)
        for name, array in self._live_arrays().items():
            array[...] = snapshot.arrays[name]
        self.steps, self.capped_steps, self.recovery_spikes, self.covariance_faults = snapshot.counters
        for generator, state in zip(self._network.noise_rngs if self.spiking else (), snapshot.noise):
            generator.bit_generator.state = state
        if snapshot.call_dt is not None and snapshot.call_dt != self._call_dt:
            self._set_step(snapshot.call_dt)

    def encode(self, x_hat: np.ndarray, run: int = 0) -> None:
        """Set the network of one run to represent ``x_hat`` (rates by NNLS over live neurons;
        with network_coding deviation the prediction restarts at ``x_hat`` and the network
        codes a zero deviation)."""
        self._net('r')
        if self.coding == 'deviation':
            x_hat = np.asarray(x_hat, dtype=float)
            if not np.isfinite(x_hat).all():
                raise ValueError(f'cannot encode {x_hat.tolist()}: not finite')
            self._network.encode(run, np.zeros_like(x_hat))
            self._network.reference[run] = x_hat
            self._x_hat[run] = x_hat
            return
        with np.errstate(over='ignore', invalid='ignore'):  # overflow is checked and refused below
            target = np.asarray(x_hat, dtype=float) / self._scale
        if not np.isfinite(target).all():
            raise ValueError(f'cannot encode {np.asarray(x_hat).tolist()}: not finite on the network '
                             f'scale S = {self._scale.tolist()}')
        if self._chip is not None:  # the chip encodes with its own (quantized) decoder
            self._x_hat[run] = self._chip.encode(run, target)
            return
        try:
            decoded = self._network.encode(run, target)
        except ValueError:
            raise ValueError(f'cannot encode {np.asarray(x_hat).tolist()}: the network overflows') from None
        self._x_hat[run] = self._scale * decoded

    def set_state(self, x_hat, P=None) -> None:
        """Replace the estimate (and covariance) of every run, keeping the network's decoder."""
        n = self.model.n_state
        x = np.broadcast_to(np.asarray(x_hat, dtype=float), (self.runs, n))
        if not np.isfinite(x).all():
            raise ValueError('x_hat must be finite')
        covariance = (None if P is None else
                      _covariance_or_error(np.broadcast_to(np.asarray(P, dtype=float), (self.runs, n, n)), 'P'))
        if self.spiking:
            for b in range(self.runs):
                self.encode(x[b], run=b)  # raises before changing the run if x is not encodable
        else:
            self._x_hat[:] = x
        if covariance is not None:
            self._p[:] = covariance
            self._fault[:] = False

    def silence(self, neurons: Sequence[int]) -> None:
        """Silence exactly ``neurons`` (others revive). A silenced neuron stops firing and its
        filtered train r_i and the synaptic input it sent (r_i times its Omega_f column) vanish,
        so the remaining neurons see the coding error and compensate at once by spiking
        (counted in ``total_spikes`` and ``recovery_spikes``).
        """
        self._net('r')
        if self._chip is not None:
            raise ValueError('silence() is not available on the chip network: set silenced_neurons')
        total = self.settings.neuron_count
        wanted = np.zeros(total, dtype=bool)
        indices = [int(i) for i in neurons]
        if any(i < 0 or i >= total for i in indices):
            raise ValueError(f'neuron indices must be in [0, {total - 1}], got {indices}')
        wanted[indices] = True
        net = self._network
        net.lose(wanted)
        # The survivors react on the fast time scale (instantaneous in continuous time), before
        # the slow dynamics of the next step see the decoded estimate.
        self.recovery_spikes += kernels.fire_kernel(self.settings.spike_rule, self.coding)(
            self.settings.max_spikes_per_step, net.kernel_tuple(), self._scale, self._x_hat)


class MeasuredSteps:
    """A step with a measurement model: H(x_hat) per run, the equivalent linear measurement and
    the NIS of an innovation."""

    @property
    def relinearises(self) -> bool:
        """True with a nonlinear measurement model (H(x_hat) each step): no least-squares start
        or restart from z = C x then."""
        return self._linearize

    def innovation_nis(self, z, measurement_covariance) -> np.ndarray:
        """Normalised innovation squared nu^T (C P C^T + R)^-1 nu of ``z`` against the current
        estimate, per run (R per sample; P = 0 for the covariance-free filters). Infinite where
        C P C^T + R cannot be inverted (a P that is no covariance any more): the estimate is then
        inconsistent with any measurement, which the runner's NIS check treats as such."""
        z = np.ascontiguousarray(z, dtype=float).reshape(self.runs, -1)
        r = np.ascontiguousarray(measurement_covariance, dtype=float)
        if r.shape != (z.shape[1], z.shape[1]):
            raise ValueError(f'measurement_covariance must be {z.shape[1]}x{z.shape[1]}, got {r.shape}')
        if self._linearize:  # the wrapped residual and S = H P H^T + R at the current estimate
            h = self.measurement.h(self._x_hat)
            nu = self.measurement.residual(z, h)
            c = self.measurement.jacobian(self._x_hat)
            if self.measurement.partial:  # only the sensors present (R block-diagonal)
                present = self.measurement.present(z)
                nu, c = np.where(present, nu, 0.0), np.where(present[:, :, None], c, 0.0)
            s = (c @ self._p @ np.swapaxes(c, 1, 2) + r if self.has_covariance
                 else np.broadcast_to(r, c.shape[:1] + r.shape))
            try:
                nis = np.einsum('bi,bi->b', nu, np.linalg.solve(s, nu[..., None])[..., 0])
            except np.linalg.LinAlgError:
                return np.full(self.runs, np.inf)
            return np.where(np.isfinite(nis), nis, np.inf)
        try:
            return kernels.innovation_nis(z, self._x_hat, self._c[0], self._p, r, self.has_covariance)
        except np.linalg.LinAlgError:
            return np.full(self.runs, np.inf)

    def _relinearize(self, z, measured):
        """Write H(x_hat) (and its pseudo-inverse) of every run into the kernel's C, and return
        the equivalent linear measurement z_eq = residual(z, h(x_hat)) + H x_hat, so that the
        kernel's z_eq - C x_hat is the wrapped residual; and the runs measured. A run whose H or
        h is not finite at x_hat (on a singular direction) keeps its last H and is not updated."""
        model, x_hat = self.measurement, self._x_hat
        jac = model.jacobian(x_hat)
        predicted = model.h(x_hat)
        present = None if z is None or not model.partial else model.present(z)
        if present is not None:  # an absent sensor: its rows of H zero, its innovation zero
            jac = np.where(present[:, :, None], jac, 0.0)
            predicted = np.where(present, predicted, 0.0)
        finite = np.isfinite(jac).all(axis=(1, 2)) & np.isfinite(predicted).all(axis=1)
        if finite.all():
            self._c[:] = jac
        else:
            self._c[finite] = jac[finite]
        if self.gain_law != 'kalman':  # C^+ of Eq. 7-8, 21-24 (the Kalman gain needs none)
            self._c_pinv[:] = np.linalg.pinv(self._c)
        if z is None:
            return None, measured
        measured = measured & finite
        z_eq = np.einsum('bij,bj->bi', self._c, x_hat)
        residual = model.residual(z[measured], predicted[measured])
        z_eq[measured] += residual if present is None else np.where(present[measured], residual, 0.0)
        return np.ascontiguousarray(z_eq), np.ascontiguousarray(measured)

