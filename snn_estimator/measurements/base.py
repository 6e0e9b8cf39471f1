"""The measurement-model interface and the relative geometry the sensor models share.

Frames. The state is ``[x, y, z, vx, vy, vz]`` in the target's LVLH frame as models.py defines
it (Fehse): x along-track (V-bar), y opposite the orbit normal (-H-bar), z radial toward Earth
(R-bar); right-handed. The chaser's attitude is not in the state: a sensor's axes are taken as
fixed to LVLH (the chaser holds an LVLH-fixed attitude in the final approach), turned by a
constant mounting rotation.

Line of sight. With ``p`` the chaser's position (the state's first three entries), ``v`` its
velocity, ``d`` the mounting offset (LVLH axes, m) and ``M`` the rotation from LVLH to sensor
axes, the sensor sees

* ``observer='chaser'`` (a sensor on the chaser looking at the target):
  ``l = -p - d``, ``l_dot = -v``;
* ``observer='target'`` (a sensor on the target looking at the chaser):
  ``l = p - d``, ``l_dot = v``;

and ``rho = M l`` in sensor axes, range ``r = |rho|``.

Angles (sensor axes; with the identity mounting, sensor axes = LVLH axes):

* azimuth ``atan2(rho_y, rho_x)`` in [-pi, pi): from the sensor's x axis (the boresight; LVLH
  +x, V-bar, with the identity mounting) toward its +y axis (LVLH -H-bar);
* elevation ``atan2(rho_z, hypot(rho_x, rho_y))`` in [-pi/2, pi/2]: positive toward the
  sensor's +z axis. With the identity mounting +z is R-bar, so **positive elevation is below
  the local horizontal, toward Earth**; a mounting rotation of 180 deg about x
  (``[1, 0, 0, 0]``) gives elevation positive away from Earth and azimuth toward +H-bar.

Validity (a code per sample, see REASONS): the state must be finite; the range above 0 and
``min_range``; below ``max_range`` (0: no limit); the line of sight inside the field-of-view
cone (full angle ``field_of_view`` about the sensor's x axis, as sensor_msgs/Range defines it;
2 pi: no limit); for angle models not along the sensor's z axis (azimuth undefined). h and H
are NaN only where they are undefined (r = 0; angles on the sensor's z axis): check validity
first, a filter uses a sample only where it is valid.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import Sequence

import numpy as np

from snn_estimator.validation import as_matrix, as_vector, check_choice, check_covariance, check_positive

#: Why a sample gives no measurement; index = the code in the arrays ``validity`` returns.
REASONS = ('valid', 'non_finite', 'too_close', 'too_far', 'out_of_view', 'singular', 'dropout')
VALID, NON_FINITE, TOO_CLOSE, TOO_FAR, OUT_OF_VIEW, SINGULAR, DROPOUT = range(len(REASONS))

#: How a model's measurement travels over ROS (scenario_nodes.codec maps a form to a message
#: type; a new model picks one and the codec needs no change): the measured position axes in a
#: PointStamped; one range in a sensor_msgs/Range; up to three components in model order in a
#: Vector3Stamped (NaN on unused components).
MESSAGE_FORMS = ('point', 'range', 'vector')
OBSERVERS = ('chaser', 'target')
#: An angle model's sample counts as singular (azimuth undefined) when the line of sight's
#: distance from the sensor z axis is below this fraction of the range.
SINGULAR_FRACTION = 1e-9
FULL_CIRCLE = 2.0 * math.pi


def wrap_angle(angle):
    """``angle`` wrapped into [-pi, pi)."""
    return np.mod(np.asarray(angle, dtype=float) + math.pi, FULL_CIRCLE) - math.pi


def rotation_from_quaternion(quaternion: Sequence[float]) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``[x, y, z, w]`` (tf2's order): it maps sensor-frame
    components to LVLH components, as a tf2 transform from LVLH to the sensor frame does."""
    q = as_vector(quaternion, 4, 'mounting_rotation (quaternion [x, y, z, w])')
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > 1e-6:
        raise ValueError(f'mounting_rotation must be a unit quaternion [x, y, z, w] (tf2 order); '
                         f'got {q.tolist()} of norm {norm:.9g} (identity: [0, 0, 0, 1])')
    x, y, z, w = q / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


