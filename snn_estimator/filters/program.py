"""What one filter step runs: the compiled kernel of a filter's composition, the arrays it steps
(packed once), the model input of a step, and the constants that depend on the step length.

The Estimator steps through its :class:`StepProgram`; the compiled Monte-Carlo loop
(snn_estimator.sim.compiled_loop) runs the same kernel on the same arrays inside its own loop,
through the program's public ``kernel``, ``constants``, ``state``, ``network`` and ``dynamics``.
"""

from __future__ import annotations

import numpy as np

from snn_estimator.config import ResolvedConfig, gain_noise_density
from snn_estimator.models import DT_CACHE_SIZE, StateSpaceModel

from . import kernels, model_kernels


class StepDynamics:
    """The kernel's per-step model input: packed [A_d | B_d] (n x (n + nu); one shared block,
    cached per dt, for a linear model), with which a step is x + dt (A_d x + B_d u) and the
    covariance's transition Phi = I + dt A_d, plus the nonlinear drift a direct filter on a
    nonlinear model integrates itself (its A_d is then only the covariance's).

    A nonlinear model with a compiled twin (:mod:`model_kernels`: NonlinearCircular) gets both
    from one compiled call per step, written into arrays held here (valid until the next call);
    any other (Van der Pol) from the model's numpy ``linearized_increment`` and ``transition``.
    One call outside the step kernel rather than a piece inside it: the kernel reads the
    dynamics as it reads H, knowing no model, and the call itself costs ~0.2 us (through its
    entry point) of the ~2.5 us this takes per step, mostly the exponential (docs/decisions.md, 62)."""

    def __init__(self, model: StateSpaceModel, method: str, runs: int, linearized: bool):
        #: ``linearized``: the network integrates A(x_hat) x_hat (Eq. 14, 17); otherwise the
        #: nonlinear f is integrated (a direct filter, or network_drive: nonlinear)
        self.model, self.method, self.runs, self.linearized = model, method, runs, linearized
        self._linear_cache: dict[float, np.ndarray] = {}
        self._last_linear: tuple[float, np.ndarray] | None = None  # the block of the last dt
        self.no_drift = np.zeros((1, model.n_state))
        #: The model's parameters for model_kernels.step_dynamics (None: numpy)
        self._params = None if model.is_linear else model_kernels.compiled_params(model)
        if self._params is not None:
            n, n_u = model.n_state, model.n_input
            self._b = np.ascontiguousarray(model.input_matrix, dtype=float)
            self._packed, self._drift = np.zeros((runs, n, n + n_u)), np.zeros((runs, n))
            self._exact, self._u_shape = method == 'exact', (runs, n_u)
            self._result = (self._packed, self.no_drift if linearized else self._drift)
            self._entry = None  # step_dynamics' entry point for its argument types (kernels.entry_point)

    @property
    def compiled(self) -> bool:
        """True when a nonlinear model's dynamics come from its compiled twin (model_kernels)."""
        return self._params is not None

    @property
    def cached_steps(self) -> int:
        """Step lengths whose linear block is cached (bounded by DT_CACHE_SIZE)."""
        return len(self._linear_cache)

    def __call__(self, x_hat: np.ndarray, u: np.ndarray, dt: float):
        model, method = self.model, self.method
        if model.is_linear:
            last = self._last_linear
            if last is not None and last[0] == dt:  # the usual case: the same dt as the last step
                return last[1], self.no_drift
            cached = self._linear_cache.get(dt)
            if cached is None:
                a_d, b_d = model.linearized_increment(None, dt, method)
                cached = np.ascontiguousarray(np.concatenate([a_d, b_d], axis=1)[None])
                if len(self._linear_cache) >= DT_CACHE_SIZE:
                    self._linear_cache.clear()
                self._linear_cache[dt] = cached
            self._last_linear = (dt, cached)
            return cached, self.no_drift
        if self._params is not None:
            return self._compiled(x_hat, u, dt)
        runs = self.runs
        a_d, b_d = model.linearized_increment(x_hat, dt, method)  # A(x_hat) held over the step (Eq. 17)
        b_d = np.broadcast_to(b_d, (runs,) + b_d.shape[-2:])
        packed = np.ascontiguousarray(np.concatenate([a_d, b_d], axis=2))
        if self.linearized:  # the network implements the linearised drift A(x_hat) x_hat (Eq. 17)
            return packed, self.no_drift
        # the non-spiking twin (and a network with network_drive: nonlinear) integrates f itself
        drift = (model.transition(x_hat, u, dt, method) - x_hat) / dt
        return packed, np.ascontiguousarray(drift)

    def _compiled(self, x_hat: np.ndarray, u: np.ndarray, dt: float):
        """[A_d | B_d] and the drift from model_kernels.step_dynamics, through its entry point
        after the first call (the arguments' types are fixed here: C-contiguous float64 arrays
        of the shapes checked, a float and two bools)."""
        x_hat = np.ascontiguousarray(x_hat, dtype=float)
        u = np.ascontiguousarray(u, dtype=float)
        if x_hat.shape != self._drift.shape or u.shape != self._u_shape:
            raise ValueError(f'x_hat and u must be {self._drift.shape} and {self._u_shape}, got {x_hat.shape} '
                             f'and {u.shape}')
        if self._entry is not None:  # the hot path: no tuple built, no dispatch
            self._entry(self._params, self._b, x_hat, u, float(dt), self._exact, self.linearized, self._packed,
                        self._drift)
            return self._result
        args = (self._params, self._b, x_hat, u, float(dt), self._exact, self.linearized, self._packed, self._drift)
        model_kernels.step_dynamics(*args)
        self._entry = kernels.entry_point(model_kernels.step_dynamics, args)
        return self._result

    def loop_model(self) -> tuple:
        """What a compiled caller (snn_estimator.sim.compiled_loop) passes to
        model_kernels.step_dynamics before each kernel step: (compiled, params, B, exact,
        linearized, [A_d | B_d], drift), the last two the arrays a call returns, written in
        place. Not compiled (a linear model's dynamics are constant): placeholders of the same
        types, so one compiled caller serves both."""
        if self._params is None:
            n, n_u = self.model.n_state, self.model.n_input
            return False, np.zeros(2), np.zeros((n, n_u)), False, False, np.zeros((1, n, n + n_u)), np.zeros((1, n))
        return (True, self._params, self._b, self._exact, self.linearized, self._packed, self._drift)

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) the compiled twin's step, if the model has one."""
        if self._params is not None:
            kernels.compile_for(model_kernels.step_dynamics, self._params, self._b, self._drift,
                                np.zeros((self.runs, self._b.shape[1])), 0.1, True, True, self._packed, self._drift)


