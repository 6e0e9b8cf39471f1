"""The network of Eq. 15 itself in Loihi's integer formats, under the local, synchronous spike rule.

:class:`~snn_estimator.spiking.chip.ChipNetwork` runs a factored form (v = D^T e recomputed from
the coding error, graded messages from n compartments to the N neurons after every spike) with
the greedy rule. This module is what a chip with binary spikes and a membrane per neuron runs
under ``spike_rule: synchronous`` (docs/decisions.md, 58-59 and 64-65):

* N membranes v_i, integers of ``membrane_bits`` that saturate; each integrates its own input
  and the spikes of the others through the fast recurrent weights Omega_f = -D^T D (Eq. 18), an
  N x N matrix of signed ``weight_bits`` mantissas with one exponent. v is never recomputed
  from anything else.
* Per sample of dt, T = ``ticks_per_sample`` ticks. The slow part of Eq. 15,
  F u + (Omega_s + Omega_k) r + F_k z = D^T y with y = dt (A x_read + K (z - C x_read) + B u)
  (Eq. 16-17, 19-22, as the factored chip builds A, K, B), is computed once per sample by n
  state compartments (8-bit A, K, B on the readout x_read = D r) and reaches neuron i as a
  constant per-tick bias D_i^T y / T (the decoder's mantissas as weights): the input of Eq. 15
  spread over the ticks, as the float kernel spreads it.
* Each tick every membrane decays (Loihi's 12-bit decay, rounded toward zero), adds its bias,
  and every live neuron fires whose potential exceeds its own integer threshold
  (1 + w) ||D_i||^2 / 2, unless refractory or out of its firing slot ((t + i) mod K = 0): the
  float kernel's rule (kernels._synchronous_template) with the same widening, refractory ticks,
  slots and spike cap. Nothing compares one neuron with another. After the tick each spike adds
  its Omega_f column to every membrane (its own reset by subtraction included) and its decoder
  column to the n readout compartments.

The scale (Decision 64). The decoder's LSB is chosen so that every entry of the Gram matrix
D^T D of the quantized decoder is at most the weight mantissa (2^(bits-1) - 1): Omega_f is then
held exactly (mantissa = the Gram entry, exponent = the membrane's fraction bits), and
v stays D^T (x~ - D r) up to the bias rounding whatever the spike counts. Quantized at the
factored chip's LSB instead, the rounding of Omega_f multiplies the spike counts r (thousands,
no leak at 12 bits) and drives the membranes off that range (measured in Decision 64). The
price is a coarse decoder (entries of a few LSB): a network with another decoder, which is
what the readout decodes. The membrane holds ``fraction_bits`` more bits than the Gram's unit
(the largest that leaves VOLTAGE_HEADROOM times the widest threshold in range), so the per-tick
bias is rounded finely; the y the compartments send is rounded to the same fraction.

The unit (Decision 66). On the integer chip each velocity is held in the chip's own unit, within
2^0.5 of the package's state_scale, chosen at prepare so that A's kinematic coupling dt s_v / s_p
is a power of two, exact in any mantissa (at the package's 1e-3 its 8-bit rounding alone costs
the SNN-EKF ~3x float over the approach). The decoder is quantized in that unit and the estimate
read out in m and m/s.

With precision float64 (a switched schedule in float) the same algebra runs in float64 with the
float decoder: the float kernel's synchronous network, to rounding (test_chip_synchronous.py).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from snn_estimator.spiking.chip import ChipNetwork, _bounded, _chip_drive, _decayed, quantize

#: The membrane's range holds this many times the largest widened threshold (the rest of its
#: bits are fraction bits below the Gram's unit).
VOLTAGE_HEADROOM = 256.0
#: How the decoder's LSB is chosen: 'gram' (Omega_f exact at the weight width, Decision 64) or
#: 'readout' (the factored chip's: the readout range over the state's range).
DECODER_LSB_RULES = ('gram', 'readout')


class SynchronousChipNetwork(ChipNetwork):
    """The Eq. 15 network of a batched spiking estimator under the synchronous rule, in the
    chip's arithmetic (module docstring). Same interface as :class:`ChipNetwork`; the state is
    the membranes v, the readout x_read and the refractory counters."""

    def __init__(self, *args, decoder_lsb: str = 'gram', **kwargs):
        if decoder_lsb not in DECODER_LSB_RULES:
            raise ValueError(f'decoder_lsb must be one of {", ".join(DECODER_LSB_RULES)}, got {decoder_lsb!r}')
        self.decoder_lsb_rule = decoder_lsb
        super().__init__(*args, **kwargs)
        if self.settings.spike_rule != 'synchronous':
            raise ValueError(f'{type(self).__name__} runs spike_rule synchronous, got {self.settings.spike_rule!r}')
        self._refractory = np.zeros((self.runs, self.neurons), dtype=np.int64)
        #: spikes fired in the same tick as another (counted by the kernel: the rule is synchronous)
        self.ticks_with_several_spikes = 0

    # ------------------------------------------------------------------ set-up
    def _build_decoder(self) -> None:
        """The quantized decoder (the parent's), then Omega_f = -D^T D in the membrane's unit and
        the integer thresholds (module docstring)."""
        super()._build_decoder()
        s, fmt = self.settings, self.format
        if fmt and self._x_range > self._read_lsb * (fmt.state_limit + 1):
            raise ValueError(f'the readout range ({self._x_range:.3g} scaled units) exceeds membrane_bits '
                             f'{fmt.membrane_bits} at the decoder LSB {self._read_lsb:.3g}: give more membrane bits')
        widened = (1.0 + s.threshold_widening) * 0.5 * np.einsum('bii->bi', self._gram)
        if fmt:
            # the membrane's unit is 2^-f of the Gram's (LSB^2): f as large as the headroom allows
            widest = max(float(widened.max()), 1.0)
            self.fraction_bits = max(0, math.floor(math.log2(fmt.state_limit / (VOLTAGE_HEADROOM * widest))))
            unit = 2.0 ** self.fraction_bits
            omega, self.shifts['omega_f'] = quantize(-self._gram * unit, 1.0, fmt)
            self.fast_weights = np.ascontiguousarray(omega)
            self.thresholds = np.ascontiguousarray(np.floor(widened * unit))
        else:
            self.fraction_bits = 0
            self.fast_weights = np.ascontiguousarray(-self._gram)
            self.thresholds = np.ascontiguousarray(widened)

    def _state_unit(self, dt: float, increment: np.ndarray) -> np.ndarray:
        """On an integer chip, each state's unit moved (by less than 2^0.5 from the package's
        state_scale) so that its coupling into an earlier state, dt a_kq u_q / u_k, is a power of
        two where that coupling is the largest entry of A's row k, which sets the row's exponent:
        exact in any mantissa. For the relative motion: each velocity's unit, so the kinematic
        coupling dt s_v / s_p (1e-3 at the package's scale, 0.7 % off in 8 bits with its row's
        exponent) becomes 2^-10 (Decisions 65-66). The estimate is read out in m and m/s whatever the unit."""
        unit = super()._state_unit(dt, increment)
        if not self.format:
            return unit
        for q in range(1, unit.size):
            scaled = increment * unit[None, :] / unit[:, None] + self.leak_rate * np.eye(unit.size)
            rows = np.abs(dt * scaled[:q])  # the rows of A (prepare) into the states before q
            k = int(np.argmax(rows[:, q]))
            off = np.log2(rows[k, q]) - np.round(np.log2(rows[k, q])) if rows[k, q] > 0.0 else 0.0
            if rows[k, q] >= rows[k].max() and abs(off) > 1e-6:  # a unit already that close is kept
                unit[q] *= 2.0 ** -off
        return unit

    def _decoder_lsb(self, decoder: np.ndarray) -> float:
        """'gram': the smallest LSB (scaled units) at which every entry of D_q^T D_q, the Gram
        of the decoder quantized to it, fits the weight mantissa; 'readout': the factored chip's."""
        if self.decoder_lsb_rule == 'readout' or not self.format:
            return super()._decoder_lsb(decoder)
        limit = self.format.mantissa_max
        lsb = math.sqrt(float(np.einsum('bki,bki->bi', decoder, decoder).max()) / limit)
        for _ in range(200):
            integers = np.rint(decoder / lsb)
            if np.abs(np.einsum('bki,bkj->bij', integers, integers)).max() <= limit:
                return lsb
            lsb *= 1.01
        raise ValueError('no decoder LSB keeps the Gram matrix within the weight mantissa')

    def _drive_weights(self, weights: np.ndarray):
        """A, K or B with one exponent per row: the synapses into one state compartment are one
        synapse group, with their own exponent (Decision 65: with one exponent per matrix the
        position rows of B, ~1/2000 of its velocity rows, round to zero). Returns (values, shifts)."""
        if not self.format:
            return quantize(weights, 1.0, None)
        values, shifts = np.empty_like(weights), []
        for k, row in enumerate(weights):
            values[k], shift = quantize(row, 1.0, self.format, fractional=True)
            shifts.append(shift)
        return values, shifts

    def _control_weights(self, weights: np.ndarray):
        """B with each input's graded payload scaled (u_j / c_j, by the host that writes it) so that
        the largest weight of its column is a power of two, exact in any mantissa: the thrust the
        filter integrates is then not off by a rounding of up to 1/256 every sample, a bias its small
        late gain hardly corrects (Decision 65). Returns the effective weights (chip weights / c)
        and the shifts."""
        if not self.format:
            return self._drive_weights(weights)
        peaks = np.abs(weights).max(axis=0)
        columns = np.where(peaks > 0.0, 2.0 ** np.round(np.log2(np.where(peaks > 0.0, peaks, 1.0))) /
                           np.where(peaks > 0.0, peaks, 1.0), 1.0)
        values, shifts = self._drive_weights(weights * columns[None, :])
        self.input_scales = columns
        return values / columns[None, :], shifts

    def _realised_leak(self, dt: float) -> tuple[float, float]:
        """(decay constant of one tick, the leak rate it realises in 1/s): a tick decays by
        (1 - lambda dt)^(1/T), as the float kernel's; on the chip rounded to the decay bits."""
        s, fmt, ticks = self.settings, self.format, self.settings.ticks_per_sample
        per_tick = 1.0 - (1.0 - s.leak_rate * dt) ** (1.0 / ticks)
        if not fmt:
            return 0.0, s.leak_rate
        unity = 2.0 ** fmt.decay_bits
        decay_int = float(round(per_tick * unity))
        return decay_int, -math.log1p(-decay_int / unity) * ticks / dt

    def prepare(self, dt: float) -> None:
        first = self._dt is None
        super().prepare(dt)
        if first:
            # one tick's float decay (the parent's is a whole sample's)
            self._decay = (1.0 - self.leak_rate * dt) ** (1.0 / self.settings.ticks_per_sample)

    def _load(self, run: int) -> None:
        """Run ``run``'s state from the encoded rates: x_read = D r, v = D^T (x~0 - D r) in the
        membrane's unit, no neuron refractory."""
        read = self._read[run].T @ self._rates0[run]
        error = self._target0[run] / self._read_lsb - read
        v = self._read[run] @ error * 2.0 ** self.fraction_bits
        if self.format:
            read, v = np.rint(read), np.rint(v)
        self._x_read[run], self._v[run] = read, v
        self._refractory[run] = 0
        self._x_hat[run] = self._x_read[run] * self._read_scale
        self.steps = 0

    _COUNTERS = ChipNetwork._COUNTERS + ('ticks_with_several_spikes',)

    def _live(self) -> tuple:
        return self._v, self._x_read, self._refractory

    # ------------------------------------------------------------------ stepping
    def step(self, z, u, dt: float) -> None:
        """Advance every run by one sample of T ticks (``z`` None: no measurement)."""
        self.prepare(dt)
        measured, z, u = self._inputs(z, u)
        s, fmt = self.settings, self.format
        limit = float(fmt.state_limit) if fmt else math.inf
        options = (fmt is not None, measured, self._unity, self._decay_int, self._decay, limit,
                   float(2.0 ** self.fraction_bits), s.ticks_per_sample, s.refractory_ticks, s.firing_slots,
                   s.max_spikes_per_step)
        weights = (self._dynamics, self._gain_weights[self.active_set()], self._control, self._c, self._read,
                   self.fast_weights, self.thresholds, self._alive, self._read_scale)
        network = (self._v, self._x_read, self._refractory, self._spikes, self._total_spikes, self._x_hat)
        capped, overflows, synops, several = synchronous_chip_step(options, weights, network, z, u)
        self.steps += 1
        self.capped_steps += capped
        self.overflows += overflows
        self.synops += synops
        self.ticks_with_several_spikes += several
        if not np.isfinite(self._x_hat).all():
            raise FloatingPointError('the chip network state became non-finite; call reset()')

    # ------------------------------------------------------------------ inspection
    @property
    def potentials(self) -> np.ndarray:
        """Membrane potentials in scaled units, (runs, N) (the float kernel's v)."""
        return self._v * self._read_lsb ** 2 / 2.0 ** self.fraction_bits

    @property
    def membranes(self) -> np.ndarray:
        """The membranes as the chip holds them (integers in its unit on the integer chip), a copy."""
        return self._v.copy()

    def describe(self) -> dict:
        out = super().describe()
        out.update({'network': 'Eq. 15 (membranes, Omega_f), spike_rule synchronous',
                    'decoder_lsb_rule': self.decoder_lsb_rule, 'fraction_bits': self.fraction_bits,
                    'decoder_mantissa_max': float(np.abs(self._read).max()),
                    'gram_max': float(np.abs(self._gram).max())})
        return out


