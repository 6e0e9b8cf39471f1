"""Several sensors as one measurement: the samples of the sensors one after the other.

A filter fusing sensors that sample at their own rates or within their own limits (a camera
far, a LIDAR close) takes ``z = [z_1, ..., z_s]`` with NaN on every component of a sensor that
gave nothing this step, ``h = [h_1, ..., h_s]``, ``H`` the sensors' Jacobians stacked and
``R = blockdiag(R_1, ..., R_s)`` (the sensors' noises independent). An absent sensor's rows
of H are zero and its innovation zero, which removes exactly its term from every gain law
(Eq. 6: P H^T R^-1 with R block-diagonal; Eq. 7-8: C^+ of the rows present; Eq. 14-22: the
network's weights from that C): the filter is then the filter of the sensors present
(test_measurement_filters checks it against the single sensor to 1e-12).

Not in :data:`snn_estimator.measurements.MODELS`: it is built from models, not named by a
parameter. Each sensor keeps its own message over ROS (``message_form`` 'stacked' has none).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .base import NON_FINITE, VALID, MeasurementModel


def _block_diagonal(blocks) -> np.ndarray:
    size = sum(b.shape[0] for b in blocks)
    out = np.zeros((size, size))
    start = 0
    for block in blocks:
        m = block.shape[0]
        out[start:start + m, start:start + m] = block
        start += m
    return out


class Stacked(MeasurementModel):
    name = 'stacked'
    message_form = 'stacked'
    #: NaN components (an absent sensor) are allowed in a sample: the filter masks them.
    partial = True

    def __init__(self, parts: Sequence[MeasurementModel], n_state: int = 6):
        self.parts = tuple(parts)
        if len(self.parts) < 1 or not all(isinstance(p, MeasurementModel) for p in self.parts):
            raise ValueError('a stacked measurement needs one or more measurement models')
        if any(getattr(p, 'partial', False) for p in self.parts):
            raise ValueError('a stacked measurement cannot hold another stacked one')
        if any(p.n_state != n_state for p in self.parts):
            raise ValueError(f'every sensor of a stacked measurement must take {n_state} states')
        bounds = np.cumsum([0] + [p.dim for p in self.parts])
        #: The components of sensor i: slice(bounds[i], bounds[i + 1]).
        self.slices = tuple(slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]))
        self.component_names = tuple(f'{i}.{name}' for i, p in enumerate(self.parts) for name in p.component_names)
        self.units = tuple(unit for p in self.parts for unit in p.units)
        self.angle_components = tuple(int(s.start) + c for p, s in zip(self.parts, self.slices)
                                      for c in p.angle_components)
        super().__init__(_block_diagonal([p.noise for p in self.parts]), n_state)

    def h(self, x) -> np.ndarray:
        return np.concatenate([p.h(x) for p in self.parts], axis=-1)

    def jacobian(self, x) -> np.ndarray:
        return np.concatenate([p.jacobian(x) for p in self.parts], axis=-2)

    def present(self, z) -> np.ndarray:
        """Which components of ``z`` came (their sensor's part is finite), shape of ``z``."""
        z = np.asarray(z, dtype=float)
        present = np.zeros(z.shape, dtype=bool)
        for part in self.slices:
            present[..., part] = np.isfinite(z[..., part]).all(axis=-1, keepdims=True)
        return present

    def validity(self, x) -> np.ndarray:
        """VALID where any sensor can measure ``x``; else the first sensor's reason."""
        codes = np.stack([p.validity(x) for p in self.parts], axis=-1)
        return np.where((codes == VALID).any(axis=-1), VALID, codes[..., 0]).astype(np.int8)

    def check_measured(self, z) -> np.ndarray:
        """VALID where any sensor's part is finite and publishable."""
        z = np.asarray(z, dtype=float)
        codes = np.stack([np.where(np.isfinite(z[..., s]).all(axis=-1), p.check_measured(np.nan_to_num(z[..., s])),
                                   NON_FINITE) for p, s in zip(self.parts, self.slices)], axis=-1)
        return np.where((codes == VALID).any(axis=-1), VALID, codes[..., 0]).astype(np.int8)

    def position_of(self, z):
        """The position from the first sensor present whose sample determines it, else None."""
        z = np.asarray(z, dtype=float)
        for part, s in zip(self.parts, self.slices):
            if np.isfinite(z[..., s]).all():
                position = part.position_of(z[..., s])
                if position is not None:
                    return position
        return None

    def describe(self) -> str:
        return ' + '.join(p.describe() for p in self.parts)
