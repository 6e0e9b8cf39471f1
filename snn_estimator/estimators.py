"""The filters of the paper (and our remedies) behind one interface, and the registry.

====================  ==============================================  ====================
kind                  gain                                            state integration
====================  ==============================================  ====================
``ekf``               Kalman, K = P C^T R^-1 (Eq. 5), P by Eq. 6      direct (Eq. 3)
``emsif``             MSIF, C^+ sat(diag(Pzz)/delta) (Eq. 8-9)        direct
``esif``              SIF, C^+ sat(|z - z_hat|/delta) (Eq. 7)         direct (twin of snn_emsif_star)
``emsif_hybrid``      MSIF rows on measured directions, Kalman rows   direct
                      on the unmeasured ones (not in the paper)
``snn_ekf``           Kalman (Eq. 19-20)                              spiking network (Eq. 14-15)
``snn_emsif``         MSIF (Eq. 21-22)                                spiking network
``snn_emsif_star``    SIF, no covariance (Eq. 23-24)                  spiking network
``snn_emsif_hybrid``  as emsif_hybrid (Omega_k = -D^T K C D, F_k = D^T K)  spiking network
====================  ==============================================  ====================

With C = [I 0] (positions measured) the MSIF/SIF gain C^+ sat(.) has zero velocity rows: the
literal (S)EMSIF never corrects a velocity error (docs/decisions.md, 16). The hybrid keeps the
sliding gain on the measured directions and adds the Kalman gain projected on the unmeasured
ones, (I - C^+ C) P C^T R^-1, with P the covariance of the gain actually used.

``gain_schedule: steady_state`` replaces any gain by its constant value at the fixed point of
Eq. 6 (see :func:`steady_state_gain`): the network's weights are then constant, which is what
a neuromorphic chip can hold (and what ``snn_export`` writes).

Every estimator steps a batch of independent runs (leading axis ``runs``); with ``runs == 1``
the public arrays drop that axis. One step maps the estimate at t_k, the measurement z_k taken
at t_k and the control u_k held over [t_k, t_k + dt) to the estimate at t_k + dt.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import scipy.linalg
import scipy.special
from scipy.optimize import nnls

from . import chip, kernels
from .catalog import CONVERGES_FROM_DISPERSION, FILTER_KINDS, PAPER_KINDS, TWIN_OF, FilterKind  # noqa: F401 (re-exported)
from .config import EstimatorConfig, ResolvedConfig, gain_noise_density, resolve
from .models import StateSpaceModel

NETWORK_STREAM = 3  # rng stream id of the decoder and membrane noise (README, "Time and seeds")
DISPERSION_STREAM = 5  # rng stream id of the dispersed initial estimate

_GAINS = {'kalman': kernels.GAIN_KALMAN, 'msif': kernels.GAIN_MSIF, 'sif': kernels.GAIN_SIF,
          'msif_hybrid': kernels.GAIN_MSIF_HYBRID, 'msif_weighted': kernels.GAIN_MSIF_WEIGHTED}
_COVARIANCES = {'none': kernels.COVARIANCE_NONE, 'riccati': kernels.COVARIANCE_RICCATI,
                'gain': kernels.COVARIANCE_GAIN}
_RULES = {'greedy': kernels.RULE_GREEDY, 'one_per_step': kernels.RULE_ONE_PER_STEP,
          'all_above': kernels.RULE_ALL_ABOVE}




def _retunable_arguments(settings: ResolvedConfig) -> dict:
    """The step kernel's arguments that :meth:`Estimator.retune` may change, from the settings."""
    return {'leak': settings.leak_rate, 'q_hat': settings.q_hat,
            'r_hat_diag': np.ascontiguousarray(np.diag(settings.r_hat)), 'delta': settings.boundary_layer}


def _read_only(array: np.ndarray) -> np.ndarray:
    """A view of ``array`` that callers cannot write through."""
    view = array.view()
    view.flags.writeable = False
    return view


