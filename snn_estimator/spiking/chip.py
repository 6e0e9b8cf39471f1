"""The spiking network as a neuromorphic chip runs it: integer formats and weight sets it can hold.

Two options of :class:`~snn_estimator.config.EstimatorConfig` route a spiking filter's network
here instead of the float kernel of kernels.py:

* ``precision: loihi``: weights, membrane potentials, synaptic currents (the filtered spike
  trains as the chip holds them) and decays in Intel Loihi's integer formats (bit widths are
  parameters): signed ``weight_bits`` mantissas with one shared exponent per weight matrix
  (Loihi: 8-bit weights, a weight exponent per synapse group), ``membrane_bits`` membrane
  potential and currents (Loihi: 24-bit; the membrane saturates, currents wrap around), and
  ``decay_bits`` decay constants (Loihi: 12-bit, x <- x (2^12 - d) / 2^12 rounded toward zero).
  Sources: Davies et al. 2018, "Loihi: A Neuromorphic Manycore Processor with On-Chip Learning",
  IEEE Micro 38(1):82-99 (Sec. "Neuron model": CUBA LIF with 24-bit state and 12-bit decays;
  8-bit synaptic weights with a weight exponent); Lava's bit-accurate Loihi model
  (lava-nc/lava, ``lava.proc.lif.models.PyLifModelBitAcc``: u and v 24-bit, du and dv 12-bit,
  u wraps modulo 2^23, v clipped to +-(2^23 - 1), decays rounded toward zero).
* ``gain_schedule: switched``: a few constant weight sets, the gain of set j held over
  [t_j, t_j+1) (``schedule_times``), each the mean of the time-varying gain over its interval
  and the last one the steady-state gain. Weights a chip can hold that still converge from a
  dispersed start (a single steady-state gain does not: results/neuromorphic.md).

The network is the paper's (Eq. 10-20) in the factored form the float kernel runs: every
v_i = D_i^T e reads one n-vector, the coding error e = x~ - D r (Eq. 13), so the network's
state is e and the readout x_read = D r (the filtered trains as the chip holds them: n
currents that jump by the decoder column D_i at a spike of i and decay with lambda, Eq. 11-12)
plus the N membranes v = D^T e. Per sample period (one chip tick; spikes resolved in place by
the filter's spike rule, as the float kernel does)::

    nu = z - C x_hat                                   (innovation against the readout)
    y  = A x_read + K[set] nu + B u                    (n state compartments, 8-bit weights:
                                                        A = dt (S^-1 A_d S + lambda I), K = dt S^-1 K,
                                                        B = dt S^-1 B_d; Eq. 16-17, 19-22)
    e <- decay(e) + y,  x_read <- decay(x_read),  v = D^T e
    spikes (greedy): i = argmax(v - T) while v_i > T_i:  e -= D_i, x_read += D_i, v -= D^T D_i
    x_hat = S x_read

Why factored. The dense form holds Omega_s, Omega_k (N x N) and F_k (N x m) as 8-bit weights;
rounded, they no longer map into the range of D^T, and the rounding error of Omega r (r are
spike counts in the thousands) drives v along the N - n directions no spike can cancel: the
membranes of the literal dense network in Loihi's formats grow until every sample hits the spike
cap (measured: 5000 of 5000 spikes from the first sample, against 130 in float; this module's
history). Held as D^T e, v stays in that range by construction, with every weight an 8-bit
mantissa (D, A, K, B); the fast connections Omega_f = -D^T D act through e (a spike of i
changes e by -D_i, which every neuron reads), which needs graded messages from the n state
compartments to the N neurons (Loihi 2's graded spikes; Orchard et al. 2021, "Efficient
Neuromorphic Signal Processing with Loihi 2", IEEE SiPS). The decoder is quantized first and
everything else is built from the quantized one, so the readout is exactly what the network
encodes. With ``precision: float64`` (a switched schedule in float) the same algebra runs in
float64 and reproduces the float kernel's network spike for spike for one set (test_chip.py).

What the chip cannot do is left to the host, as on Loihi: the graded inputs z and u enter as a
per-tick bias (rounded to the membrane's LSB), the decoded x_hat is read from the readout
currents, and the schedule's switch is a time signal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from scipy.optimize import nnls

from snn_estimator.schema import PRECISIONS

#: Loihi's formats (Davies et al. 2018; Lava PyLifModelBitAcc).
LOIHI_WEIGHT_BITS = 8
LOIHI_MEMBRANE_BITS = 24
LOIHI_DECAY_BITS = 12
#: The readout currents' range is this factor times the largest |x~| the start can have
#: (|S^-1 x_hat0| + 4 sigma of P0).
READOUT_HEADROOM = 8.0

#: The spike rules as the chip kernel's codes (its one compiled loop serves all three).
RULE_GREEDY, RULE_ONE_PER_STEP, RULE_ALL_ABOVE = 0, 1, 2
_RULES = {'greedy': RULE_GREEDY, 'one_per_step': RULE_ONE_PER_STEP, 'all_above': RULE_ALL_ABOVE}


def wanted(config) -> bool:
    """True when ``config`` asks for this module's network (fixed point or switched sets)."""
    return config.precision != 'float64' or config.gain_schedule == 'switched'


