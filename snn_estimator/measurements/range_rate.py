"""``range_rate``: the rate of change of the range (Doppler of an RF link or a radar).

r_dot = l . l_dot / r with l = sign p - d, l_dot = sign v (base.py; the mounting offset is
constant in LVLH axes). H on the position: sign (l_dot - r_dot l/r) / r; on the velocity:
sign l / r. The rotation drops out (a scalar), but the field of view uses it.
"""

from __future__ import annotations

import numpy as np

from .base import RelativeGeometry


class RangeRate(RelativeGeometry):
    name = 'range_rate'
    component_names = ('range_rate',)
    units = ('m/s',)
    message_form = 'vector'

    def _geometry(self, x):
        x = np.asarray(x, dtype=float)
        los = self.sign * x[..., 0:3] - self.offset
        los_rate = self.sign * x[..., 3:6]
        r = np.linalg.norm(los, axis=-1, keepdims=True)
        with np.errstate(divide='ignore', invalid='ignore'):
            unit = np.where(r > 0.0, los / r, np.nan)
        return los_rate, r, unit

    def h(self, x) -> np.ndarray:
        los_rate, _, unit = self._geometry(x)
        return np.sum(unit * los_rate, axis=-1, keepdims=True)

    def jacobian(self, x) -> np.ndarray:
        los_rate, r, unit = self._geometry(x)
        rate = np.sum(unit * los_rate, axis=-1, keepdims=True)
        out = np.zeros(unit.shape[:-1] + (1, self.n_state))
        with np.errstate(divide='ignore', invalid='ignore'):
            out[..., 0, 0:3] = self.sign * (los_rate - rate * unit) / r
        out[..., 0, 3:6] = self.sign * unit
        return out
