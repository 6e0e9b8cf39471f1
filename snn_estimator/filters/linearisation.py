"""The measurement a filter steps with: C of Eq. 3-9 and its pseudo-inverse C^+ (Eq. 7-8, 21-24),
constant for the model's C or a linear measurement model, or H(x_hat) of a nonlinear one,
re-linearised per run each step, with the equivalent linear measurement the kernel reads."""

from __future__ import annotations

import numpy as np

from snn_estimator.measurements import MeasurementModel
from snn_estimator.models import StateSpaceModel

from . import kernels


class Linearisation:
    """C and C^+ of ``runs`` runs (the arrays the step kernel's constants hold): one shared
    (1, m, n) for a linear measurement, else one per run, written in place each step.
    ``needs_pinv``: whether the gain law reads C^+ (the Kalman gain does not)."""

    def __init__(self, model: StateSpaceModel, measurement: MeasurementModel | None, runs: int, needs_pinv: bool):
        self.measurement = measurement
        #: True with a nonlinear measurement model: H(x_hat) each step.
        self.relinearises = measurement is not None and measurement.linear_matrix is None
        self.runs, self.needs_pinv = runs, needs_pinv
        n = model.n_state
        m = model.n_meas if measurement is None else measurement.dim
        if self.relinearises:
            self.c, self.c_pinv = np.zeros((runs, m, n)), np.zeros((runs, n, m))
        else:
            linear_c = model.measurement_matrix if measurement is None else measurement.linear_matrix
            self.c = np.ascontiguousarray(np.asarray(linear_c, dtype=float)[None])
            self.c_pinv = np.ascontiguousarray(np.linalg.pinv(self.c[0])[None])

    @property
    def dim(self) -> int:
        return self.c.shape[1]

    def restart(self, x_hat: np.ndarray, none_measured: np.ndarray) -> None:
        """H at the start (reset): linearised anew at ``x_hat``."""
        if self.relinearises:
            self.c[:] = 0.0
            self.relinearize(x_hat, None, none_measured)

    def relinearize(self, x_hat: np.ndarray, z, measured: np.ndarray):
        """Write H(x_hat) (and its pseudo-inverse) of every run into C, and return the equivalent
        linear measurement z_eq = residual(z, h(x_hat)) + H x_hat, so that the kernel's
        z_eq - C x_hat is the wrapped residual; and the runs measured. A run whose H or h is not
        finite at x_hat (on a singular direction) keeps its last H and is not updated."""
        model = self.measurement
        jac = model.jacobian(x_hat)
        predicted = model.h(x_hat)
        present = None if z is None or not model.partial else model.present(z)
        if present is not None:  # an absent sensor: its rows of H zero, its innovation zero
            jac = np.where(present[:, :, None], jac, 0.0)
            predicted = np.where(present, predicted, 0.0)
        finite = np.isfinite(jac).all(axis=(1, 2)) & np.isfinite(predicted).all(axis=1)
        if finite.all():
            self.c[:] = jac
        else:
            self.c[finite] = jac[finite]
        if self.needs_pinv:  # C^+ of Eq. 7-8, 21-24 (the Kalman gain needs none)
            self.c_pinv[:] = np.linalg.pinv(self.c)
        if z is None:
            return None, measured
        measured = measured & finite
        z_eq = np.einsum('bij,bj->bi', self.c, x_hat)
        residual = model.residual(z[measured], predicted[measured])
        z_eq[measured] += residual if present is None else np.where(present[measured], residual, 0.0)
        return np.ascontiguousarray(z_eq), np.ascontiguousarray(measured)

    def checked(self, z: np.ndarray, measured: np.ndarray) -> np.ndarray:
        """The runs with a measurement: ``measured``, less the runs whose every sensor is absent
        (NaN components of a stacked model); ValueError if a present component is not finite."""
        if self.measurement.partial:  # NaN components: a sensor absent this step (Stacked)
            present = self.measurement.present(z)
            measured = np.ascontiguousarray(measured & present.any(axis=1))
            if not np.isfinite(np.where(present, z, 0.0)[measured]).all():
                raise ValueError('z and u must be finite')
        elif not np.isfinite(z[measured]).all():
            raise ValueError('z and u must be finite')
        return measured

    def innovation_nis(self, x_hat: np.ndarray, p: np.ndarray, z, measurement_covariance,
                       has_covariance: bool) -> np.ndarray:
        """Normalised innovation squared nu^T (C P C^T + R)^-1 nu of ``z`` against ``x_hat``, per
        run (R per sample; P = 0 for the covariance-free filters). Infinite where C P C^T + R
        cannot be inverted: the estimate is then inconsistent with any measurement, which the
        runner's NIS check treats as such."""
        z = np.ascontiguousarray(z, dtype=float).reshape(self.runs, -1)
        r = np.ascontiguousarray(measurement_covariance, dtype=float)
        if r.shape != (z.shape[1], z.shape[1]):
            raise ValueError(f'measurement_covariance must be {z.shape[1]}x{z.shape[1]}, got {r.shape}')
        if self.relinearises:  # the wrapped residual and S = H P H^T + R at the current estimate
            model = self.measurement
            nu = model.residual(z, model.h(x_hat))
            c = model.jacobian(x_hat)
            if model.partial:  # only the sensors present (R block-diagonal)
                present = model.present(z)
                nu, c = np.where(present, nu, 0.0), np.where(present[:, :, None], c, 0.0)
            s = (c @ p @ np.swapaxes(c, 1, 2) + r if has_covariance
                 else np.broadcast_to(r, c.shape[:1] + r.shape))
            try:
                nis = np.einsum('bi,bi->b', nu, np.linalg.solve(s, nu[..., None])[..., 0])
            except np.linalg.LinAlgError:
                return np.full(self.runs, np.inf)
            return np.where(np.isfinite(nis), nis, np.inf)
        try:
            return kernels.innovation_nis(z, x_hat, self.c[0], p, r, has_covariance)
        except np.linalg.LinAlgError:
            return np.full(self.runs, np.inf)