class MeasurementModel(ABC):
    """``z = h(x) + v``, v ~ N(0, R): one sensor's measurement of the state.

    Every method takes a leading batch axis (``x`` of shape ``(..., n_state)``). Subclasses set
    ``name``, ``component_names``, ``units``, ``angle_components`` (indices wrapped at +-pi)
    and ``message_form``, and implement :meth:`h`, :meth:`jacobian` and :meth:`validity`.
    """

    name: str
    component_names: tuple[str, ...]
    units: tuple[str, ...]
    angle_components: tuple[int, ...] = ()
    message_form: str
    #: Keyword arguments the constructor takes besides ``noise`` (the registry passes these).
    parameters: tuple[str, ...] = ()
    #: False for a model without limits or angles: every finite sample is valid and nothing is
    #: wrapped, so a sensor may skip validity, check_measured and normalize (position).
    has_limits: bool = True
    #: The constant C of a linear model (h(x) = C x, nothing wrapped), else None: a filter then
    #: uses C as it is and does not re-linearise (position: exactly the model's C).
    linear_matrix: np.ndarray | None = None
    #: True for a model whose sample may lack some components (NaN: a sensor of a stacked
    #: measurement that gave nothing this step); the filter then masks them.
    partial: bool = False

    def __init__(self, noise, n_state: int = 6):
        self.n_state = int(n_state)
        m = self.dim
        label = (f'measurement_noise (R of {self.name}, {m}x{m} in '
                 + ', '.join(f'{u}^2' for u in self.units) + ')')
        self.noise = check_covariance(as_matrix(noise, (m, m), label), label)

    @property
    def dim(self) -> int:
        """Number of measured components m."""
        return len(self.component_names)

    @abstractmethod
    def h(self, x) -> np.ndarray:
        """Noise-free measurement, shape ``(..., m)``."""

    @abstractmethod
    def jacobian(self, x) -> np.ndarray:
        """``H = dh/dx`` at ``x``, shape ``(..., m, n_state)``."""

    @abstractmethod
    def validity(self, x) -> np.ndarray:
        """A REASONS code per sample for the true state ``x`` (0: it can be measured), shape ``(...)``."""

    def check_measured(self, z) -> np.ndarray:
        """A REASONS code per noisy measurement (0: publishable): e.g. a measured range below the
        sensor's minimum is discarded, as sensor_msgs/Range prescribes."""
        z = np.asarray(z, dtype=float)
        return np.where(np.isfinite(z).all(axis=-1), VALID, NON_FINITE).astype(np.int8)

    def normalize(self, z) -> np.ndarray:
        """``z`` with its angle components wrapped into [-pi, pi) (what a sensor reports)."""
        z = np.array(z, dtype=float)
        if self.angle_components:
            index = list(self.angle_components)
            z[..., index] = wrap_angle(z[..., index])
        return z

    def residual(self, z, z_predicted) -> np.ndarray:
        """``z - z_predicted`` with angle components wrapped into [-pi, pi): 179 deg against
        -179 deg is -2 deg, not 358 deg. The filters use this, never a plain difference."""
        return self.normalize(np.asarray(z, dtype=float) - np.asarray(z_predicted, dtype=float))

    def valid(self, x) -> np.ndarray:
        return self.validity(x) == VALID

    #: True when the noise of a sample depends on the true state (:meth:`noise_at`); the sensor
    #: then draws each sample with R(x). The filters take R_hat from their configuration.
    state_dependent_noise: bool = False

    def noise_at(self, x) -> np.ndarray:
        """R of a sample of the true state ``x``, shape ``(..., m, m)``: :attr:`noise` unless
        the model's noise grows with the state (a range that grows noisier with distance)."""
        x = np.asarray(x, dtype=float)
        return np.broadcast_to(self.noise, x.shape[:-1] + self.noise.shape)

    def position_of(self, z) -> np.ndarray | None:
        """The LVLH position (x, y, z) of the state that ``z`` measures, shape ``(..., 3)``, when
        one sample determines it (range and both angles); None otherwise (angles only, range,
        range rate). A filter that must re-initialise mid-flight takes it from here."""
        return None

    def describe(self) -> str:
        return (f"{self.name}: [{', '.join(self.component_names)}] in "
                f"[{', '.join(self.units)}], R diagonal {np.diagonal(self.noise).tolist()}")