class SampledNoise:
    """The noise terms of a sampled step of ``dt`` (docs/decisions.md, 43): Q_d, the covariance
    the process noise of density Q_hat adds (Van Loan's integral for a linear model with
    discretization exact, Q_hat dt otherwise; cached per dt), and R_d = R / dt, a sample's
    variance (R of Eq. 5-6)."""

    def __init__(self, model: StateSpaceModel, settings: ResolvedConfig):
        self.model, self.settings = model, settings
        self._process: dict[float, np.ndarray] = {}

    def process(self, dt: float) -> np.ndarray:
        cached = self._process.get(dt)
        if cached is None:
            s = self.settings
            exact = self.model.is_linear and s.discretization == 'exact'
            cached = np.ascontiguousarray(self.model.process_noise_discrete(s.q_hat, dt) if exact else s.q_hat * dt)
            if len(self._process) >= DT_CACHE_SIZE:
                self._process.clear()
            self._process[dt] = cached
        return cached

    def sample(self, dt: float) -> np.ndarray:
        return np.ascontiguousarray(gain_noise_density(self.settings, dt) / dt)


class StepProgram:
    """A filter's compiled step and the arrays it reads and writes.

    ``composition`` is the argument tuple of :func:`kernels.step_kernel` (gain law, covariance
    law, spiking, spike rule, drift, coding); ``packed`` the :class:`kernels.Packed` constants,
    filter state and network arrays (updated in place by the kernel); ``dynamics`` the
    :class:`StepDynamics` of the filter's model. :meth:`run` steps every run through the kernel
    called on one packed object, then through its compiled entry point (no per-call dispatch);
    ``kernel`` is the same kernel on the three tuples, for a caller that steps them in its own
    compiled loop."""

    def __init__(self, composition: tuple, packed: kernels.Packed, dynamics: StepDynamics, runs: int):
        self.composition = composition
        #: The step kernel on the (constants, state, network) tuples.
        self.kernel = kernels.step_kernel(*composition)
        self._packed_kernel = kernels.step_kernel(*composition, packed=True)
        self.packed = packed
        self.dynamics = dynamics
        #: Every run measured (the kernel's ``measured`` when all are).
        self.all_runs = np.ones(runs, dtype=np.bool_)
        #: The step length the dt constants were set for (None: not yet).
        self.dt: float | None = None
        self._entry = None  # the packed kernel's entry point for the step's argument types

    #: A hash of the sources the kernels are compiled from (a compiled caller's cache key).
    DIGEST = kernels.DIGEST

    @property
    def constants(self) -> tuple:
        """The kernel's constants (kernels.CONSTANTS), read each call: a retune rebuilds them."""
        return self.packed.constants

    @property
    def state(self) -> tuple:
        return self.packed.state

    @property
    def network(self) -> tuple:
        return self.packed.network

    @property
    def on_entry_point(self) -> bool:
        """True once steps go through the compiled entry point (no per-call type dispatch)."""
        return self._entry is not None and self._entry is not self._packed_kernel

    def set_step(self, dt: float, **constants) -> None:
        """The constants of steps of ``dt`` (kernels.STEP_CONSTANTS), written in place."""
        self.packed.update(**constants)
        self.dt = dt

    def update(self, **constants) -> None:
        """Constants that follow the settings (a retune)."""
        self.packed.update(**constants)

    def run(self, measured: np.ndarray, dt: float, dynamics: np.ndarray, drift: np.ndarray, z: np.ndarray,
            u: np.ndarray, noise: np.ndarray) -> tuple[int, int]:
        """One kernel step of every run; (status, runs whose spikes hit the cap). ``z`` and ``u``
        C-contiguous float64 (runs, m) and (runs, nu), ``measured`` a bool per run: the entry
        point reads the types of the first call (kernels.entry_point)."""
        args = (self.packed.ref, measured, float(dt), dynamics, drift, z, u, noise)
        if self._entry is None:  # the first step: through numba's dispatch, then its entry point
            result = self._packed_kernel(*args)
            self._entry = kernels.entry_point(self._packed_kernel, args)
            return result
        return self._entry(*args)

    def warm_up(self, n_input: int, noise: np.ndarray) -> None:
        """Compile (or load from numba's cache) the packed kernel without stepping."""
        runs, m = self.all_runs.size, self.packed.constants[1].shape[2]
        n = self.dynamics.model.n_state
        kernels.compile_for(self._packed_kernel, self.packed.ref, self.all_runs, 0.1, np.zeros((1, n, n + n_input)),
                            self.dynamics.no_drift, np.zeros((runs, m)), np.zeros((runs, n_input)), noise)
        self.dynamics.warm_up()