@dataclass(frozen=True)
class ChipFormat:
    """Bit widths of the integer network (None: float64)."""

    weight_bits: int = LOIHI_WEIGHT_BITS
    membrane_bits: int = LOIHI_MEMBRANE_BITS
    decay_bits: int = LOIHI_DECAY_BITS

    @classmethod
    def of(cls, config) -> ChipFormat | None:
        """The format of ``config`` (None for precision float64); ValueError naming the field."""
        if config.precision not in PRECISIONS:
            raise ValueError(f'precision must be one of {", ".join(PRECISIONS)}; got {config.precision!r}')
        for name, low, high in (('weight_bits', 2, 24), ('membrane_bits', 8, 52), ('decay_bits', 4, 24)):
            value = getattr(config, name)
            if isinstance(value, bool) or int(value) != value or not low <= value <= high:
                raise ValueError(f'{name} must be an integer in [{low}, {high}] (Loihi: '
                                 f'{globals()["LOIHI_" + name.upper()]}), got {value!r}')
        if config.precision == 'float64':
            return None
        if config.membrane_bits + config.decay_bits > 52:
            raise ValueError('membrane_bits + decay_bits must be <= 52 (the products are exact in float64)')
        return cls(int(config.weight_bits), int(config.membrane_bits), int(config.decay_bits))

    @property
    def mantissa_max(self) -> int:
        return 2 ** (self.weight_bits - 1) - 1

    @property
    def state_limit(self) -> int:
        """Largest magnitude of the membrane and the currents, in LSB."""
        return 2 ** (self.membrane_bits - 1) - 1


def quantize(weights: np.ndarray, lsb: float, chip: ChipFormat | None, fractional: bool = False):
    """``weights`` (real) in units of ``lsb`` as signed mantissas of weight_bits times 2^shift,
    one shift (exponent) for the whole matrix: the smallest that fits the largest entry. Without
    ``fractional`` the shift is at least 0 (integer weights on an integer state: a matrix whose
    entries are all below 2^(bits-1) LSB keeps fewer significant bits); with it, negative
    (weights on graded inputs, the product rounded to the LSB). Returns (values, shift); float64
    precision returns weights / lsb."""
    scaled = np.asarray(weights, dtype=float) / lsb
    if chip is None:
        return scaled, 0
    peak = float(np.abs(scaled).max()) if scaled.size else 0.0
    if peak == 0.0:
        return np.zeros_like(scaled), 0
    shift = math.ceil(math.log2(peak / chip.mantissa_max))
    if not fractional:
        shift = max(shift, 0)
    mantissa = np.clip(np.rint(scaled / 2.0 ** shift), -chip.mantissa_max, chip.mantissa_max)
    return mantissa * 2.0 ** shift, shift


def schedule_times(config) -> tuple[float, ...]:
    """The switch times of ``config`` (s, increasing, > 0); ValueError naming the field."""
    times = tuple(float(t) for t in (config.schedule_times or ()))
    if config.gain_schedule != 'switched':
        return ()
    if any(not math.isfinite(t) or t <= 0.0 for t in times) or any(b <= a for a, b in zip(times, times[1:])):
        raise ValueError(f'schedule_times must be increasing times > 0 s, got {list(times)}')
    return times


