"""``range``: the distance between the sensor and the other spacecraft (an RF link, a laser
range finder). h = |rho|; H = sign * l^T / r on the position (base.py)."""

from __future__ import annotations

import numpy as np

from .base import RelativeGeometry


class Range(RelativeGeometry):
    name = 'range'
    component_names = ('range',)
    units = ('m',)
    message_form = 'range'
    range_component = 0

    def h(self, x) -> np.ndarray:
        r = np.linalg.norm(self.line_of_sight(x), axis=-1, keepdims=True)
        return np.where(r > 0.0, r, np.nan)

    def jacobian(self, x) -> np.ndarray:
        rho = self.line_of_sight(x)
        with np.errstate(divide='ignore', invalid='ignore'):
            d_range = rho / np.linalg.norm(rho, axis=-1, keepdims=True)
        return self._position_block(d_range[..., None, :])