def network_rng(seed: int) -> np.random.Generator:
    """The generator of a network's decoder and membrane noise for one run."""
    return np.random.default_rng([int(seed), NETWORK_STREAM])


class Estimator:
    """A filter from :data:`FILTER_KINDS` over ``runs`` independent runs.

    Build with :func:`make_estimator`. ``step(z, u, dt)`` returns the new estimate.
    """

    def __init__(self, kind: str, model: StateSpaceModel, config: EstimatorConfig,
                 runs: int = 1, seeds: Sequence[int] | None = None):
        if kind not in FILTER_KINDS:
            raise ValueError(f'unknown filter kind {kind!r}; choose one of {", ".join(FILTER_KINDS)}')
        if int(runs) < 1:
            raise ValueError(f'runs must be >= 1, got {runs}')
        self.kind = kind
        self.model = model
        self.config = config
        self.settings: ResolvedConfig = resolve(config, model)
        spec = FILTER_KINDS[kind]
        self.spiking = spec.spiking
        self.constant_gain = self.settings.gain_schedule == 'steady_state'
        if self.constant_gain and not model.is_linear:
            raise ValueError('gain_schedule steady_state needs a linear model (the gain is the '
                             'fixed point of Eq. 6); use time_varying')
        #: The gain law of the kind (kalman | msif | sif | msif_hybrid), even when held constant.
        self.gain_law = spec.gain
        covariance = spec.covariance
        if self.constant_gain and covariance == 'riccati':
            covariance = 'gain'  # a constant gain is not the Kalman gain of the current P
        self.covariance_law = covariance
        self.has_covariance = covariance != 'none'
        self.runs = int(runs)
        self.seeds = ([self.settings.seed + b for b in range(self.runs)] if seeds is None
                      else [int(s) for s in seeds])
        if len(self.seeds) != self.runs:
            raise ValueError(f'seeds must have {self.runs} entries, got {len(self.seeds)}')
        n, m = model.n_state, model.n_meas
        self._c = np.ascontiguousarray(model.measurement_matrix, dtype=float)
        self._c_pinv = np.linalg.pinv(self._c)
        self._gain = np.zeros((self.runs, n, m))
        self._no_drift = np.zeros((1, n))
        self._no_measurement = np.zeros((self.runs, m))
        self._linear_cache: dict[float, np.ndarray] = {}
        self._scale = np.ascontiguousarray(self.settings.state_scale)
        self._x_hat = np.zeros((self.runs, n))
        self._p = np.zeros((self.runs, n, n))
        self.steps = 0
        self.capped_steps = 0
        self._build_network(neurons=self.settings.neuron_count if self.spiking else 0)
        # precision loihi / gain_schedule switched: the network runs on snn_estimator.chip
        self._chip = (chip.ChipNetwork(kind, model, config, self.settings, self._decoder, self._alive,
                                       self._x_hat, self._spikes, self._total_spikes)
                      if chip.wanted(config) else None)
        self.has_covariance = self.has_covariance and self._chip is None  # the chip computes no P
        self._call = self._kernel_call()
        self._call_dt: float | None = None
        self._slots = tuple(self._call.slot(name) for name in
                            ('measured', 'dt', 'dynamics', 'drift', 'use_given_drift', 'z', 'u', 'noise'))
        self.reset()

    def _kernel_call(self) -> kernels.StepCall:
        """Every argument of the step kernel, by name, shape-checked once (see kernels.StepCall).
        The dt-dependent ones are set by :meth:`prepare` before the first step of a dt."""
        s = self.settings
        n, m, n_u = self.model.n_state, self.model.n_meas, self.model.n_input
        dims = {'runs': self.runs, 'n': n, 'm': m, 'nu': n_u, 'N': self._r.shape[1], 'w': 2 * n + n_u}
        no_gain = np.zeros((n, m))
        return kernels.StepCall(
            dims,
            gain_law=kernels.GAIN_FIXED if self.constant_gain else _GAINS[self.gain_law],
            covariance_law=_COVARIANCES[self.covariance_law], spiking=self.spiking,
            spike_rule=_RULES[s.spike_rule], use_given_drift=False, measured=True, dt=0.0,
            max_spikes=s.max_spikes_per_step, c=self._c, c_pinv=self._c_pinv,
            r_density=np.eye(m), r_density_inv=np.eye(m), **_retunable_arguments(s), scale=self._scale,
            fixed_gain=no_gain, dynamics=np.zeros((1, n, 2 * n + n_u)),
            drift=self._no_drift, z=self._no_measurement, u=np.zeros((self.runs, n_u)),
            noise=self._zero_noise, x_hat=self._x_hat, p=self._p, gain=self._gain,
            decoder=self._decoder, gram=self._gram, thresholds=self._thresholds, alive=self._alive,
            r=self._r, v=self._v, spikes=self._spikes, total_spikes=self._total_spikes)

    # ------------------------------------------------------------------ public state
    def _single(self, array: np.ndarray) -> np.ndarray:
        return array[0] if self.runs == 1 else array

    @property
    def x_hat(self) -> np.ndarray:
        """Current estimate, shape (n,) or (runs, n)."""
        return self._single(self._x_hat)

    @property
    def P(self) -> np.ndarray | None:
        """Error covariance, shape (n, n) or (runs, n, n): Eq. 6, or that of the gain used
        (:attr:`covariance_law`); None for the SIF-gain filters, which compute none."""
        return self._single(self._p) if self.has_covariance else None

    @property
    def batch_x_hat(self) -> np.ndarray:
        """The estimates of all runs, shape (runs, n), even for one run: a read-only view the
        filter updates in place (the offline simulator reads it every step)."""
        return _read_only(self._x_hat)

    @property
    def batch_P(self) -> np.ndarray | None:
        """Covariances of all runs, (runs, n, n), read-only view; None without a covariance."""
        return _read_only(self._p) if self.has_covariance else None

    @property
    def batch_spikes(self) -> np.ndarray | None:
        """Spikes per neuron in the last step for all runs, (runs, N), read-only view."""
        return _read_only(self._spikes) if self.spiking else None

    @property
    def gain(self) -> np.ndarray:
        """The gain K used in the last step, shape (n, m) or (runs, n, m)."""
        return self._single(self._gain)

    @property
    def spikes(self) -> np.ndarray | None:
        """Spikes per neuron in the last step, shape (N,) or (runs, N); None if not spiking."""
        return self._single(self._spikes) if self.spiking else None

    @property
    def spike_count(self) -> int | np.ndarray:
        """Spikes emitted in the last step (per run)."""
        if not self.spiking:
            return 0
        counts = self._spikes.sum(axis=1)
        return int(counts[0]) if self.runs == 1 else counts

    @property
    def total_spikes(self) -> int | np.ndarray:
        """Spikes emitted since the last reset (per run)."""
        if not self.spiking:
            return 0
        return int(self._total_spikes[0]) if self.runs == 1 else self._total_spikes.copy()

    @property
    def chip(self):
        """The chip network (snn_estimator.chip.ChipNetwork) when precision or gain_schedule asks
        for it, else None."""
        return self._chip

    @property
    def neuron_count(self) -> int:
        return self.settings.neuron_count if self.spiking else 0

    @property
    def decoder(self) -> np.ndarray:
        """D, shape (n, N) or (runs, n, N) (in scaled units; x_hat = S D r)."""
        self._require_network()
        return self._single(self._decoder)

    @property
    def rates(self) -> np.ndarray:
        """Filtered spike trains r, shape (N,) or (runs, N)."""
        self._require_network()
        return self._single(self._r)

    @property
    def potentials(self) -> np.ndarray:
        """Membrane potentials v, shape (N,) or (runs, N)."""
        self._require_network()
        return self._single(self._v)

    @property
    def thresholds(self) -> np.ndarray:
        """T_i = ||D_i||^2 / 2, shape (N,) or (runs, N)."""
        self._require_network()
        return self._single(self._thresholds)

    @property
    def alive(self) -> np.ndarray:
        """False for silenced neurons, shape (N,) or (runs, N)."""
        self._require_network()
        return self._single(self._alive).copy()

    @property
    def silenced(self) -> tuple:
        """Indices of the silenced neurons."""
        return tuple(int(i) for i in np.flatnonzero(~self._alive[0])) if self.spiking else ()

    # ------------------------------------------------------------------ set-up
    def _require_network(self):
        if not self.spiking:
            raise AttributeError(f'{self.kind} is not a spiking filter')

    def _build_network(self, neurons: int):
        """Decoder D ~ N(0, var) per run, Gram matrix D^T D, thresholds T_i = ||D_i||^2/2.
        A non-spiking filter gets empty arrays (the kernel ignores them)."""
        s = self.settings
        n = self.model.n_state
        self._decoder = np.empty((self.runs, n, neurons))
        for b, seed in enumerate(self.seeds):
            self._decoder[b] = network_rng(seed).normal(0.0, math.sqrt(s.decoder_variance), (n, neurons))
        self._noise_rngs = [np.random.default_rng([seed, NETWORK_STREAM, 1]) for seed in self.seeds]
        self._gram = np.ascontiguousarray(np.einsum('bki,bkj->bij', self._decoder, self._decoder))
        self._thresholds = 0.5 * np.einsum('bki,bki->bi', self._decoder, self._decoder)
        self._r = np.zeros((self.runs, neurons))
        self._v = np.zeros((self.runs, neurons))
        self._alive = np.ones((self.runs, neurons), dtype=np.bool_)
        self._alive[:, list(s.silenced_neurons)] = False
        self._spikes = np.zeros((self.runs, neurons), dtype=np.int64)
        self._total_spikes = np.zeros(self.runs, dtype=np.int64)
        self._zero_noise = np.zeros((self.runs, neurons))

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
        p0 = np.broadcast_to(p0, (self.runs, n, n))
        if not np.isfinite(p0).all():
            raise ValueError('P0 must be finite')
        # in place: the kernel call and the offline simulator hold these arrays
        self._p[:] = p0
        self._x_hat[:] = x0
        self._gain[:] = 0.0
        self.steps = 0
        self.capped_steps = 0
        self.recovery_spikes = 0
        if self.spiking:
            self._r[:] = 0.0
            self._v[:] = 0.0
            self._spikes[:] = 0
            self._total_spikes[:] = 0
            for b in range(self.runs):
                self.encode(x0[b], run=b)

    def encode(self, x_hat: np.ndarray, run: int = 0) -> None:
        """Set the network of one run to represent ``x_hat`` (rates by NNLS over live neurons)."""
        self._require_network()
        with np.errstate(over='ignore', invalid='ignore'):  # overflow is checked and refused below
            target = np.asarray(x_hat, dtype=float) / self._scale
        if not np.isfinite(target).all():
            raise ValueError(f'cannot encode {np.asarray(x_hat).tolist()}: not finite on the network '
                             f'scale S = {self._scale.tolist()}')
        if self._chip is not None:  # the chip encodes with its own (quantized) decoder
            self._x_hat[run] = self._chip.encode(run, target)
            return
        alive = self._alive[run]
        decoder = self._decoder[run]
        rates = np.zeros(decoder.shape[1])
        if np.any(alive):
            rates[alive], _ = nnls(decoder[:, alive], target, maxiter=50 * decoder.shape[1])
        with np.errstate(over='ignore', invalid='ignore'):
            decoded = decoder @ rates
            potentials = decoder.T @ (target - decoded)
        if not (np.isfinite(decoded).all() and np.isfinite(potentials).all()):
            raise ValueError(f'cannot encode {np.asarray(x_hat).tolist()}: the network overflows')
        self._r[run] = rates
        self._v[run] = potentials
        self._x_hat[run] = self._scale * decoded

    def set_state(self, x_hat, P=None) -> None:
        """Replace the estimate (and covariance) of every run, keeping the network's decoder."""
        n = self.model.n_state
        x = np.broadcast_to(np.asarray(x_hat, dtype=float), (self.runs, n))
        if not np.isfinite(x).all():
            raise ValueError('x_hat must be finite')
        covariance = None if P is None else np.broadcast_to(np.asarray(P, dtype=float), (self.runs, n, n))
        if covariance is not None and not np.isfinite(covariance).all():
            raise ValueError('P must be finite')
        if self.spiking:
            for b in range(self.runs):
                self.encode(x[b], run=b)  # raises before changing the run if x is not encodable
        else:
            self._x_hat[:] = x
        if covariance is not None:
            self._p[:] = covariance

    def silence(self, neurons: Sequence[int]) -> None:
        """Silence exactly ``neurons`` (others revive). A silenced neuron stops firing and its
        filtered train r_i and the synaptic input it sent (r_i times its Omega_f column) vanish,
        so the remaining neurons see the coding error and compensate at once by spiking
        (counted in ``total_spikes`` and ``recovery_spikes``).
        """
        self._require_network()
        if self._chip is not None:
            raise ValueError('silence() is not available on the chip network: set silenced_neurons')
        total = self.settings.neuron_count
        wanted = np.zeros(total, dtype=bool)
        indices = [int(i) for i in neurons]
        if any(i < 0 or i >= total for i in indices):
            raise ValueError(f'neuron indices must be in [0, {total - 1}], got {indices}')
        wanted[indices] = True
        for b in range(self.runs):
            newly_dead = wanted & self._alive[b]
            if np.any(newly_dead):
                lost = self._r[b, newly_dead]
                self._v[b] += self._gram[b][:, newly_dead] @ lost
                self._r[b, newly_dead] = 0.0
            self._alive[b] = ~wanted
        # The survivors react on the fast time scale (instantaneous in continuous time), before
        # the slow dynamics of the next step see the decoded estimate.
        self.recovery_spikes += kernels.fire_only(
            _RULES[self.settings.spike_rule], self.settings.max_spikes_per_step, self._decoder, self._gram,
            self._thresholds, self._alive, self._r, self._v, self._scale, self._spikes,
            self._total_spikes, self._x_hat)

    #: Settings that may change between steps (the [runtime] parameters of docs/parameters.md).
    RETUNABLE = ('leak_rate', 'boundary_layer', 'process_noise_scale', 'measurement_noise_scale',
                 'membrane_noise')

    def retune(self, **changes) -> None:
        """Change settings of :attr:`RETUNABLE` between steps. Validated first: a ValueError
        leaves the filter exactly as it was."""
        unknown = set(changes) - set(self.RETUNABLE)
        if unknown:
            raise ValueError(f'cannot change {sorted(unknown)} at runtime; retunable: {list(self.RETUNABLE)}')
        if self._chip is not None and changes:
            raise ValueError('the chip network holds its weights: rebuild the estimator to change them')
        config = self.config.replace(**changes)
        settings = resolve(config, self.model)
        if self._call_dt is not None:  # the step size in use must still work
            self.check_time_step(self._call_dt, settings)
        self.config, self.settings = config, settings
        self._call.update(**_retunable_arguments(settings))
        if self._call_dt is not None:  # R of Eq. 5-6 and a constant gain depend on the settings too
            self.prepare(self._call_dt)

    def check_time_step(self, dt: float, settings: ResolvedConfig | None = None) -> None:
        """Raise ValueError when steps of ``dt`` cannot work: a network needs leak_rate * dt < 1
        (Eq. 10-11), and one Euler step of Eq. 6 from P0 must remove less than P0 in the
        measured directions (dt C P0 C^T R^-1 <= 1, R the density of Eq. 5-6), or P stops
        being a covariance and the filter diverges."""
        s = settings or self.settings
        if not 0.0 < dt < math.inf:
            raise ValueError(f'dt must be a finite positive number of seconds, got {dt!r}')
        if self.spiking and s.leak_rate * dt >= 1.0:
            raise ValueError(f'leak_rate * dt must be < 1 (got {s.leak_rate} * {dt}); use a smaller step')
        if not self.has_covariance:
            return
        c = self._c
        step_gain = dt * c @ s.initial_covariance @ c.T @ np.linalg.inv(gain_noise_density(s, dt))
        largest = float(np.max(np.linalg.eigvals(step_gain).real))
        if largest > 1.0 + 1e-9:
            hint = (', or measurement_noise_units spectral_density'
                    if s.measurement_noise_units == 'per_sample' else '')
            raise ValueError(
                f'dt C P0 C^T R^-1 reaches {largest:.3g} at dt = {dt} s (at most 1): the '
                'Euler step of Eq. 6 would make P indefinite and the filter diverge. Lower '
                f'initial_covariance (P0) on the measured axes, raise measurement_noise_scale{hint}, '
                'or use a smaller time step')

    def prepare(self, dt: float) -> None:
        """Get ready for steps of ``dt``: check it (ValueError naming the fix, nothing changed)
        and set what depends on it (the R of Eq. 5-6, a constant gain). ``step`` does this the
        first time it sees a dt; calling it up front makes later :meth:`retune` calls check
        against that step too."""
        self.check_time_step(dt)
        s = self.settings
        density = gain_noise_density(s, dt)
        changes = {'r_density': np.ascontiguousarray(density),
                   'r_density_inv': np.ascontiguousarray(np.linalg.inv(density))}
        if self.constant_gain:
            changes['fixed_gain'] = np.ascontiguousarray(
                steady_state_gain(self.gain_law, self.model, s, dt))
        self._call.update(**changes)
        self._call_dt = dt
        if self._chip is not None:
            self._chip.prepare(dt)

    def innovation_nis(self, z, measurement_covariance) -> np.ndarray:
        """Normalised innovation squared nu^T (C P C^T + R)^-1 nu of ``z`` against the current
        estimate, per run (R per sample; P = 0 for the covariance-free filters)."""
        z = np.ascontiguousarray(z, dtype=float).reshape(self.runs, -1)
        r = np.ascontiguousarray(measurement_covariance, dtype=float)
        if r.shape != (z.shape[1], z.shape[1]):
            raise ValueError(f'measurement_covariance must be {z.shape[1]}x{z.shape[1]}, got {r.shape}')
        return kernels.innovation_nis(z, self._x_hat, self._c, self._p, r, self.has_covariance)

    # ------------------------------------------------------------------ stepping
    def _dynamics(self, dt: float, u: np.ndarray):
        """Packed [A_d | B_d | J] for this step, plus the nonlinear drift of a direct filter."""
        model = self.model
        method = self.settings.discretization
        if model.is_linear:
            cached = self._linear_cache.get(dt)
            if cached is None:
                a_d, b_d = model.linearized_increment(None, dt, method)
                jac = model.jacobian(np.zeros(model.n_state), np.zeros(model.n_input))
                cached = np.ascontiguousarray(np.concatenate([a_d, b_d, jac], axis=1)[None])
                if len(self._linear_cache) > 64:
                    self._linear_cache.clear()
                self._linear_cache[dt] = cached
            return cached, self._no_drift, False
        runs = self.runs
        jac = model.jacobian(self._x_hat, u)
        b_d = np.broadcast_to(model.input_matrix, (runs,) + model.input_matrix.shape)
        if self.spiking:  # the network implements the linearised drift A(x_hat) x_hat (Eq. 17)
            a_d, b_d = model.linearized_increment(self._x_hat, dt, method)
            b_d = np.broadcast_to(b_d, (runs,) + b_d.shape[-2:])
            return np.ascontiguousarray(np.concatenate([a_d, b_d, jac], axis=2)), self._no_drift, False
        # the non-spiking twin integrates the nonlinear f itself
        drift = (model.transition(self._x_hat, u, dt, method) - self._x_hat) / dt
        return (np.ascontiguousarray(np.concatenate([jac, b_d, jac], axis=2)),
                np.ascontiguousarray(drift), True)

    def predict(self, u, dt: float) -> np.ndarray:
        """Advance by ``dt`` without a measurement (sensor dropout): K = 0, and Eq. 6 without
        its measurement term."""
        return self.step(None, u, dt)

    def step(self, z, u, dt: float) -> np.ndarray:
        """Advance every run by ``dt`` seconds with measurement ``z`` (at the current time) and
        control ``u`` (held over the step). Shapes (m,), (m_u,) or with a leading runs axis;
        ``z`` None means no measurement this step (see :meth:`predict`).

        Raises ValueError for non-finite input or a bad dt (the state is then unchanged) and
        FloatingPointError if the state became non-finite (reset() before going on).
        """
        runs = self.runs
        measured = z is not None
        z = (np.asarray(z, dtype=float).reshape(runs, -1) if measured
             else self._no_measurement)
        u = np.asarray(u, dtype=float).reshape(runs, -1)
        if z.shape[1] != self.model.n_meas or u.shape[1] != self.model.n_input:
            raise ValueError(f'z must have {self.model.n_meas} and u {self.model.n_input} entries '
                             f'per run, got shapes {z.shape} and {u.shape}')
        if dt != self._call_dt:
            self.prepare(dt)  # checks dt the first time it is used
        dynamics, drift, use_drift = self._dynamics(dt, u)
        noise = self._zero_noise
        if self.spiking and self.settings.membrane_noise > 0.0:
            sigma = self.settings.membrane_noise * math.sqrt(dt)
            noise = np.stack([g.normal(0.0, sigma, self.settings.neuron_count)
                              for g in self._noise_rngs])
        if self._chip is not None:  # the chip network (snn_estimator.chip) replaces the kernel
            self._chip.step(z if measured else None, u, dt)
            self.steps += 1
            self.capped_steps = self._chip.capped_steps
            return self.x_hat
        self._call.set_slots(zip(self._slots, (measured, float(dt), dynamics, drift, use_drift,
                                               np.ascontiguousarray(z), np.ascontiguousarray(u), noise)))
        status, capped = self._call()
        if status == kernels.STATUS_BAD_INPUT:
            raise ValueError('z and u must be finite')
        self.steps += 1
        self.capped_steps += capped
        if status == kernels.STATUS_NON_FINITE:
            raise FloatingPointError(f'the {self.kind} state became non-finite; call reset()')
        return self.x_hat

    # ------------------------------------------------------------------ inspection
    def weights(self, u=None, dt: float = 0.1, run: int = 0) -> dict:
        """The network's matrices at the current state (Eq. 16-22), in scaled units.

        ``F = D^T S^-1 B_d``, ``Omega_s = D^T (S^-1 A_d S + lambda I) D``,
        ``Omega_f = -D^T D``, ``Omega_k = -D^T S^-1 K C S D``, ``F_k = D^T S^-1 K``, thresholds;
        K is the gain used in the last step (the constant gain with gain_schedule
        steady_state). With discretization='euler' and S = I these are exactly the paper's
        formulas.
        """
        self._require_network()
        d = self._decoder[run]
        scale = self._scale
        x = self._x_hat[run]
        a_d, b_d = self.model.linearized_increment(x, dt, self.settings.discretization)
        a_scaled = a_d / scale[:, None] * scale[None, :]
        gain = (steady_state_gain(self.gain_law, self.model, self.settings, dt) if self.constant_gain
                else self._gain[run])
        k_scaled = gain / scale[:, None]
        c_scaled = self._c * scale[None, :]
        neurons = d.shape[1]
        return {
            'F': d.T @ (b_d / scale[:, None]),
            'Omega_s': d.T @ (a_scaled + self.settings.leak_rate * np.eye(len(scale))) @ d,
            'Omega_f': -d.T @ d,
            'Omega_k': -d.T @ k_scaled @ c_scaled @ d,
            'F_k': d.T @ k_scaled,
            'thresholds': self._thresholds[run].copy(),
            'decoder': d.copy(),
            'neurons': neurons,
        }


