"""``range_azimuth_elevation`` (LIDAR, radar) and ``line_of_sight`` (camera: the angles only).

Angles and frames as base.py states them: azimuth from the sensor x axis toward +y in
[-pi, pi), elevation positive toward the sensor's +z axis (with the identity mounting: toward
Earth). Jacobians are analytic (test_measurements checks them against finite differences).
"""

from __future__ import annotations

import numpy as np

from .base import RelativeGeometry, angle_derivatives, spherical


class RangeAzimuthElevation(RelativeGeometry):
    name = 'range_azimuth_elevation'
    component_names = ('range', 'azimuth', 'elevation')
    units = ('m', 'rad', 'rad')
    angle_components = (1, 2)
    message_form = 'vector'
    has_angles = True
    range_component = 0

    def h(self, x) -> np.ndarray:
        r, azimuth, elevation, _ = spherical(self.line_of_sight(x))
        return np.stack([r, azimuth, elevation], axis=-1)

    def jacobian(self, x) -> np.ndarray:
        d_range, d_azimuth, d_elevation = angle_derivatives(self.line_of_sight(x))
        return self._position_block(np.stack([d_range, d_azimuth, d_elevation], axis=-2))

    def position_of(self, z) -> np.ndarray:
        """The inverse of h on the position: rho from (range, azimuth, elevation), then
        p = sign (M^T rho + d) (base.py: rho = M (sign p - d), sign -1 for observer chaser)."""
        z = np.asarray(z, dtype=float)
        r, azimuth, elevation = z[..., 0], z[..., 1], z[..., 2]
        rho = np.stack([r * np.cos(elevation) * np.cos(azimuth), r * np.cos(elevation) * np.sin(azimuth),
                        r * np.sin(elevation)], axis=-1)
        return self.sign * (rho @ self.rotation + self.offset)


class LineOfSight(RelativeGeometry):
    name = 'line_of_sight'
    component_names = ('azimuth', 'elevation')
    units = ('rad', 'rad')
    angle_components = (0, 1)
    message_form = 'vector'
    has_angles = True

    def h(self, x) -> np.ndarray:
        _, azimuth, elevation, _ = spherical(self.line_of_sight(x))
        return np.stack([azimuth, elevation], axis=-1)

    def jacobian(self, x) -> np.ndarray:
        _, d_azimuth, d_elevation = angle_derivatives(self.line_of_sight(x))
        return self._position_block(np.stack([d_azimuth, d_elevation], axis=-2))