@numba.njit(cache=True)
def _sample_input(b, options, weights, x_read, z, u, nu, drive, bias, remainder):
    """Run b's sample input D_i^T y, y = A x_read + K nu + B u (n compartments) in the membrane's
    fraction, as a constant bias per tick plus a remainder at the first tick: on the integer chip
    floor(D_i^T y / T) and what is left, so a sample delivers D^T y exactly (a bias rounded per
    tick would add a constant current off the range of D^T, which no spike cancels)."""
    integer, measured, unit, ticks = options[0], options[1], options[6], options[7]
    read = weights[4]
    n, neurons = drive.shape[0], bias.shape[0]
    _chip_drive(b, False, measured, weights, x_read, z, u, nu, drive)
    for k in range(n):
        drive[k] = np.rint(drive[k] * unit) if integer else drive[k]
    for i in range(neurons):
        acc = 0.0
        for k in range(n):
            acc += read[b, i, k] * drive[k]
        if integer:
            bias[i] = math.floor(acc / ticks)
            remainder[i] = acc - bias[i] * ticks
        else:
            bias[i] = acc * (1.0 / ticks)
            remainder[i] = 0.0


@numba.njit(cache=True)
def _tick(b, tick, count, options, weights, network, bias, remainder, fired):
    """One chip tick of run b: every membrane decays and integrates its bias; every live neuron in
    its slot, not refractory and above its own threshold fires, all together (no comparison
    across neurons; past max_spikes none does); then each spike's Omega_f column reaches every
    membrane and its decoder row the readout. Returns (spikes so far, spikes this tick, whether
    the cap stopped one, membrane saturations)."""
    integer, unity, decay_int, decay, limit = options[0], options[2], options[3], options[4], options[5]
    refractory, slots, max_spikes = options[8], options[9], options[10]
    read, fast, thresholds, alive = weights[4], weights[5], weights[6], weights[7]
    v, x_read, refractory_left, spikes = network[0], network[1], network[2], network[3]
    neurons, n = v.shape[1], x_read.shape[1]
    fired_now = overflows = 0
    hit_cap = False
    for i in range(neurons):
        value = _decayed(v[b, i], integer, unity, decay_int, decay) + bias[i]
        if tick == 0:
            value += remainder[i]
        if value > limit or value < -limit:  # Loihi's membrane saturates
            value = math.copysign(limit, value)
            overflows += 1
        v[b, i] = value
        fire = alive[b, i] and refractory_left[b, i] == 0 and (tick + i) % slots == 0 and value > thresholds[b, i]
        if fire and count >= max_spikes:
            fire = False
            hit_cap = True
        if fire:
            count += 1
            fired_now += 1
            refractory_left[b, i] = refractory
        elif refractory_left[b, i] > 0:
            refractory_left[b, i] -= 1
        fired[i] = fire
    for k in range(n):
        x_read[b, k] = _decayed(x_read[b, k], integer, unity, decay_int, decay)
    if fired_now:
        for i in range(neurons):
            if fired[i]:
                spikes[b, i] += 1
                for j in range(neurons):
                    v[b, j] += fast[b, j, i]
                for k in range(n):
                    x_read[b, k] += read[b, i, k]
    return count, fired_now, hit_cap, overflows