class RelativeGeometry(MeasurementModel):
    """A sensor that sees the line of sight between chaser and target (module docstring):
    observer, mounting offset and rotation, field of view and range limits."""

    parameters = ('observer', 'field_of_view', 'min_range', 'max_range', 'mounting_offset',
                  'mounting_rotation', 'range_noise_growth')
    #: True for models with angle components: the sensor's z axis is a singular direction.
    has_angles = False
    #: Index of the range among the components (None: no range measured).
    range_component: int | None = None
    #: The range noise's growth with range r: sigma_r(r)^2 = R_rr + (g r^e)^2, with g =
    #: ``range_noise_growth`` (m^(1-e); a negative or None value: the model's own default
    #: below) and e = this exponent (1: a time-of-flight ranger, 0.1 % of r; 2: a camera on a
    #: pattern of known size, docking_camera). g = 0: R as given at every range.
    range_noise_exponent: int = 1
    default_range_noise_growth: float = 0.0

    def __init__(self, noise, observer: str = 'chaser', field_of_view: float = FULL_CIRCLE,
                 min_range: float = 0.0, max_range: float = 0.0, mounting_offset=(0.0, 0.0, 0.0),
                 mounting_rotation=(0.0, 0.0, 0.0, 1.0), range_noise_growth: float | None = None,
                 n_state: int = 6):
        super().__init__(noise, n_state)
        if range_noise_growth is None or float(range_noise_growth) < 0.0:
            range_noise_growth = self.default_range_noise_growth
        self.range_noise_growth = check_positive(range_noise_growth, 'range_noise_growth', strict=False)
        if self.range_noise_growth and self.range_component is None:
            raise ValueError(f'range_noise_growth: {self.name} measures no range; set it to 0')
        self.state_dependent_noise = self.range_noise_growth > 0.0
        if self.n_state < 6:
            raise ValueError(f'{self.name} needs a state [x, y, z, vx, vy, vz]; got {self.n_state} states')
        self.observer = check_choice(observer, OBSERVERS, 'observer')
        self.sign = -1.0 if observer == 'chaser' else 1.0
        self.field_of_view = check_positive(field_of_view, 'field_of_view (full cone angle, rad)')
        if self.field_of_view > FULL_CIRCLE + 1e-12:
            raise ValueError(f'field_of_view is the full cone angle in rad, at most 2 pi (no limit); '
                             f'got {field_of_view!r}')
        self.min_range = check_positive(min_range, 'min_range (m)', strict=False)
        self.max_range = check_positive(max_range, 'max_range (m; 0: no limit)', strict=False)
        if self.max_range and self.max_range <= self.min_range:
            raise ValueError(f'max_range ({max_range} m) must exceed min_range ({min_range} m), '
                             'or be 0 (no limit)')
        self.offset = as_vector(mounting_offset, 3, 'mounting_offset (m, LVLH axes)')
        #: LVLH -> sensor axes (rho = M l).
        self.rotation = rotation_from_quaternion(mounting_rotation).T
        self._cos_half_view = math.cos(min(self.field_of_view, FULL_CIRCLE) / 2.0)

    # ------------------------------------------------------------ geometry, batched
    def line_of_sight(self, x) -> np.ndarray:
        """``rho``, the line of sight in sensor axes, shape (..., 3)."""
        x = np.asarray(x, dtype=float)
        return (self.sign * x[..., 0:3] - self.offset) @ self.rotation.T

    def line_of_sight_rate(self, x) -> np.ndarray:
        """``rho_dot`` in sensor axes, shape (..., 3) (the sensor axes are fixed to LVLH)."""
        x = np.asarray(x, dtype=float)
        return (self.sign * x[..., 3:6]) @ self.rotation.T

    def _position_block(self, d_rho: np.ndarray) -> np.ndarray:
        """``dh/dp = dh/drho * sign * M`` placed in an (..., m, n_state) Jacobian."""
        out = np.zeros(d_rho.shape[:-1] + (self.n_state,))
        out[..., 0:3] = self.sign * d_rho @ self.rotation
        return out

    def validity(self, x) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        rho = self.line_of_sight(x)
        r = np.linalg.norm(rho, axis=-1)
        codes = np.zeros(r.shape, dtype=np.int8)
        finite = np.isfinite(x).all(axis=-1)
        with np.errstate(invalid='ignore'):
            checks = [(~finite, NON_FINITE), (finite & ((r <= 0.0) | (r < self.min_range)), TOO_CLOSE)]
            if self.max_range:
                checks.append((r > self.max_range, TOO_FAR))
            checks.append((rho[..., 0] < self._cos_half_view * r, OUT_OF_VIEW))
            if self.has_angles:
                checks.append((np.hypot(rho[..., 0], rho[..., 1]) <= SINGULAR_FRACTION * r, SINGULAR))
        for mask, code in reversed(checks):  # the first failing check gives the reason
            codes[mask] = code
        return codes

    def noise_at(self, x) -> np.ndarray:
        """R of a sample of ``x``: R with the range variance grown by (g r^e)^2 at the true
        range r (class attributes above); R itself where g = 0 or the range is undefined."""
        noise = super().noise_at(x)
        if not self.state_dependent_noise:
            return noise
        r = np.linalg.norm(self.line_of_sight(x), axis=-1)
        r = np.where(np.isfinite(r), r, 0.0)  # a broken truth: not measured (validity), its draw the floor's
        grown = np.square(self.range_noise_growth * r ** self.range_noise_exponent)
        noise = noise.copy()
        i = self.range_component
        noise[..., i, i] += grown
        return noise

    def check_measured(self, z) -> np.ndarray:
        codes = super().check_measured(z)
        if self.range_component is None:
            return codes
        measured = np.asarray(z, dtype=float)[..., self.range_component]
        with np.errstate(invalid='ignore'):
            too_far = (measured > self.max_range) if self.max_range else np.zeros(measured.shape, bool)
            too_close = (measured <= 0.0) | (measured < self.min_range)
        codes = np.where((codes == VALID) & too_far, TOO_FAR, codes)
        return np.where((codes == VALID) & too_close, TOO_CLOSE, codes).astype(np.int8)


