"""``position``: the measured Cartesian position axes, ``z = C x`` (Table 6; today's sensor).

Exactly the measurement blocks.PositionSensor and the filters use: the same C (one row per
measured axis), so the noise and the numbers are identical. No field of view or range limit.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .base import NON_FINITE, TOO_CLOSE, TOO_FAR, VALID, MeasurementModel

AXIS_NAMES = ('x', 'y', 'z')


class Position(MeasurementModel):
    name = 'position'
    message_form = 'point'
    parameters = ('measured_axes',)
    has_limits = False

    def __init__(self, noise, measured_axes: Sequence[int] = (0, 1, 2), n_state: int = 6):
        axes = tuple(int(a) for a in measured_axes)
        if not axes or len(set(axes)) != len(axes) or not all(0 <= a <= 2 for a in axes):
            raise ValueError(
                f'measured_axes must be distinct position axes among 0 (x), 1 (y), 2 (z); got {axes}')
        self.measured_axes = axes
        self.component_names = tuple(AXIS_NAMES[a] for a in axes)
        self.units = ('m',) * len(axes)
        super().__init__(noise, n_state)
        self.matrix = np.zeros((len(axes), self.n_state))
        self.matrix[np.arange(len(axes)), axes] = 1.0
        self.linear_matrix = self.matrix

    def h(self, x) -> np.ndarray:
        return np.asarray(x, dtype=float) @ self.matrix.T

    def jacobian(self, x) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        return np.broadcast_to(self.matrix, x.shape[:-1] + self.matrix.shape).copy()

    def position_of(self, z) -> np.ndarray | None:
        """The position when every axis is measured, else None."""
        if sorted(self.measured_axes) != [0, 1, 2]:
            return None
        z = np.asarray(z, dtype=float)
        out = np.empty(z.shape[:-1] + (3,))
        out[..., list(self.measured_axes)] = z
        return out

    def validity(self, x) -> np.ndarray:
        finite = np.isfinite(np.asarray(x, dtype=float)).all(axis=-1)
        return np.where(finite, VALID, NON_FINITE).astype(np.int8)


class RelativeGPS(Position):
    """``relative_gps``: the position (z = C x, as :class:`Position`) from differential GPS
    between chaser and target, valid only from ``min_range`` m out (to ``max_range``, 0: no
    limit). Close to a large target its antennas see multipath and the target's shadow, so
    missions hand over to a LIDAR (HTV left relative GPS at 500 m; docs/decisions.md, 72).
    Outside its range a sensor node publishes a PointStamped of NaN ("nothing measured")."""

    name = 'relative_gps'
    parameters = ('min_range', 'max_range')
    has_limits = True

    def __init__(self, noise, min_range: float = 0.0, max_range: float = 0.0, n_state: int = 6):
        super().__init__(noise, (0, 1, 2), n_state)
        self.min_range, self.max_range = float(min_range), float(max_range)
        if not (0.0 <= self.min_range and 0.0 <= self.max_range and (not self.max_range
                                                                     or self.max_range > self.min_range)):
            raise ValueError(f'relative_gps needs 0 <= min_range < max_range (0: no limit), m; got '
                             f'{min_range!r}, {max_range!r}')

    def validity(self, x) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        finite = np.isfinite(x).all(axis=-1)
        r = np.linalg.norm(np.where(finite[..., None], x[..., :3], 0.0), axis=-1)
        codes = np.where(finite, VALID, NON_FINITE)
        codes = np.where(finite & (r < self.min_range), TOO_CLOSE, codes)
        if self.max_range:
            codes = np.where(finite & (r > self.max_range), TOO_FAR, codes)
        return codes.astype(np.int8)