class ChipNetwork:
    """The network of a batched spiking :class:`~snn_estimator.filters.estimators.Estimator` in the
    chip's arithmetic. Built by the estimator (which hands over its decoder, live neurons and
    output arrays); :meth:`prepare` builds the weights for a sample period, :meth:`step`
    advances every run."""

    def __init__(self, kind: str, model, config, settings, decoder: np.ndarray, alive: np.ndarray,
                 x_hat: np.ndarray, spikes: np.ndarray, total_spikes: np.ndarray, gain_source):
        if decoder.shape[2] == 0:
            raise ValueError(f'precision {config.precision} and gain_schedule {config.gain_schedule} '
                             f'apply to the spiking filters; {kind} has no network')
        if not model.is_linear:
            raise ValueError(f'{type(model).__name__} is nonlinear: its weights follow the Jacobian at '
                             'the estimate (Eq. 17) every step; a chip network needs a linear model')
        if config.precision != 'float64' and config.gain_schedule == 'time_varying':
            raise ValueError('precision loihi needs weights a chip can hold: gain_schedule steady_state '
                             'or switched (a time-varying gain rewrites every weight each step)')
        if settings.membrane_noise > 0.0:
            raise ValueError('membrane_noise must be 0 on the chip network (its membranes read the '
                             'coding error, v = D^T e)')
        self.kind, self.model, self.config, self.settings = kind, model, config, settings
        #: dt -> the gain of each weight set (snn_estimator.filters.gain_schedule): the chip
        #: holds the gains it is given and runs no filter itself
        self._gain_source = gain_source
        self.format = ChipFormat.of(config)
        schedule_times(config)  # validate early
        self._alive = alive
        self._x_hat, self._spikes, self._total_spikes = x_hat, spikes, total_spikes
        runs, n, neurons = decoder.shape
        self.runs, self.neurons = runs, neurons
        #: the chip's unit of each state (x = unit * D r, m or m/s per unit): the package's
        #: state_scale unless a subclass chooses its own at prepare (_state_unit)
        self.unit = np.array(settings.state_scale, dtype=float)
        self._decoder_in = np.array(decoder, dtype=float)  # in the package's scaled units
        self.shifts: dict[str, int] = {}
        self._build_decoder()
        self._rates0 = np.zeros((runs, neurons))
        self._target0 = np.zeros((runs, n))
        self._dt: float | None = None
        self.steps = 0
        self.capped_steps = 0
        self.overflows = 0
        self.synops = 0
        #: the rule's code for chip_step (None for synchronous: chip_synchronous runs that network)
        self.rule = _RULES.get(settings.spike_rule)

    # ------------------------------------------------------------------ set-up
    def _build_decoder(self) -> None:
        """The decoder quantized in the chip's unit, first: every other weight is built from it."""
        decoder = self._decoder_in * (self.settings.state_scale / self.unit)[None, :, None]
        runs, n, neurons = decoder.shape
        self._x_range = self._readout_range(self.settings)
        self._read_lsb = self._decoder_lsb(decoder)
        self.decoder = np.empty_like(decoder)
        self._read = np.empty((runs, neurons, n))
        for b in range(runs):
            integers, self.shifts['decoder'] = quantize(decoder[b], self._read_lsb, self.format)
            self.decoder[b] = integers * self._read_lsb
            self._read[b] = integers.T
        # exact in the readout's LSB: v = D^T e with integer D and e, T_i = ||D_i||^2 / 2
        self._gram = np.ascontiguousarray(np.einsum('bik,bjk->bij', self._read, self._read))
        self._thresholds = 0.5 * np.einsum('bii->bi', self._gram)

    def _state_unit(self, dt: float, increment: np.ndarray) -> np.ndarray:
        """The chip's unit of each state for steps of ``dt`` (A's increment ``increment``): here the
        package's state_scale."""
        return np.array(self.settings.state_scale, dtype=float)

    def _change_unit(self, unit: np.ndarray) -> None:
        """Hold the states in ``unit``: the decoder re-quantized in it, each run re-encoded from its
        target (before the first step: the chip's state is loaded from the rates at prepare)."""
        targets = self._target0 * (self.unit / self.settings.state_scale)  # the package's scaled units
        self.unit = np.array(unit, dtype=float)
        self._build_decoder()
        for b in range(self.runs):
            self.encode(b, targets[b])

    def _readout_range(self, settings) -> float:
        """Range of the readout currents, in the chip's units: READOUT_HEADROOM x the largest |x~|
        of the start."""
        spread = np.abs(settings.initial_state) + 4.0 * np.sqrt(np.diag(settings.initial_covariance))
        return READOUT_HEADROOM * float(np.max(spread / self.unit))

    def _decoder_lsb(self, decoder: np.ndarray) -> float:
        """The readout's LSB (scaled units): the readout range over the state's range, so the
        readout currents span it (1 in float64)."""
        return self._x_range / (self.format.state_limit + 1) if self.format else 1.0

    def _realised_leak(self, dt: float) -> tuple[float, float]:
        """(decay constant, leak rate it realises in 1/s) of one tick of a sample period ``dt``:
        Loihi's round(lambda dt 2^bits) (0 in float64, where the leak is the designed one)."""
        s, fmt = self.settings, self.format
        if not fmt:
            return 0.0, s.leak_rate
        unity = 2.0 ** fmt.decay_bits
        decay_int = float(round(s.leak_rate * dt * unity))
        if decay_int >= unity:
            raise ValueError(f'leak_rate * dt = {s.leak_rate * dt} is not below 1')
        return decay_int, decay_int / (unity * dt)  # the leak the chip realises, designed for

    def _drive_weights(self, weights: np.ndarray):
        """The n state compartments' weights A, K or B (real, on graded inputs) as the chip holds
        them: one exponent for the matrix. Returns (values, shift)."""
        return quantize(weights, 1.0, self.format, fractional=True)

    def _control_weights(self, weights: np.ndarray):
        """B as the chip holds it (see :meth:`_drive_weights`)."""
        return self._drive_weights(weights)

    def encode(self, run: int, target: np.ndarray) -> np.ndarray:
        """Rates r >= 0 (NNLS over the live neurons) with D r = ``target`` (the package's scaled
        units, in the chip's unit); returns the decoded estimate unit * D r. The chip's state is
        set from r at :meth:`prepare`."""
        target = np.asarray(target, dtype=float) * (self.settings.state_scale / self.unit)
        decoder = self.decoder[run]
        alive = self._alive[run]
        rates = np.zeros(self.neurons)
        if np.any(alive):
            rates[alive], _ = nnls(decoder[:, alive], target, maxiter=50 * self.neurons)
        self._rates0[run] = rates
        self._target0[run] = target
        self.steps = 0
        if self._dt is not None:
            self._load(run)
        return self.unit * (decoder @ rates)

    def prepare(self, dt: float) -> None:
        """Build the weights of sample period ``dt`` (once: a chip network is built for one
        period; another dt raises ValueError)."""
        if self._dt is not None:
            if dt != self._dt:
                raise ValueError(f'the chip network was built for dt = {self._dt} s; got {dt} s')
            return
        s, model, fmt = self.settings, self.model, self.format
        n, m = model.n_state, model.n_meas
        unity = 2.0 ** fmt.decay_bits if fmt else 1.0
        self._decay_int, leak = self._realised_leak(dt)
        self.leak_rate = leak
        self._unity, self._decay = unity, 1.0 - leak * dt
        a_d, b_d = model.linearized_increment(None, dt, s.discretization)
        unit = self._state_unit(dt, a_d)
        if not np.array_equal(unit, self.unit):
            self._change_unit(unit)
        scale = self.unit
        lsb = self._read_lsb
        self.gains = [np.asarray(gain, dtype=float) for gain in self._gain_source(dt)]
        self.times = np.array(schedule_times(self.config))
        # y = A x_read + K nu + B u in readout LSB: x_read is in LSB already, nu in m, u in m/s^2
        self._dynamics, self.shifts['dynamics'] = self._drive_weights(
            dt * (a_d / scale[:, None] * scale[None, :] + leak * np.eye(n)))
        self._control, self.shifts['control'] = self._control_weights(dt * b_d / scale[:, None] / lsb)
        self._gain_weights = np.empty((len(self.gains), n, m))
        for j, gain in enumerate(self.gains):
            self._gain_weights[j], self.shifts[f'gain_{j}'] = self._drive_weights(dt * gain / scale[:, None] / lsb)
        self._c = np.ascontiguousarray(model.measurement_matrix * (scale * lsb)[None, :])
        self._e = np.zeros((self.runs, n))
        self._x_read = np.zeros((self.runs, n))
        self._v = np.zeros((self.runs, self.neurons))
        self._read_scale = np.ascontiguousarray(scale * lsb)
        self._dt = float(dt)
        for b in range(self.runs):
            self._load(b)

    def _load(self, run: int) -> None:
        """The chip's state of ``run`` from the encoded rates: x_read = D r, e = x~0 - D r."""
        read = self._read[run].T @ self._rates0[run]
        error = self._target0[run] / self._read_lsb - read
        if self.format:
            read, error = np.rint(read), np.rint(error)
        self._x_read[run], self._e[run] = read, error
        self._v[run] = self._read[run] @ error
        self._x_hat[run] = self._x_read[run] * self._read_scale
        self.steps = 0

    def snapshot(self) -> tuple:
        """The state a step changes (readout, coding error, potentials, counters), copied; the
        estimate and spike arrays belong to the estimator, which copies them itself."""
        arrays = None if self._dt is None else tuple(a.copy() for a in self._live())
        return arrays, tuple(getattr(self, name) for name in self._COUNTERS)

    #: The counters a snapshot keeps.
    _COUNTERS = ('steps', 'capped_steps', 'overflows', 'synops')

    def _live(self) -> tuple:
        """The arrays a step changes (a snapshot copies them, restore writes them back)."""
        return self._e, self._x_read, self._v

    def restore(self, snapshot: tuple) -> None:
        """Return to ``snapshot`` (see :meth:`snapshot`); one taken before :meth:`prepare` is
        the state loaded from the encoded rates."""
        arrays, counters = snapshot
        if arrays is None:
            if self._dt is not None:
                for b in range(self.runs):
                    self._load(b)
        else:
            for live, saved in zip(self._live(), arrays):
                live[...] = saved
        for name, value in zip(self._COUNTERS, counters):
            setattr(self, name, value)

    # ------------------------------------------------------------------ stepping
    def active_set(self) -> int:
        """The weight set in use at the current time (steps x dt since the reset)."""
        if not len(self.times):
            return 0
        return int(np.searchsorted(self.times, (self.steps + 0.5) * self._dt))

    def _inputs(self, z, u) -> tuple[bool, np.ndarray, np.ndarray]:
        """(measured, z, u) as a step's kernel takes them: z zeros when None; ValueError unless finite."""
        measured = z is not None
        z = np.zeros((self.runs, self.model.n_meas)) if z is None else np.ascontiguousarray(z, dtype=float)
        u = np.ascontiguousarray(u, dtype=float)
        if not (np.isfinite(z).all() and np.isfinite(u).all()):
            raise ValueError('z and u must be finite')
        return measured, z, u

    def step(self, z, u, dt: float) -> None:
        """Advance every run by one sample (``z`` None: no measurement, no correction)."""
        self.prepare(dt)
        measured, z, u = self._inputs(z, u)
        fmt = self.format
        limit = float(fmt.state_limit) if fmt else math.inf
        options = (fmt is not None, self.rule, self.settings.max_spikes_per_step, measured, self._unity,
                   self._decay_int, self._decay, limit)
        weights = (self._dynamics, self._gain_weights[self.active_set()], self._control, self._c, self._read,
                   self._gram, self._thresholds, self._alive, self._read_scale)
        network = (self._e, self._x_read, self._v, self._spikes, self._total_spikes, self._x_hat)
        capped, overflows, synops = chip_step(options, weights, network, z, u)
        self.steps += 1
        self.capped_steps += capped
        self.overflows += overflows
        self.synops += synops
        if not np.isfinite(self._x_hat).all():
            raise FloatingPointError('the chip network state became non-finite; call reset()')

    # ------------------------------------------------------------------ inspection
    def initial_rates(self, run: int = 0) -> np.ndarray:
        """The rates r >= 0 the last encoding chose (the state the readout was loaded from)."""
        return self._rates0[run].copy()

    @property
    def dynamics(self) -> np.ndarray:
        """A as the state compartments hold it, dt (U^-1 A_d U + lambda I) in the chip's unit U
        (:attr:`unit`), a copy (after :meth:`prepare`)."""
        if self._dt is None:
            raise ValueError('the chip network has no weights yet: call prepare(dt) or step once')
        return self._dynamics.copy()

    @property
    def potentials(self) -> np.ndarray:
        """Membrane potentials v = D^T e in scaled units, (runs, N)."""
        return self._v * self._read_lsb ** 2

    def describe(self) -> dict:
        """The formats and what they hold: LSB, shifts per weight matrix, the realised leak."""
        fmt = self.format
        return {'precision': self.config.precision,
                'weight_bits': fmt.weight_bits if fmt else None,
                'membrane_bits': fmt.membrane_bits if fmt else None,
                'decay_bits': fmt.decay_bits if fmt else None,
                'readout_lsb_scaled': self._read_lsb, 'readout_range_scaled': self._x_range,
                'weight_shifts': dict(self.shifts), 'leak_rate_realised': getattr(self, 'leak_rate', None),
                'decay_constant': self._decay_int if fmt else None,
                'weight_sets': len(getattr(self, 'gains', [])), 'switch_times_s': list(schedule_times(self.config))}