def spherical(rho: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(range, azimuth, elevation, horizontal distance) of ``rho`` (..., 3); NaN where r = 0."""
    horizontal = np.hypot(rho[..., 0], rho[..., 1])
    r = np.linalg.norm(rho, axis=-1)
    azimuth = wrap_angle(np.arctan2(rho[..., 1], rho[..., 0]))
    elevation = np.arctan2(rho[..., 2], horizontal)
    bad = r <= 0.0
    if np.any(bad):
        r, azimuth, elevation = (np.where(bad, np.nan, a) for a in (r, azimuth, elevation))
    return r, azimuth, elevation, horizontal


def angle_derivatives(rho: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """d(range)/d(rho), d(azimuth)/d(rho), d(elevation)/d(rho), each (..., 3); NaN where the
    angles are undefined (on the sensor z axis or at r = 0)."""
    x, y, z = rho[..., 0], rho[..., 1], rho[..., 2]
    h2 = x * x + y * y
    r2 = h2 + z * z
    with np.errstate(divide='ignore', invalid='ignore'):
        h = np.sqrt(h2)
        r = np.sqrt(r2)
        d_range = rho / r[..., None]
        d_azimuth = np.stack([-y / h2, x / h2, np.zeros_like(x)], axis=-1)
        d_elevation = np.stack([-x * z / (r2 * h), -y * z / (r2 * h), h / r2], axis=-1)
    singular = (h <= 0.0)[..., None]
    return (d_range, np.where(singular, np.nan, d_azimuth), np.where(singular, np.nan, d_elevation))