@numba.njit(cache=True)
def synchronous_chip_step(options, weights, network, z, u):
    """One sample of every run (module docstring). ``options`` = (integer, measured, unity,
    decay_int, decay, limit, unit, ticks, refractory, slots, max_spikes); ``weights`` =
    (dynamics, gain, control, c, read, fast, thresholds, alive, read_scale); ``network`` = (v,
    x_read, refractory_left, spikes, total_spikes, x_hat), updated in place. Returns (runs that
    hit max_spikes, saturated or wrapped states, synaptic operations, ticks in which more than
    one neuron fired)."""
    integer, limit, ticks = options[0], options[5], options[7]
    read_scale = weights[8]
    v, x_read, spikes, total_spikes, x_hat = network[0], network[1], network[3], network[4], network[5]
    runs, neurons = v.shape
    n = x_read.shape[1]
    capped = overflows = synops = several = 0
    nu, drive = np.empty(z.shape[1]), np.empty(n)
    bias, remainder = np.empty(neurons), np.empty(neurons)
    fired = np.zeros(neurons, dtype=np.bool_)
    for b in range(runs):
        _sample_input(b, options, weights, x_read, z, u, nu, drive, bias, remainder)
        for i in range(neurons):
            spikes[b, i] = 0
        count = 0
        hit_cap = False
        for tick in range(ticks):
            count, fired_now, capped_now, saturated = _tick(b, tick, count, options, weights, network, bias,
                                                            remainder, fired)
            hit_cap = hit_cap or capped_now
            overflows += saturated
            if fired_now > 1:
                several += 1
        if hit_cap:
            capped += 1
        # per tick the bias from the n compartments (N n graded), per spike its Omega_f row and the readout
        synops += ticks * neurons * n + count * (neurons + n)
        total_spikes[b] += count
        if integer:
            for k in range(n):
                x_read[b, k], wrapped = _bounded(x_read[b, k], limit)
                overflows += wrapped
        for k in range(n):
            x_hat[b, k] = x_read[b, k] * read_scale[k]
    return capped, overflows, synops, several