@numba.njit(cache=True)
def _decayed(value, integer, unity, decay_int, decay):
    """One tick of decay: Loihi's x (2^bits - d) / 2^bits rounded toward zero, or x (1 - lambda dt)."""
    if integer:
        product = value * (unity - decay_int)
        return math.copysign(math.floor(abs(product) / unity), product)
    return value * decay


@numba.njit(cache=True)
def _bounded(value, limit):
    """Loihi's currents wrap around modulo 2^(bits-1) (Lava PyLifModelBitAcc); returns
    (value, wrapped)."""
    if abs(value) <= limit:
        return value, False
    modulus = limit + 1.0
    magnitude = abs(value)
    return math.copysign(magnitude - modulus * math.floor(magnitude / modulus), value), True


@numba.njit(cache=True)
def chip_step(options, weights, network, z, u):
    """One sample of every run (see the module docstring). ``options`` = (integer, spike_rule,
    max_spikes, measured, unity, decay_int, decay, limit); ``weights`` = (dynamics, gain,
    control, c, read, gram, thresholds, alive, read_scale); ``network`` = (e, x_read, v,
    spikes, total_spikes, x_hat), updated in place. Integers are held in float64 (exact below
    2^53). Returns (runs whose spike loop hit max_spikes, wrapped states, synaptic operations)."""
    integer, spike_rule, max_spikes, measured, unity, decay_int, decay, limit = options
    read_scale = weights[8]
    e, x_read, v, spikes, total_spikes, x_hat = network
    runs, neurons = v.shape
    n = x_read.shape[1]
    capped = 0
    overflows = 0
    synops = 0
    nu = np.empty(z.shape[1])
    drive = np.empty(n)
    limit_spikes = 1 if spike_rule == RULE_ONE_PER_STEP else max_spikes
    for b in range(runs):
        _chip_drive(b, integer, measured, weights, x_read, z, u, nu, drive)
        for k in range(n):
            e[b, k] = _decayed(e[b, k], integer, unity, decay_int, decay) + drive[k]
            x_read[b, k] = _decayed(x_read[b, k], integer, unity, decay_int, decay)
        count = _chip_fire(b, spike_rule, limit_spikes, weights, network)
        if spike_rule == RULE_GREEDY and count >= limit_spikes:
            capped += 1
        # graded e to every neuron each tick and after each spike, the spike to e and the readout
        synops += (1 + count) * neurons * n + 2 * n * count
        total_spikes[b] += count
        if integer:
            for k in range(n):
                e[b, k], wrapped = _bounded(e[b, k], limit)
                overflows += wrapped
                x_read[b, k], wrapped = _bounded(x_read[b, k], limit)
                overflows += wrapped
        for k in range(n):
            x_hat[b, k] = x_read[b, k] * read_scale[k]
    return capped, overflows, synops