def make_estimator(kind: str, config: EstimatorConfig | None = None,
                   model: StateSpaceModel | None = None, runs: int = 1,
                   seeds: Sequence[int] | None = None) -> Estimator:
    """Build the filter ``kind`` (see :data:`FILTER_KINDS`) for ``model`` (default: the
    standard CW rendezvous model) with ``config`` (default: :class:`EstimatorConfig`)."""
    if model is None:
        from .models import ClohessyWiltshire
        model = ClohessyWiltshire()
    return Estimator(kind, model, config or EstimatorConfig(), runs=runs, seeds=seeds)


def steady_state_gain(gain_law: str, model: StateSpaceModel, settings: ResolvedConfig,
                      dt: float) -> np.ndarray:
    """The constant gain of ``gain_law`` at the fixed point P_ss of Eq. 6 (the continuous
    algebraic Riccati equation J P + P J^T + Q - P C^T R^-1 C P = 0, R the density of Eq. 5-6):

    * kalman: P_ss C^T R^-1;
    * msif: C^+ sat(diag(C P_ss C^T + R_hat) / delta) (Eq. 8-9);
    * sif: C^+ diag(E[sat(|nu_j| / delta_j)]) with nu ~ N(0, C P_ss C^T + R_hat): the mean of
      Eq. 7's saturation over the innovations the filter expects;
    * msif_hybrid: the msif gain plus (I - C^+ C) P_ss C^T R^-1.

    Linear models only. ValueError when the Riccati equation has no stabilising solution (e.g.
    Q_hat = 0 with undamped modes).
    """
    if not model.is_linear:
        raise ValueError('a steady-state gain needs a linear model')
    n = model.n_state
    c = model.measurement_matrix
    jac = model.jacobian(np.zeros(n), np.zeros(model.n_input))
    density = gain_noise_density(settings, dt)
    try:
        p_ss = scipy.linalg.solve_continuous_are(jac.T, c.T, settings.q_hat, density)
    except (np.linalg.LinAlgError, ValueError) as error:
        raise ValueError(f'no steady-state gain: the Riccati equation of Eq. 6 has no stabilising '
                         f'solution for this Q_hat and R ({error}); raise process_noise_scale or '
                         'use gain_schedule time_varying') from None
    kalman = p_ss @ c.T @ np.linalg.inv(density)
    if gain_law == 'kalman':
        return kalman
    c_pinv = np.linalg.pinv(c)
    innovation_variance = np.diag(c @ p_ss @ c.T + settings.r_hat)
    delta = settings.boundary_layer
    if gain_law == 'sif':
        sigma = np.sqrt(innovation_variance)
        inside = 2.0 * sigma / math.sqrt(2.0 * math.pi) * (1.0 - np.exp(-delta ** 2 / (2.0 * sigma ** 2)))
        mean_saturation = inside / delta + scipy.special.erfc(delta / (sigma * math.sqrt(2.0)))
        return c_pinv @ np.diag(mean_saturation)
    saturation = np.diag(np.minimum(innovation_variance / delta, 1.0))
    msif = c_pinv @ saturation
    if gain_law == 'msif':
        return msif
    if gain_law == 'msif_weighted':
        return p_ss @ c.T @ np.linalg.inv(c @ p_ss @ c.T) @ saturation
    if gain_law == 'msif_hybrid':
        return msif + (np.eye(n) - c_pinv @ c) @ kalman
    raise ValueError(f'unknown gain law {gain_law!r}')
