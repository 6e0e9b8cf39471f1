"""The filters of the paper (and our remedies) behind one interface, and the registry.

Filter kinds (snn_estimator.catalog.FILTER_KINDS):

{kinds}

Gain laws (one module each in snn_estimator.gains):

{laws}

With C = [I 0] (positions measured) the MSIF/SIF gain C^+ sat(.) has zero velocity rows: the
literal (S)EMSIF never corrects a velocity error (docs/decisions.md, 16). The weighted law
replaces C^+ by the covariance-weighted right inverse P C^T (C P C^T)^-1, with P the covariance
of the gain actually used.

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

from snn_estimator import gains
from snn_estimator.catalog import CONVERGES_FROM_DISPERSION, FILTER_KINDS, PAPER_KINDS, TWIN_OF, FilterKind, kinds_table  # noqa: F401
from snn_estimator.config import EstimatorConfig, ResolvedConfig, gain_noise_density, resolve
from snn_estimator.measurements import MeasurementModel
from snn_estimator.models import DT_CACHE_SIZE, StateSpaceModel
from snn_estimator.schema import RUNTIME
from snn_estimator.spiking import chip
from snn_estimator.spiking.network import NETWORK_STREAM, Network, network_rng, weights  # noqa: F401 (re-exported)

from . import kernels
from .estimator_parts import DISPERSION_STREAM, EstimatorState, MeasuredSteps  # noqa: F401 (re-exported)
from .gain_schedule import schedule_gains
from .steady_state import steady_state_gain  # noqa: F401 (re-exported)

__doc__ = __doc__.format(kinds=kinds_table(), laws=gains.table())



def _settings_constants(settings: ResolvedConfig) -> dict:
    """The kernel constants that follow the settings (what :meth:`Estimator.retune` changes)."""
    return {'leak': settings.leak_rate, 'max_spikes': settings.max_spikes_per_step,
            'r_hat_diag': np.ascontiguousarray(np.diag(settings.r_hat)), 'delta': settings.boundary_layer}


def _read_only(array: np.ndarray) -> np.ndarray:
    """A view of ``array`` that callers cannot write through."""
    view = array.view()
    view.flags.writeable = False
    return view


class StepDynamics:
    """The kernel's per-step model input: packed [A_d | B_d] (n x (n + nu); one shared block,
    cached per dt, for a linear model), with which a step is x + dt (A_d x + B_d u) and the
    covariance's transition Phi = I + dt A_d, plus the nonlinear drift a direct filter on a
    nonlinear model integrates itself (its A_d is then only the covariance's)."""

    def __init__(self, model: StateSpaceModel, method: str, runs: int, linearized: bool):
        #: ``linearized``: the network integrates A(x_hat) x_hat (Eq. 14, 17); otherwise the
        #: nonlinear f is integrated (a direct filter, or network_drive: nonlinear)
        self.model, self.method, self.runs, self.linearized = model, method, runs, linearized
        self._linear_cache: dict[float, np.ndarray] = {}
        self.no_drift = np.zeros((1, model.n_state))

    def __call__(self, x_hat: np.ndarray, u: np.ndarray, dt: float):
        model, method = self.model, self.method
        if model.is_linear:
            cached = self._linear_cache.get(dt)
            if cached is None:
                a_d, b_d = model.linearized_increment(None, dt, method)
                cached = np.ascontiguousarray(np.concatenate([a_d, b_d], axis=1)[None])
                if len(self._linear_cache) >= DT_CACHE_SIZE:
                    self._linear_cache.clear()
                self._linear_cache[dt] = cached
            return cached, self.no_drift
        runs = self.runs
        a_d, b_d = model.linearized_increment(x_hat, dt, method)  # A(x_hat) held over the step (Eq. 17)
        b_d = np.broadcast_to(b_d, (runs,) + b_d.shape[-2:])
        packed = np.ascontiguousarray(np.concatenate([a_d, b_d], axis=2))
        if self.linearized:  # the network implements the linearised drift A(x_hat) x_hat (Eq. 17)
            return packed, self.no_drift
        # the non-spiking twin (and a network with network_drive: nonlinear) integrates f itself
        drift = (model.transition(x_hat, u, dt, method) - x_hat) / dt
        return packed, np.ascontiguousarray(drift)


class EstimatorViews:
    """The public, read-only state of an :class:`Estimator`: estimates, covariances, gains and
    the network's arrays, for one run (no leading axis) or the batch."""

    runs: int
    spiking: bool
    has_covariance: bool

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
    def batch_fault(self) -> np.ndarray:
        """True for each run whose last step left P not positive definite or its gain not
        finite, shape (runs,), read-only view (the run must restart: :class:`CovarianceLost`)."""
        return _read_only(self._fault)

    @property
    def batch_spikes(self) -> np.ndarray | None:
        """Spikes per neuron in the last step for all runs, (runs, N), read-only view."""
        return _read_only(self._network.spikes) if self.spiking else None

    @property
    def prediction(self) -> np.ndarray | None:
        """x_pred of network_coding deviation (x_hat = x_pred + S D r), shape (n,) or (runs, n), a
        copy; None for the paper's coding and the non-spiking filters."""
        if not self.spiking or self.coding != 'deviation':
            return None
        return self._single(self._network.reference).copy()

    @property
    def gain(self) -> np.ndarray:
        """The gain K used in the last step, shape (n, m) or (runs, n, m)."""
        return self._single(self._gain)

    @property
    def spikes(self) -> np.ndarray | None:
        """Spikes per neuron in the last step, shape (N,) or (runs, N); None if not spiking."""
        return self._single(self._network.spikes) if self.spiking else None

    @property
    def spike_count(self) -> int | np.ndarray:
        """Spikes emitted in the last step (per run)."""
        if not self.spiking:
            return 0
        counts = self._network.spikes.sum(axis=1)
        return int(counts[0]) if self.runs == 1 else counts

    @property
    def total_spikes(self) -> int | np.ndarray:
        """Spikes emitted since the last reset (per run)."""
        if not self.spiking:
            return 0
        total = self._network.total_spikes
        return int(total[0]) if self.runs == 1 else total.copy()

    @property
    def neuron_count(self) -> int:
        return self.settings.neuron_count if self.spiking else 0

    def _net(self, name: str) -> np.ndarray:
        if not self.spiking:
            raise AttributeError(f'{self.kind} is not a spiking filter')
        return self._single(getattr(self._network, name))

    #: D, shape (n, N) or (runs, n, N) (in scaled units; x_hat = S D r).
    decoder = property(lambda self: self._net('decoder'))
    #: Filtered spike trains r, shape (N,) or (runs, N).
    rates = property(lambda self: self._net('r'))
    #: Membrane potentials v, shape (N,) or (runs, N).
    potentials = property(lambda self: self._net('v'))
    #: T_i = ||D_i||^2 / 2, shape (N,) or (runs, N).
    thresholds = property(lambda self: self._net('thresholds'))
    #: False for silenced neurons, shape (N,) or (runs, N) (a copy).
    alive = property(lambda self: self._net('alive').copy())

    @property
    def chip(self):
        """The chip network (snn_estimator.spiking.chip.ChipNetwork) when precision or gain_schedule asks
        for it, else None."""
        return self._chip

    @property
    def silenced(self) -> tuple:
        """Indices of the silenced neurons."""
        return tuple(int(i) for i in np.flatnonzero(~self._network.alive[0])) if self.spiking else ()


class Estimator(EstimatorViews, EstimatorState, MeasuredSteps):
    """A filter from :data:`FILTER_KINDS` over ``runs`` independent runs.

    Build with :func:`make_estimator`. ``step(z, u, dt)`` returns the new estimate.
    """

    #: Settings that may change between steps (schema fields with runtime=True).
    RETUNABLE = RUNTIME

    def __init__(self, kind: str, model: StateSpaceModel, config: EstimatorConfig,
                 runs: int = 1, seeds: Sequence[int] | None = None, measurement: MeasurementModel | None = None):
        if kind not in FILTER_KINDS:
            raise ValueError(f'unknown filter kind {kind!r}; choose one of {", ".join(FILTER_KINDS)}')
        if int(runs) < 1:
            raise ValueError(f'runs must be >= 1, got {runs}')
        self.kind, self.model, self.config = kind, model, config
        #: The sensor model z = h(x) + v the filter linearises each step (None: the model's C).
        self.measurement = _check_measurement(measurement, model)
        self._linearize = self.measurement is not None and self.measurement.linear_matrix is None
        self._n_meas = model.n_meas if self.measurement is None else self.measurement.dim
        self.settings: ResolvedConfig = resolve(config, model, self.n_meas)
        self._choose_laws(FILTER_KINDS[kind])
        self.runs = int(runs)
        self.seeds = ([self.settings.seed + b for b in range(self.runs)] if seeds is None
                      else [int(s) for s in seeds])
        if len(self.seeds) != self.runs:
            raise ValueError(f'seeds must have {self.runs} entries, got {len(self.seeds)}')
        n, m = model.n_state, self.n_meas
        self._c, self._c_pinv = self._measurement_matrices(n, m)
        self._all_measured = np.ones(self.runs, dtype=np.bool_)
        self._none_measured = np.zeros(self.runs, dtype=np.bool_)
        self._gain = np.zeros((self.runs, n, m))
        self._fault = np.zeros(self.runs, dtype=np.bool_)
        self._noise_steps: dict[float, np.ndarray] = {}
        self._no_measurement = np.zeros((self.runs, m))
        linearized = self.spiking and self.settings.network_drive == 'linearized'
        self._dynamics = StepDynamics(model, self.settings.discretization, self.runs, linearized)
        self._scale = np.ascontiguousarray(self.settings.state_scale)
        self._x_hat = np.zeros((self.runs, n))
        self._p = np.zeros((self.runs, n, n))
        self.steps = self.capped_steps = 0
        s = self.settings
        self._network = Network(self.seeds, n, s.neuron_count if self.spiking else 0, s.decoder_variance,
                                s.silenced_neurons)
        # precision loihi / gain_schedule switched: the network runs on snn_estimator.spiking.chip
        net = self._network
        if chip.wanted(config) and self.measurement is not None:
            raise ValueError('the chip network (precision loihi, gain_schedule switched) holds the constant C of '
                             'the model: it takes no measurement model; use precision float64')
        self._chip = (chip.ChipNetwork(kind, model, config, self.settings, net.decoder, net.alive,
                                       self._x_hat, net.spikes, net.total_spikes, self._chip_gains)
                      if chip.wanted(config) else None)
        #: What the network codes (schema network_coding): the estimate, or its deviation from
        #: the prediction x_pred (held in the network's ``reference``)
        self.coding = s.network_coding if self.spiking else 'state'
        if self._chip is not None and self.coding != 'state':
            raise ValueError('network_coding deviation runs on the float64 network only: use '
                             'network_coding state with precision loihi or gain_schedule switched')
        self.has_covariance = self.has_covariance and self._chip is None  # the chip computes no P
        self._packed = self._pack()
        composition = (self.gain_law if not self.constant_gain else 'fixed', self.covariance_law, self.spiking,
                       s.spike_rule, not (model.is_linear or linearized), self.coding)
        self._kernel = kernels.step_kernel(*composition)  # the packed tuples (the compiled loop's)
        self._packed_kernel = kernels.step_kernel(*composition, packed=True)  # one PackedRef (step's)
        self._step_entry = None  # the packed kernel's entry point for the step's argument types (see _advance)
        self._call_dt: float | None = None
        self.reset()

    def _chip_gains(self, dt: float) -> list[np.ndarray]:
        """The gains the chip network holds for steps of ``dt`` (its gain source): the switched
        schedule of this filter's twin, or the steady-state gain."""
        if self.config.gain_schedule == 'switched':
            return schedule_gains(self.kind, self.model, self.config, self.settings, dt,
                                  lambda kind, config: Estimator(kind, self.model, config))
        return [steady_state_gain(self.gain_law, self.model, self.settings, dt)]

    def _measurement_matrices(self, n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
        """H and its pseudo-inverse: one shared (1, m, n) for a linear measurement, else one
        per run, written in place each step (the kernel's constants hold these arrays)."""
        if self._linearize:
            return np.zeros((self.runs, m, n)), np.zeros((self.runs, n, m))
        linear_c = self.model.measurement_matrix if self.measurement is None else self.measurement.linear_matrix
        c = np.ascontiguousarray(np.asarray(linear_c, dtype=float)[None])
        return c, np.ascontiguousarray(np.linalg.pinv(c[0])[None])

    def _choose_laws(self, spec: FilterKind) -> None:
        self.spiking = spec.spiking
        self.constant_gain = self.settings.gain_schedule == 'steady_state'
        if self.constant_gain and (not self.model.is_linear or self._linearize):
            raise ValueError('gain_schedule steady_state needs a linear model and measurement (the gain is '
                             'the fixed point of Eq. 6); use time_varying')
        #: The gain law of the kind (a module of snn_estimator.gains), even when held constant.
        self.gain_law = spec.gain
        covariance = spec.covariance
        if self.constant_gain and covariance == 'riccati':
            covariance = 'gain'  # a constant gain is not the Kalman gain of the current P
        self.covariance_law = covariance
        self.has_covariance = covariance != 'none'

    def _pack(self) -> kernels.Packed:
        """The kernel's constants, filter state and network state, shape-checked once; the
        dt-dependent constants are set by :meth:`prepare` before the first step of a dt."""
        n, m, n_u = self.model.n_state, self.n_meas, self.model.n_input
        dims = {'runs': self.runs, 'n': n, 'm': m, 'nu': n_u, 'N': self._network.r.shape[1], 'w': n + n_u}
        return kernels.Packed(
            dims, c=self._c, c_pinv=self._c_pinv, q_step=np.zeros((n, n)), r_sample=np.eye(m),
            **_settings_constants(self.settings), scale=self._scale, fixed_gain=np.zeros((n, m)), x_hat=self._x_hat,
            p=self._p, gain=self._gain, fault=self._fault, **self._network.arrays)

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) this filter's kernels without stepping: a node
        calls this at configure so that its first step is not its slowest."""
        n, n_u = self.model.n_state, self.model.n_input
        kernels.compile_for(self._packed_kernel, self._packed.ref, self._all_measured, 0.1,
                            np.zeros((1, n, n + n_u)), self._dynamics.no_drift, self._no_measurement,
                            np.zeros((self.runs, n_u)), self._network.zero_noise)
        if self.spiking:
            net = self._network
            kernels.compile_for(kernels.fire_kernel(self.settings.spike_rule, self.coding), 1, net.kernel_tuple(),
                                self._scale, self._x_hat)

    # ------------------------------------------------------------------ state
    # ------------------------------------------------------------------ settings and steps
    def retune(self, **changes) -> None:
        """Change settings of :attr:`RETUNABLE` between steps. Validated first (the step in
        use included, once): a ValueError leaves the filter exactly as it was. A new
        ``silenced_neurons`` set silences exactly those neurons (:meth:`silence`)."""
        unknown = set(changes) - set(self.RETUNABLE)
        if unknown:
            raise ValueError(f'cannot change {sorted(unknown)} at runtime; retunable: {list(self.RETUNABLE)}')
        if self._chip is not None and changes:
            raise ValueError('the chip network holds its weights: rebuild the estimator to change them')
        config = self.config.replace(**changes)
        settings = resolve(config, self.model, self.n_meas)
        if self._call_dt is not None:  # the step size in use must still work
            self.check_time_step(self._call_dt, settings)
        self.config, self.settings = config, settings
        self._noise_steps.clear()
        self._packed.update(**_settings_constants(settings))
        if self._call_dt is not None:  # Q_d, R_d and a constant gain depend on the settings too
            self._set_step(self._call_dt)
        if 'silenced_neurons' in changes and self.spiking:
            self.silence(settings.silenced_neurons)

    def check_time_step(self, dt: float, settings: ResolvedConfig | None = None) -> None:
        """Raise ValueError when steps of ``dt`` cannot work: dt must be finite and positive, and
        a network needs leak_rate * dt < 1 (Eq. 10-11). The covariance step is exact at any dt
        (docs/decisions.md, 43)."""
        s = settings or self.settings
        if not 0.0 < dt < math.inf:
            raise ValueError(f'dt must be a finite positive number of seconds, got {dt!r}')
        if self.spiking and s.leak_rate * dt >= 1.0:
            raise ValueError(f'leak_rate * dt must be < 1 (got {s.leak_rate} * {dt}); use a smaller step')

    def prepare(self, dt: float) -> None:
        """Get ready for steps of ``dt``: check it (ValueError naming the fix, nothing changed)
        and set what depends on it (Q_d and R_d of the sampled step, a constant gain). ``step``
        does this the first time it sees a dt; calling it up front makes later :meth:`retune`
        calls check against that step too."""
        self.check_time_step(dt)
        self._set_step(dt)

    def _set_step(self, dt: float) -> None:
        """What depends on a checked ``dt``: the process noise of a step Q_d, the variance of a
        sample R_d = R / dt (R of Eq. 5-6) and a constant gain."""
        s = self.settings
        changes = {'q_step': self._process_noise_step(dt),
                   'r_sample': np.ascontiguousarray(gain_noise_density(s, dt) / dt)}
        if self.constant_gain:
            changes['fixed_gain'] = np.ascontiguousarray(steady_state_gain(self.gain_law, self.model, s, dt))
        self._packed.update(**changes)
        self._call_dt = dt
        if self._chip is not None:
            self._chip.prepare(dt)

    def _process_noise_step(self, dt: float) -> np.ndarray:
        """Q_d, the covariance the process noise of density Q_hat adds over ``dt``: Van Loan's
        integral for a linear model with discretization exact, Q_hat dt otherwise (cached per dt)."""
        cached = self._noise_steps.get(dt)
        if cached is None:
            s = self.settings
            exact = self.model.is_linear and s.discretization == 'exact'
            cached = np.ascontiguousarray(self.model.process_noise_discrete(s.q_hat, dt) if exact else s.q_hat * dt)
            if len(self._noise_steps) >= DT_CACHE_SIZE:
                self._noise_steps.clear()
            self._noise_steps[dt] = cached
        return cached

    # ------------------------------------------------------------------ stepping
    def predict(self, u, dt: float) -> np.ndarray:
        """Advance by ``dt`` without a measurement (sensor dropout): K = 0, and the covariance
        predicted only (Phi P Phi^T + Q_d)."""
        return self.step(None, u, dt)

    @property
    def n_meas(self) -> int:
        """Components of the measurement the filter takes (the measurement model's, or the model's C)."""
        return self._n_meas

    def step(self, z, u, dt: float, valid=None) -> np.ndarray:
        """Advance every run by ``dt`` seconds with measurement ``z`` (at the current time) and
        control ``u`` (held over the step). Shapes (m,), (m_u,) or with a leading runs axis;
        ``z`` None means no measurement this step (see :meth:`predict`); ``valid`` (a bool per
        run, default all) marks the runs that have one (the others' rows are not read: a
        sample the sensor could not take, e.g. out of its field of view).

        With a nonlinear measurement model the filter re-linearises at the current estimate:
        C = H(x_hat) (Eq. 3-9, 19-22) and the innovation is the model's wrapped residual
        z - h(x_hat) (Eq. 3-4).

        Raises ValueError for non-finite input or a bad dt (the state is then unchanged),
        FloatingPointError if the state became non-finite and :class:`CovarianceLost` (a
        FloatingPointError) if a run's P stopped being positive definite or its gain finite
        (reset() or restart() those runs before going on: :attr:`batch_fault` marks them).
        """
        runs, m = self.runs, self._n_meas
        if z is None:
            z, measured = self._no_measurement, self._none_measured
        else:
            z = np.ascontiguousarray(z, dtype=float).reshape(runs, -1)  # the kernel's types (entry_point)
            measured = self._all_measured
            if valid is not None:
                measured = np.ascontiguousarray(np.broadcast_to(np.asarray(valid, dtype=np.bool_), (runs,)))
                if not measured.all():
                    z = np.where(measured[:, None], z, 0.0)
        u = np.ascontiguousarray(u, dtype=float).reshape(runs, -1)
        if z.shape[1] != m or u.shape[1] != self.model.n_input:
            raise ValueError(f'z must have {m} and u {self.model.n_input} entries '
                             f'per run, got shapes {z.shape} and {u.shape}')
        if self._linearize:
            if self.measurement.partial:  # NaN components: a sensor absent this step (Stacked)
                present = self.measurement.present(z)
                measured = np.ascontiguousarray(measured & present.any(axis=1))
                if not np.isfinite(np.where(present, z, 0.0)[measured]).all():
                    raise ValueError('z and u must be finite')
            elif not np.isfinite(z[measured]).all():
                raise ValueError('z and u must be finite')
            if dt != self._call_dt:
                self.prepare(dt)
            z, measured = self._relinearize(z, measured)
        elif dt != self._call_dt:
            self.prepare(dt)  # checks dt the first time it is used
        return self._advance(z, measured, u, dt)

    def _advance(self, z, measured, u, dt: float) -> np.ndarray:
        """One kernel step of ``dt`` (prepared) with the kernel's z and measured runs (z and u
        C-contiguous float64, (runs, m) and (runs, nu): the entry point's types)."""
        dynamics, drift = self._dynamics(self._x_hat, u, dt)
        noise = self._network.zero_noise
        if self.spiking and self.settings.membrane_noise > 0.0:
            noise = self._network.noise(self.settings.membrane_noise * math.sqrt(dt))
        if self._chip is not None:  # the chip network (snn_estimator.spiking.chip) replaces the kernel
            self._chip.step(z if measured.any() else None, u, dt)
            self.steps += 1
            self.capped_steps = self._chip.capped_steps
            return self.x_hat
        args = (self._packed.ref, measured, float(dt), dynamics, drift, z, u, noise)
        if self._step_entry is None:  # the first step: through numba's dispatch, then its entry point
            status, capped = self._packed_kernel(*args)
            self._step_entry = kernels.entry_point(self._packed_kernel, args)
        else:
            status, capped = self._step_entry(*args)
        if status == kernels.STATUS_BAD_INPUT:
            raise ValueError('z and u must be finite')
        self.steps += 1
        self.capped_steps += capped
        if status == kernels.STATUS_NON_FINITE:
            raise FloatingPointError(f'the {self.kind} state became non-finite; call reset()')
        if status == kernels.STATUS_COVARIANCE:
            self.covariance_faults += int(self._fault.sum())
            raise CovarianceLost(f'the {self.kind} covariance stopped being positive definite (or its gain finite) '
                                 f'in run(s) {np.flatnonzero(self._fault).tolist()}; restart them')
        return self.x_hat

    # ------------------------------------------------------------------ inspection
    def weights(self, u=None, dt: float = 0.1, run: int = 0) -> dict:
        """The network's matrices at the current state (Eq. 16-22, :func:`network.weights`), in
        scaled units; K is the gain used in the last step (the constant gain with gain_schedule
        steady_state). With discretization='euler' and S = I these are exactly the paper's
        formulas."""
        decoder = self._net('decoder')
        decoder = decoder if self.runs == 1 else decoder[run]
        a_d, b_d = self.model.linearized_increment(self._x_hat[run], dt, self.settings.discretization)
        gain = (steady_state_gain(self.gain_law, self.model, self.settings, dt) if self.constant_gain
                else self._gain[run])
        c = self._c[0] if self._c.shape[0] == 1 else self._c[run]
        return weights(decoder, self._scale, a_d, b_d, gain, c, self.settings.leak_rate,
                       self._network.thresholds[run], self.coding)


class CovarianceLost(FloatingPointError):
    """A step left a run's P not symmetric positive definite, or its gain not finite (the
    guard of the sampled step, docs/decisions.md, 43): the run must restart before it steps
    again; the estimate it holds is not to be published."""


def make_estimator(kind: str, config: EstimatorConfig | None = None,
                   model: StateSpaceModel | None = None, runs: int = 1,
                   seeds: Sequence[int] | None = None, measurement: MeasurementModel | None = None) -> Estimator:
    """Build the filter ``kind`` (see :data:`FILTER_KINDS`) for ``model`` (default: the
    standard CW rendezvous model) with ``config`` (default: :class:`EstimatorConfig`), measuring
    through ``measurement`` (a snn_estimator.measurements model; default: the model's linear C).
    The filter's R_hat is ``config.measurement_noise`` (times its scale) in that model's units."""
    if model is None:
        from snn_estimator.models import ClohessyWiltshire
        model = ClohessyWiltshire()
    return Estimator(kind, model, config or EstimatorConfig(), runs=runs, seeds=seeds, measurement=measurement)


def _check_measurement(measurement, model: StateSpaceModel):
    """``measurement`` if it is a measurement model of ``model``'s state, else ValueError."""
    if measurement is None:
        return None
    if not isinstance(measurement, MeasurementModel):
        raise ValueError(f'measurement must be a snn_estimator.measurements model (make_model), got '
                         f'{type(measurement).__name__}')
    if measurement.n_state != model.n_state:
        raise ValueError(f'the measurement model {measurement.name} takes {measurement.n_state} states, the '
                         f'model has {model.n_state}')
    return measurement