@numba.njit(cache=True)
def _chip_drive(b, integer, measured, weights, x_read, z, u, nu, drive):
    """Run b's input this sample: nu = z - C x_read (zero without a measurement), then
    drive = A x_read + K nu + B u, rounded to the LSB on the integer chip."""
    dynamics, gain, control, c = weights[0], weights[1], weights[2], weights[3]
    n, m, n_u = x_read.shape[1], z.shape[1], u.shape[1]
    for j in range(m):
        acc = 0.0
        if measured:
            acc = z[b, j]
            for k in range(n):
                acc -= c[j, k] * x_read[b, k]
        nu[j] = acc
    for k in range(n):
        acc = 0.0
        for q in range(n):
            acc += dynamics[k, q] * x_read[b, q]
        for j in range(m):
            acc += gain[k, j] * nu[j]
        for j in range(n_u):
            acc += control[k, j] * u[b, j]
        drive[k] = np.rint(acc) if integer else acc


@numba.njit(cache=True)
def _chip_fire(b, spike_rule, limit_spikes, weights, network):
    """Run b's potentials v = D^T e and its spikes by the rule (all above threshold at once, or
    the neuron furthest above, one at a time, up to ``limit_spikes``); returns the count."""
    read, gram, thresholds, alive = weights[4], weights[5], weights[6], weights[7]
    e, x_read, v, spikes = network[0], network[1], network[2], network[3]
    neurons, n = v.shape[1], e.shape[1]
    for i in range(neurons):
        acc = 0.0
        for k in range(n):
            acc += read[b, i, k] * e[b, k]
        v[b, i] = acc
        spikes[b, i] = 0
    count = 0
    if spike_rule == RULE_ALL_ABOVE:
        for i in range(neurons):
            if alive[b, i] and v[b, i] > thresholds[b, i]:
                spikes[b, i] = 1
                count += 1
        for i in range(neurons):
            if spikes[b, i]:
                _deliver(b, i, read, gram, e, x_read, v)
        return count
    while count < limit_spikes:
        best = -1
        best_over = 0.0
        for j in range(neurons):
            if alive[b, j]:
                over = v[b, j] - thresholds[b, j]
                if over > best_over:
                    best_over = over
                    best = j
        if best < 0:
            break
        spikes[b, best] += 1
        count += 1
        _deliver(b, best, read, gram, e, x_read, v)
    return count


