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

An :class:`Estimator` is composed of parts that each own their state: the filter state
(:class:`~snn_estimator.filters.state.FilterState`: x_hat, P, gain, fault), the spiking network
(:class:`~snn_estimator.spiking.network.Network`, or the chip network), the measurement's
linearisation (:class:`~snn_estimator.filters.linearisation.Linearisation`: C, C^+) and the step
program (:class:`~snn_estimator.filters.program.StepProgram`: the compiled kernel and the packed
arrays it steps). The Estimator only decides what happens when.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from snn_estimator import gains
from snn_estimator.catalog import CONVERGES_FROM_DISPERSION, FILTER_KINDS, PAPER_KINDS, TWIN_OF, FilterKind, kinds_table  # noqa: F401
from snn_estimator.config import EstimatorConfig, ResolvedConfig, resolve
from snn_estimator.measurements import MeasurementModel
from snn_estimator.models import StateSpaceModel
from snn_estimator.schema import RUNTIME
from snn_estimator.spiking import chip
from snn_estimator.spiking.chip_synchronous import SynchronousChipNetwork
from snn_estimator.spiking.network import NETWORK_STREAM, Network, network_rng, weights  # noqa: F401 (re-exported)

from . import kernels
from .gain_schedule import schedule_gains
from .linearisation import Linearisation
from .program import SampledNoise, StepDynamics, StepProgram
from .state import DISPERSION_STREAM, EstimatorSnapshot, FilterState, covariance_or_error, initial_states  # noqa: F401
from .steady_state import steady_state_gain  # noqa: F401 (re-exported)

__doc__ = __doc__.format(kinds=kinds_table(), laws=gains.table())


def _settings_constants(settings: ResolvedConfig) -> dict:
    """The kernel constants that follow the settings (what :meth:`Estimator.retune` changes)."""
    return {'leak': settings.leak_rate, 'max_spikes': settings.max_spikes_per_step,
            'ticks': settings.ticks_per_sample, 'widening': settings.threshold_widening,
            'refractory': settings.refractory_ticks, 'slots': settings.firing_slots,
            'r_hat_diag': np.ascontiguousarray(np.diag(settings.r_hat)), 'delta': settings.boundary_layer}


def _read_only(array: np.ndarray) -> np.ndarray:
    """A view of ``array`` that callers cannot write through."""
    view = array.view()
    view.flags.writeable = False
    return view


class CovarianceLost(FloatingPointError):
    """A step left a run's P not symmetric positive definite, or its gain not finite (the
    guard of the sampled step, docs/decisions.md, 43): the run must restart before it steps
    again; the estimate it holds is not to be published."""