@numba.njit(cache=True)
def _deliver(b, i, read, gram, e, x_read, v):
    """A spike of neuron i: e -= D_i, x_read += D_i, and every v_j = D_j^T e follows
    (v -= (D^T D)[:, i], Eq. 18)."""
    for k in range(e.shape[1]):
        e[b, k] -= read[b, i, k]
        x_read[b, k] += read[b, i, k]
    for j in range(v.shape[1]):
        v[b, j] -= gram[b, i, j]


def effective_weights(network: ChipNetwork, weight_set: int = 0) -> dict:
    """The dense weights (Eq. 16-20, scaled units, as Estimator.weights gives them) that the
    chip's factored network of set ``weight_set`` computes: products of its quantized factors
    (D, A, K, B), so exact numbers that a dense reader (NIR, Brian2) can run; the integer network
    differs from them only by rounding its drive y to the readout LSB each sample."""
    if network._dt is None:
        raise ValueError('the chip network has no weights yet: call prepare(dt) or step once')
    if not 0 <= weight_set < len(network.gains):
        raise ValueError(f'weight_set must be in [0, {len(network.gains) - 1}], got {weight_set}')
    dt, lsb = network._dt, network._read_lsb
    d = network.decoder[0]
    c_scaled = network._c / lsb  # C S in readout-LSB units -> C S
    k = network._gain_weights[weight_set] * lsb / dt  # S^-1 K in scaled units
    return {
        'F': d.T @ (network._control * lsb / dt),
        'Omega_s': d.T @ (network._dynamics / dt) @ d,
        'Omega_f': -d.T @ d,
        'Omega_k': -d.T @ k @ c_scaled @ d,
        'F_k': d.T @ k,
        'thresholds': 0.5 * np.einsum('ki,ki->i', d, d),
        'decoder': (network.unit / network.settings.state_scale)[:, None] * d,  # the package's scaled units
        'neurons': d.shape[1],
        'gain': network.unit[:, None] * k,
        'leak_rate': network.leak_rate,
    }