class Estimator:
    """A filter from :data:`FILTER_KINDS` over ``runs`` independent runs.

    Build with :func:`make_estimator`. ``step(z, u, dt)`` returns the new estimate. Its parts
    (module docstring) are public: ``state``, ``network``, ``linearisation``, ``program``,
    ``chip``.
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
        self._n_meas = model.n_meas if self.measurement is None else self.measurement.dim
        self.settings: ResolvedConfig = resolve(config, model, self.n_meas)
        spec = FILTER_KINDS[kind]
        self.spiking = spec.spiking
        self.constant_gain = self.settings.gain_schedule == 'steady_state'
        self.runs = int(runs)
        self.seeds = ([self.settings.seed + b for b in range(self.runs)] if seeds is None
                      else [int(s) for s in seeds])
        if len(self.seeds) != self.runs:
            raise ValueError(f'seeds must have {self.runs} entries, got {len(self.seeds)}')
        #: C and C^+ (H(x_hat) of a nonlinear measurement, re-linearised each step).
        self.linearisation = Linearisation(model, self.measurement, self.runs, needs_pinv=spec.gain != 'kalman')
        self._choose_laws(spec)
        s, n, m = self.settings, model.n_state, self.n_meas
        #: x_hat, P, the last gain and the guard's fault flag of every run.
        self.state = FilterState(self.runs, n, m)
        self._estimate = self._single(self.state.x_hat)  # x_hat: a view made once (~0.2 us a step)
        self._n_input, self._relinearises = model.n_input, self.linearisation.relinearises  # read every step
        #: The spiking network's arrays (empty for a non-spiking filter).
        self.network = Network(self.seeds, n, s.neuron_count if self.spiking else 0, s.decoder_variance,
                               s.silenced_neurons)
        self._none_measured = np.zeros(self.runs, dtype=np.bool_)
        self._no_measurement = np.zeros((self.runs, m))
        self._scale = np.ascontiguousarray(s.state_scale)
        self._noise = SampledNoise(model, s)
        self.steps = self.capped_steps = 0
        # precision loihi / gain_schedule switched: the network runs on snn_estimator.spiking.chip
        if chip.wanted(config) and self.measurement is not None:
            raise ValueError('the chip network (precision loihi, gain_schedule switched) holds the constant C of '
                             'the model: it takes no measurement model; use precision float64')
        net = self.network
        # the greedy rules on the factored network; the synchronous rule on the Eq. 15 network itself
        # (membranes and Omega_f, docs/decisions.md, 64)
        chip_network = SynchronousChipNetwork if s.spike_rule == 'synchronous' else chip.ChipNetwork
        self.chip = (chip_network(kind, model, config, s, net.decoder, net.alive, self.state.x_hat, net.spikes,
                                  net.total_spikes, self._chip_gains)
                     if chip.wanted(config) else None)
        #: What the network codes (schema network_coding): the estimate, or its deviation from
        #: the prediction x_pred (held in the network's ``reference``)
        self.coding = s.network_coding if self.spiking else 'state'
        if self.chip is not None and self.coding != 'state':
            raise ValueError('network_coding deviation runs on the float64 network only: use '
                             'network_coding state with precision loihi or gain_schedule switched')
        self.has_covariance = self.has_covariance and self.chip is None  # the chip computes no P
        linearized = self.spiking and s.network_drive == 'linearized'
        composition = (self.gain_law if not self.constant_gain else 'fixed', self.covariance_law, self.spiking,
                       s.spike_rule, not (model.is_linear or linearized), self.coding)
        #: The compiled step and the packed arrays it steps (the compiled loop's too).
        self.program = StepProgram(composition, self._pack(), StepDynamics(model, s.discretization, self.runs,
                                                                           linearized), self.runs)
        self.reset()

    def _choose_laws(self, spec: FilterKind) -> None:
        if self.constant_gain and (not self.model.is_linear or self.relinearises):
            raise ValueError('gain_schedule steady_state needs a linear model and measurement (the gain is '
                             'the fixed point of Eq. 6); use time_varying')
        #: The gain law of the kind (a module of snn_estimator.gains), even when held constant.
        self.gain_law = spec.gain
        covariance = spec.covariance
        if self.constant_gain and covariance == 'riccati':
            covariance = 'gain'  # a constant gain is not the Kalman gain of the current P
        self.covariance_law = covariance
        self.has_covariance = covariance != 'none'

    def _chip_gains(self, dt: float) -> list[np.ndarray]:
        """The gains the chip network holds for steps of ``dt`` (its gain source): the switched
        schedule of this filter's twin, or the steady-state gain."""
        if self.config.gain_schedule == 'switched':
            return schedule_gains(self.kind, self.model, self.config, self.settings, dt,
                                  lambda kind, config: Estimator(kind, self.model, config))
        return [steady_state_gain(self.gain_law, self.model, self.settings, dt)]

    def _pack(self) -> kernels.Packed:
        """The kernel's constants, filter state and network state, shape-checked once; the
        dt-dependent constants are set by :meth:`prepare` before the first step of a dt."""
        n, m, n_u = self.model.n_state, self.n_meas, self.model.n_input
        dims = {'runs': self.runs, 'n': n, 'm': m, 'nu': n_u, 'N': self.network.r.shape[1], 'w': n + n_u}
        return kernels.Packed(
            dims, c=self.linearisation.c, c_pinv=self.linearisation.c_pinv, q_step=np.zeros((n, n)),
            r_sample=np.eye(m), layer_step=np.zeros(m), **_settings_constants(self.settings), scale=self._scale,
            fixed_gain=np.zeros((n, m)),
            **self.state.arrays(), **self.network.arrays)

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) this filter's kernels without stepping: a node
        calls this at configure so that its first step is not its slowest."""
        self.program.warm_up(self.model.n_input, self.network.zero_noise)
        if self.spiking:
            net = self.network
            kernels.compile_for(kernels.fire_kernel(self.settings.spike_rule, self.coding), 1, net.kernel_tuple(),
                                self._scale, self.state.x_hat)

    # ------------------------------------------------------------------ what it holds
    def _single(self, array: np.ndarray) -> np.ndarray:
        return array[0] if self.runs == 1 else array

    @property
    def x_hat(self) -> np.ndarray:
        """Current estimate, shape (n,) or (runs, n)."""
        return self._estimate

    @property
    def P(self) -> np.ndarray | None:
        """Error covariance, shape (n, n) or (runs, n, n): Eq. 6, or that of the gain used
        (:attr:`covariance_law`); None for the SIF-gain filters, which compute none."""
        return self._single(self.state.p) if self.has_covariance else None

    @property
    def batch_x_hat(self) -> np.ndarray:
        """The estimates of all runs, shape (runs, n), even for one run: a read-only view the
        filter updates in place (the simulator reads it every step)."""
        return _read_only(self.state.x_hat)

    @property
    def batch_P(self) -> np.ndarray | None:
        """Covariances of all runs, (runs, n, n), read-only view; None without a covariance."""
        return _read_only(self.state.p) if self.has_covariance else None

    @property
    def batch_fault(self) -> np.ndarray:
        """True for each run whose last step left P not positive definite or its gain not
        finite, shape (runs,), read-only view (the run must restart: :class:`CovarianceLost`)."""
        return _read_only(self.state.fault)

    @property
    def batch_spikes(self) -> np.ndarray | None:
        """Spikes per neuron in the last step for all runs, (runs, N), read-only view."""
        return _read_only(self.network.spikes) if self.spiking else None

    @property
    def prediction(self) -> np.ndarray | None:
        """x_pred of network_coding deviation (x_hat = x_pred + S D r), shape (n,) or (runs, n), a
        copy; None for the paper's coding and the non-spiking filters."""
        if not self.spiking or self.coding != 'deviation':
            return None
        return self._single(self.network.reference).copy()

    @property
    def gain(self) -> np.ndarray:
        """The gain K used in the last step, shape (n, m) or (runs, n, m)."""
        return self._single(self.state.gain)

    @property
    def spikes(self) -> np.ndarray | None:
        """Spikes per neuron in the last step, shape (N,) or (runs, N); None if not spiking."""
        return self._single(self.network.spikes) if self.spiking else None

    @property
    def spike_count(self) -> int | np.ndarray:
        """Spikes emitted in the last step (per run)."""
        if not self.spiking:
            return 0
        counts = self.network.spikes.sum(axis=1)
        return int(counts[0]) if self.runs == 1 else counts

    @property
    def total_spikes(self) -> int | np.ndarray:
        """Spikes emitted since the last reset (per run)."""
        if not self.spiking:
            return 0
        total = self.network.total_spikes
        return int(total[0]) if self.runs == 1 else total.copy()

    @property
    def neuron_count(self) -> int:
        return self.settings.neuron_count if self.spiking else 0

    def _net(self, name: str) -> np.ndarray:
        if not self.spiking:
            raise AttributeError(f'{self.kind} is not a spiking filter')
        return self._single(getattr(self.network, name))

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
    def silenced(self) -> tuple:
        """Indices of the silenced neurons."""
        return tuple(int(i) for i in np.flatnonzero(~self.network.alive[0])) if self.spiking else ()

    @property
    def n_meas(self) -> int:
        """Components of the measurement the filter takes (the measurement model's, or the model's C)."""
        return self._n_meas

    @property
    def relinearises(self) -> bool:
        """True with a nonlinear measurement model (H(x_hat) each step): no least-squares start
        or restart from z = C x then."""
        return self.linearisation.relinearises

    # ------------------------------------------------------------------ where it starts
    def initial_states(self) -> np.ndarray:
        """The configured start of every run, (runs, n): initial_state, or with
        initial_state_dispersion a draw from N(initial_state, P0) seeded by the run's seed
        (stream 5), the same on every call and for a run alone or in a batch."""
        return initial_states(self.settings, self.seeds)

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
        p0 = covariance_or_error(np.broadcast_to(p0, (self.runs, n, n)), 'P0')
        self.state.put(slice(None), x0, p0)
        self.steps = self.capped_steps = self.recovery_spikes = 0
        #: Runs whose P stopped being positive definite (or gain finite) in a step, summed over steps.
        self.covariance_faults = 0
        if self.spiking:
            self.network.clear()
            for b in range(self.runs):
                self.encode(x0[b], run=b)
        self.linearisation.restart(self.state.x_hat, self._none_measured)

    def restart(self, runs) -> None:
        """Restart the runs ``runs`` (indices, or a bool per run) from their configured start
        (:meth:`initial_states`, P0) and leave every other run exactly as it is; the step and
        spike counters go on. The simulator restarts a run that diverged so that the batch can
        go on stepping (the run's later samples are discarded). Not available on the chip
        network (ValueError)."""
        if self.chip is not None:
            raise ValueError('restart() is not available on the chip network: reset() restarts every run')
        chosen = np.zeros(self.runs, dtype=bool)
        chosen[np.asarray(runs).reshape(-1)] = True
        starts = self.initial_states()
        self.state.put(chosen, starts[chosen], self.settings.initial_covariance)
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
            self.network.retire(chosen)

    def _live_arrays(self) -> dict:
        """The arrays a step writes: the filter state, H (and its pseudo-inverse) of a nonlinear
        measurement, and the network's rates, potentials, spikes and prediction."""
        arrays = dict(self.state.arrays())
        if self.relinearises:
            arrays.update(c=self.linearisation.c, c_pinv=self.linearisation.c_pinv)
        if self.spiking:
            net = self.network
            arrays.update(r=net.r, v=net.v, spikes=net.spikes, total_spikes=net.total_spikes,
                          reference=net.reference, refractory_left=net.refractory_left)
        return arrays

    def snapshot(self) -> EstimatorSnapshot:
        """Everything a step changes (estimate, covariance, gain, the network's r, v, spikes,
        total spikes and prediction, the chip network's state, the membrane-noise generators,
        the step counters), copied: :meth:`restore` returns the filter to it bit for bit, so a
        step can be taken again with another control. Settings, silenced neurons and the
        decoder are not part of it (retune and silence between the two are not undone)."""
        rngs = tuple(g.bit_generator.state for g in self.network.noise_rngs) if self.spiking else ()
        return EstimatorSnapshot(
            owner=id(self), arrays={name: array.copy() for name, array in self._live_arrays().items()},
            counters=(self.steps, self.capped_steps, self.recovery_spikes, self.covariance_faults), noise=rngs,
            chip=self.chip.snapshot() if self.chip is not None else None, call_dt=self.program.dt)

    def restore(self, snapshot: EstimatorSnapshot) -> None:
        """Return to ``snapshot`` (taken from this estimator by :meth:`snapshot`), in place:
        the kernel's packed arguments keep holding the same arrays."""
        if not isinstance(snapshot, EstimatorSnapshot) or snapshot.owner != id(self):
            raise ValueError('restore takes a snapshot() of this estimator')
        if self.chip is not None:  # first: reloading an unprepared chip writes x_hat
            self.chip.restore(snapshot.chip)
        for name, array in self._live_arrays().items():
            array[...] = snapshot.arrays[name]
        self.steps, self.capped_steps, self.recovery_spikes, self.covariance_faults = snapshot.counters
        for generator, state in zip(self.network.noise_rngs if self.spiking else (), snapshot.noise):
            generator.bit_generator.state = state
        if snapshot.call_dt is not None and snapshot.call_dt != self.program.dt:
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
            self.network.encode(run, np.zeros_like(x_hat))
            self.network.reference[run] = x_hat
            self.state.x_hat[run] = x_hat
            return
        with np.errstate(over='ignore', invalid='ignore'):  # overflow is checked and refused below
            target = np.asarray(x_hat, dtype=float) / self._scale
        if not np.isfinite(target).all():
            raise ValueError(f'cannot encode {np.asarray(x_hat).tolist()}: not finite on the network '
                             f'scale S = {self._scale.tolist()}')
        if self.chip is not None:  # the chip encodes with its own (quantized) decoder
            self.state.x_hat[run] = self.chip.encode(run, target)
            return
        try:
            decoded = self.network.encode(run, target)
        except ValueError:
            raise ValueError(f'cannot encode {np.asarray(x_hat).tolist()}: the network overflows') from None
        self.state.x_hat[run] = self._scale * decoded

    def set_state(self, x_hat, P=None) -> None:
        """Replace the estimate (and covariance) of every run, keeping the network's decoder."""
        n = self.model.n_state
        x = np.broadcast_to(np.asarray(x_hat, dtype=float), (self.runs, n))
        if not np.isfinite(x).all():
            raise ValueError('x_hat must be finite')
        covariance = (None if P is None else
                      covariance_or_error(np.broadcast_to(np.asarray(P, dtype=float), (self.runs, n, n)), 'P'))
        if self.spiking:
            for b in range(self.runs):
                self.encode(x[b], run=b)  # raises before changing the run if x is not encodable
        else:
            self.state.x_hat[:] = x
        if covariance is not None:
            self.state.p[:] = covariance
            self.state.fault[:] = False

    def silence(self, neurons: Sequence[int]) -> None:
        """Silence exactly ``neurons`` (others revive). A silenced neuron stops firing and its
        filtered train r_i and the synaptic input it sent (r_i times its Omega_f column) vanish,
        so the remaining neurons see the coding error and compensate at once by spiking
        (counted in ``total_spikes`` and ``recovery_spikes``).
        """
        self._net('r')
        if self.chip is not None:
            raise ValueError('silence() is not available on the chip network: set silenced_neurons')
        total = self.settings.neuron_count
        wanted = np.zeros(total, dtype=bool)
        indices = [int(i) for i in neurons]
        if any(i < 0 or i >= total for i in indices):
            raise ValueError(f'neuron indices must be in [0, {total - 1}], got {indices}')
        wanted[indices] = True
        net = self.network
        net.lose(wanted)
        # The survivors react on the fast time scale (instantaneous in continuous time), before
        # the slow dynamics of the next step see the decoded estimate.
        self.recovery_spikes += kernels.fire_kernel(self.settings.spike_rule, self.coding)(
            self.settings.max_spikes_per_step, net.kernel_tuple(), self._scale, self.state.x_hat)

    # ------------------------------------------------------------------ settings and steps
    def retune(self, **changes) -> None:
        """Change settings of :attr:`RETUNABLE` between steps. Validated first (the step in
        use included, once): a ValueError leaves the filter exactly as it was. A new
        ``silenced_neurons`` set silences exactly those neurons (:meth:`silence`)."""
        unknown = set(changes) - set(self.RETUNABLE)
        if unknown:
            raise ValueError(f'cannot change {sorted(unknown)} at runtime; retunable: {list(self.RETUNABLE)}')
        if self.chip is not None and changes:
            raise ValueError('the chip network holds its weights: rebuild the estimator to change them')
        config = self.config.replace(**changes)
        settings = resolve(config, self.model, self.n_meas)
        if self.program.dt is not None:  # the step size in use must still work
            self.check_time_step(self.program.dt, settings)
        self.config, self.settings = config, settings
        self._noise = SampledNoise(self.model, settings)
        self.program.update(**_settings_constants(settings))
        if self.program.dt is not None:  # Q_d, R_d and a constant gain depend on the settings too
            self._set_step(self.program.dt)
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
        changes = {'q_step': self._noise.process(dt), 'r_sample': self._noise.sample(dt),
                   'layer_step': np.full(self._n_meas, dt if self.settings.boundary_layer_mode == 'variable' else 0.0)}
        if self.constant_gain:
            changes['fixed_gain'] = np.ascontiguousarray(steady_state_gain(self.gain_law, self.model, self.settings,
                                                                           dt))
        self.program.set_step(dt, **changes)
        if self.chip is not None:
            self.chip.prepare(dt)

    def predict(self, u, dt: float) -> np.ndarray:
        """Advance by ``dt`` without a measurement (sensor dropout): K = 0, and the covariance
        predicted only (Phi P Phi^T + Q_d)."""
        return self.step(None, u, dt)

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
        runs, m, n_u = self.runs, self._n_meas, self._n_input
        if z is None:
            z, measured = self._no_measurement, self._none_measured
        else:
            z = np.ascontiguousarray(z, dtype=np.float64).reshape(runs, -1)  # the kernel's types (entry_point)
            measured = self.program.all_runs
            if valid is not None:
                measured = np.ascontiguousarray(np.broadcast_to(np.asarray(valid, dtype=np.bool_), (runs,)))
                if not measured.all():
                    z = np.where(measured[:, None], z, 0.0)
        # np.float64, not float: numpy resolves the Python type on every call (~0.15 us a call)
        u = np.ascontiguousarray(u, dtype=np.float64).reshape(runs, -1)
        if z.shape[1] != m or u.shape[1] != n_u:
            raise ValueError(f'z must have {m} and u {n_u} entries '
                             f'per run, got shapes {z.shape} and {u.shape}')
        if self._relinearises:
            measured = self.linearisation.checked(z, measured)
            if dt != self.program.dt:
                self.prepare(dt)
            z, measured = self.linearisation.relinearize(self.state.x_hat, z, measured)
        elif dt != self.program.dt:
            self.prepare(dt)  # checks dt the first time it is used
        return self._advance(z, measured, u, dt)

    def _advance(self, z, measured, u, dt: float) -> np.ndarray:
        """One kernel step of ``dt`` (prepared) with the kernel's z and measured runs (z and u
        C-contiguous float64, (runs, m) and (runs, nu): the entry point's types)."""
        dynamics, drift = self.program.dynamics(self.state.x_hat, u, dt)
        noise = self.network.zero_noise
        if self.spiking and self.settings.membrane_noise > 0.0:
            noise = self.network.noise(self.settings.membrane_noise * math.sqrt(dt))
        if self.chip is not None:  # the chip network (snn_estimator.spiking.chip) replaces the kernel
            self.chip.step(z if measured.any() else None, u, dt)
            self.steps += 1
            self.capped_steps = self.chip.capped_steps
            return self.x_hat
        status, capped = self.program.run(measured, dt, dynamics, drift, z, u, noise)
        if status == kernels.STATUS_BAD_INPUT:
            raise ValueError('z and u must be finite')
        self.steps += 1
        self.capped_steps += capped
        if status == kernels.STATUS_NON_FINITE:
            raise FloatingPointError(f'the {self.kind} state became non-finite; call reset()')
        if status == kernels.STATUS_COVARIANCE:
            self.covariance_faults += int(self.state.fault.sum())
            raise CovarianceLost(f'the {self.kind} covariance stopped being positive definite (or its gain finite) '
                                 f'in run(s) {np.flatnonzero(self.state.fault).tolist()}; restart them')
        return self.x_hat

    # ------------------------------------------------------------------ inspection
    def innovation_nis(self, z, measurement_covariance) -> np.ndarray:
        """Normalised innovation squared nu^T (C P C^T + R)^-1 nu of ``z`` against the current
        estimate, per run (R per sample; P = 0 for the covariance-free filters); infinite where
        C P C^T + R cannot be inverted (Linearisation.innovation_nis)."""
        return self.linearisation.innovation_nis(self.state.x_hat, self.state.p, z, measurement_covariance,
                                                 self.has_covariance)

    def weights(self, u=None, dt: float = 0.1, run: int = 0) -> dict:
        """The network's matrices at the current state (Eq. 16-22, :func:`network.weights`), in
        scaled units; K is the gain used in the last step (the constant gain with gain_schedule
        steady_state). With discretization='euler' and S = I these are exactly the paper's
        formulas."""
        decoder = self._net('decoder')
        decoder = decoder if self.runs == 1 else decoder[run]
        a_d, b_d = self.model.linearized_increment(self.state.x_hat[run], dt, self.settings.discretization)
        gain = (steady_state_gain(self.gain_law, self.model, self.settings, dt) if self.constant_gain
                else self.state.gain[run])
        c = self.linearisation.c
        c = c[0] if c.shape[0] == 1 else c[run]
        return weights(decoder, self._scale, a_d, b_d, gain, c, self.settings.leak_rate,
                       self.network.thresholds[run], self.coding)


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
