"""The live view's scene and plot values, free of ROS and of Foxglove: what the live_view node
draws, built from the pipeline's decoded messages. Two thin encoders read it: Foxglove's
SceneUpdate and JSON channels (:mod:`scenario_nodes.foxglove_view`) and RViz's
visualization_msgs/MarkerArray (:mod:`scenario_nodes.scene_markers`), so both show the same.

Frame: everything in the target's LVLH frame ``lvlh`` (metres; the target at the origin).
The scene holds the target, the chaser's true and estimated positions with their trails, the
estimate's position covariance ellipsoid at ``covariance_sigma`` sigma, the keep-out sphere,
the approach corridor (a cone with its apex at the target) and the thrust vector (the
control, m/s^2, drawn ``thrust_scale`` m per m/s^2 long from the estimated position).

Time: a frame (:class:`Frame`) carries one simulated time, the newest stamp the view has heard
of, so the frames' times never go backwards; each part keeps its own stamp inside (the plot
sample is older: the truth of an estimate's stamp arrives after it). :class:`LogClock` puts
simulated time on a real epoch (the run's start), the time a viewer shows.

Plot values (:class:`PlotSample`) pair an estimate with the truth of the same stamp: error
``x_hat - x`` per state beside 3 sigma from the published covariance, range, spikes in the
step and the NEES ``e^T P^-1 e``. The published Odometry carries only the position and velocity
blocks of P (no cross terms), so the NEES uses that block-diagonal P; it is left out (None),
never NaN, when P is not positive definite (a filter that publishes no covariance).
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from snn_estimator import defaults as D

STATES = ('x', 'y', 'z', 'vx', 'vy', 'vz')
#: Points a trail is drawn with at most (:func:`decimate`).
TRAIL_POINTS = 100
#: RGBA colours (0-1) of the scene's parts.
COLORS = {
    'target': (0.85, 0.85, 0.85, 1.0),
    'truth': (0.2, 0.8, 0.2, 1.0),
    'estimate': (0.2, 0.5, 1.0, 1.0),
    'covariance': (0.2, 0.5, 1.0, 0.35),
    'keep_out': (1.0, 0.2, 0.2, 0.15),
    'corridor': (1.0, 0.8, 0.1, 0.15),
    'thrust': (1.0, 0.4, 0.0, 1.0),
}


@dataclass(frozen=True)
class SceneSettings:
    """What the scene draws besides the states (the live_view node's parameters)."""

    covariance_sigma: float = 3.0
    keep_out_radius: float = 2.0
    #: Direction of the approach corridor's axis from the target (need not be unit length):
    #: by default the chaser's initial position (Table 6).
    corridor_axis: tuple = tuple(D.RENDEZVOUS_X0[:3])
    corridor_half_angle: float = 15.0  # deg
    corridor_length: float = 100.0  # m
    thrust_scale: float = 200.0  # m of arrow per m/s^2 of control (0.09 m/s^2 at the start: 18 m)
    trail_length: int = 500  # positions kept per trail
    target_radius: float = 1.0  # m

    def __post_init__(self):
        checks = {'covariance_sigma': self.covariance_sigma > 0, 'keep_out_radius': self.keep_out_radius >= 0,
                  'corridor_half_angle': 0 < self.corridor_half_angle < 90,
                  'corridor_length': self.corridor_length >= 0, 'thrust_scale': self.thrust_scale >= 0,
                  'trail_length': self.trail_length >= 2, 'target_radius': self.target_radius > 0,
                  'corridor_axis': len(self.corridor_axis) == 3 and np.linalg.norm(self.corridor_axis) > 0}
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f'{name} = {getattr(self, name)!r} is out of range: see the live_view '
                                 'parameters (docs/parameters.md)')


# ---------------------------------------------------------------- primitives
@dataclass(frozen=True)
class Sphere:
    """An ellipsoid: ``radii`` (m) along the axes of the rotation ``orientation`` (x, y, z, w)."""
    name: str
    center: tuple
    radii: tuple
    orientation: tuple
    color: tuple


@dataclass(frozen=True)
class Arrow:
    name: str
    start: tuple
    end: tuple
    color: tuple


@dataclass(frozen=True)
class Lines:
    """A line strip through ``points`` ((n, 3), m)."""
    name: str
    points: np.ndarray
    color: tuple
    width: float = 0.2


@dataclass(frozen=True)
class Triangles:
    """A triangle list: ``points`` (3k, 3), every three a triangle."""
    name: str
    points: np.ndarray
    color: tuple


@dataclass
class Scene:
    """One frame of the 3D view, stamped with the simulated time of its estimate."""
    stamp_ns: int
    frame_id: str
    spheres: list = field(default_factory=list)
    arrows: list = field(default_factory=list)
    lines: list = field(default_factory=list)
    triangles: list = field(default_factory=list)

    def names(self) -> list[str]:
        return [p.name for group in (self.spheres, self.arrows, self.lines, self.triangles) for p in group]

    def get(self, name: str):
        return next(p for group in (self.spheres, self.arrows, self.lines, self.triangles)
                    for p in group if p.name == name)


def quaternion_of(rotation: np.ndarray) -> tuple:
    """(x, y, z, w) of a proper rotation matrix (Shepperd's method, numerically safe)."""
    m = np.asarray(rotation, dtype=float)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s)
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + m[i, i] - m[j, j] - m[k, k], 1e-300))
        q = [0.0] * 4
        q[i] = 0.25 * s
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
        q[3] = (m[k, j] - m[j, k]) / s
    q = np.array(q)
    return tuple(float(v) for v in q / np.linalg.norm(q))


def covariance_ellipsoid(name: str, center, covariance: np.ndarray, sigma: float, color) -> Sphere:
    """The ``sigma``-sigma ellipsoid of a 3x3 covariance: radii sigma*sqrt(eigenvalues) along
    its eigenvectors (a right-handed frame). Negative eigenvalues (rounding) count as zero."""
    values, vectors = np.linalg.eigh(0.5 * (covariance + covariance.T))
    if np.linalg.det(vectors) < 0:
        vectors[:, 2] = -vectors[:, 2]
    radii = sigma * np.sqrt(np.clip(values, 0.0, None))
    return Sphere(name, tuple(float(c) for c in center), tuple(float(r) for r in radii),
                  quaternion_of(vectors), tuple(color))


def corridor_mesh(axis, half_angle_deg: float, length: float, segments: int = 32) -> np.ndarray:
    """Triangles (3k, 3) of a cone with its apex at the origin, opening along ``axis``: the
    side and the base cap."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    helper = np.array([0.0, 0.0, 1.0]) if abs(a[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(a, helper)
    u /= np.linalg.norm(u)
    v = np.cross(a, u)
    radius = length * math.tan(math.radians(half_angle_deg))
    angles = np.linspace(0.0, 2 * math.pi, segments + 1)
    rim = length * a + radius * (np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v)
    centre = length * a
    triangles = []
    for k in range(segments):
        triangles += [np.zeros(3), rim[k], rim[k + 1], centre, rim[k + 1], rim[k]]
    return np.array(triangles)


class Trail:
    """The last ``length`` positions in a ring buffer; ``points()`` gives at most
    :data:`TRAIL_POINTS` of them, oldest first, evenly spread with the oldest and the newest kept
    (a trail drawn every frame stays cheap to encode)."""

    def __init__(self, length: int):
        self._buffer = np.zeros((length, 3))
        self._count = 0

    def __len__(self) -> int:
        return min(self._count, len(self._buffer))

    def append(self, position) -> None:
        self._buffer[self._count % len(self._buffer)] = position[:3]
        self._count += 1

    def points(self, most: int = TRAIL_POINTS) -> np.ndarray:
        n, size = len(self), len(self._buffer)
        order = (self._count - n + np.linspace(0, n - 1, min(n, most)).round().astype(int)) % size
        return self._buffer[order]


# ---------------------------------------------------------------- plot values
@dataclass(frozen=True)
class PlotSample:
    """Plot values of one estimate paired with the truth of the same stamp (see the module)."""
    stamp_ns: int
    estimate: np.ndarray      # (6,)
    error: np.ndarray         # (6,) x_hat - x
    three_sigma: np.ndarray   # (6,) covariance_sigma * sqrt(diag P)
    range_true: float         # |r|, m
    range_estimated: float    # |r_hat|, m
    spikes: int | None        # spikes in the step (None: no spike count received yet)
    nees: float | None        # e^T P^-1 e with the published block-diagonal P; None if P is not PD


def nees(error: np.ndarray, covariance: np.ndarray) -> float | None:
    """e^T P^-1 e, or None when P is not positive definite (Cholesky fails) or the result is
    not finite."""
    try:
        factor = np.linalg.cholesky(covariance)
    except np.linalg.LinAlgError:
        return None
    whitened = np.linalg.solve(factor, error)
    value = float(whitened @ whitened)
    return value if math.isfinite(value) else None


@dataclass(frozen=True)
class Frame:
    """What the view sends at one instant: ``stamp_ns``, the newest simulated time heard of
    (never less than the last frame's), the scene (stamped with its estimate), the plot sample
    (None: no new one) and the raster (None: no spikes yet)."""
    stamp_ns: int
    scene: Scene | None
    sample: PlotSample | None
    raster: np.ndarray | None


class LogClock:
    """Log times of a run: simulated time (ns) on a real epoch, ``epoch_ns + stamp_ns``.

    ``epoch_ns`` None anchors the epoch at the first call: the wall-clock time then less the
    simulated time then (the run's start when the view starts with the loop, exactly so at 1x).
    A viewer then shows the run's date, and the seconds since its start are simulated seconds at
    any real-time factor."""

    def __init__(self, epoch_ns: int | None = None, wall_ns=time.time_ns):
        if epoch_ns is not None and epoch_ns < 0:
            raise ValueError(f'log_epoch = {epoch_ns * 1e-9!r} s: must be >= 0 (s since the Unix epoch; '
                             '0: the run\'s start)')
        self.epoch_ns = epoch_ns
        self._wall_ns = wall_ns

    def __call__(self, stamp_ns: int) -> int:
        if self.epoch_ns is None:
            self.epoch_ns = max(self._wall_ns() - stamp_ns, 0)
        return self.epoch_ns + stamp_ns


class LiveScene:
    """Keeps the newest decoded inputs and builds frames from them (no ROS: the node feeds it).

    ``add_truth`` / ``add_estimate`` / ``add_control`` / ``add_spikes`` take arrays; ``frame()``
    returns a :class:`Frame` (the scene, the plot sample, None until an estimate meets its
    truth, and the spike raster of the last ``raster_steps`` steps), or None when nothing new
    arrived since the last frame (nothing to send)."""

    def __init__(self, settings: SceneSettings = SceneSettings(), frame_id: str = 'lvlh',
                 raster_steps: int = 200, keep: int = 64):
        self.settings = settings
        self.frame_id = frame_id
        self._truths: dict[int, np.ndarray] = {}
        self._estimates: dict[int, tuple] = {}  # stamp_ns -> (x, P), the newest few
        self._keep = keep
        self._estimate = None  # (stamp_ns, x, P), the newest
        self._control = np.zeros(3)
        self._spike_count = None
        self._raster = deque(maxlen=raster_steps)
        self._true_trail = Trail(settings.trail_length)
        self._estimated_trail = Trail(settings.trail_length)
        self._changed = False
        self._corridor = corridor_mesh(settings.corridor_axis, settings.corridor_half_angle,
                                       settings.corridor_length)
        self.frames = 0
        self._plotted_ns = -1
        self._heard_ns = None  # the newest stamp of any input

    def _heard(self, stamp_ns: int) -> None:
        if self._heard_ns is None or stamp_ns > self._heard_ns:
            self._heard_ns = stamp_ns

    def add_truth(self, stamp_ns: int, x: np.ndarray) -> None:
        self._heard(stamp_ns)
        self._truths[stamp_ns] = np.array(x[:6], dtype=float)
        if len(self._truths) > self._keep:
            del self._truths[min(self._truths)]
        self._true_trail.append(x[:3])
        self._changed = True

    def add_estimate(self, stamp_ns: int, x: np.ndarray, covariance: np.ndarray) -> None:
        self._heard(stamp_ns)
        self._estimate = (stamp_ns, np.array(x[:6], dtype=float), np.array(covariance, dtype=float))
        self._estimates[stamp_ns] = self._estimate[1:]
        if len(self._estimates) > self._keep:
            del self._estimates[min(self._estimates)]
        self._estimated_trail.append(x[:3])
        self._changed = True

    def add_control(self, u: np.ndarray) -> None:
        self._control = np.array(u[:3], dtype=float)
        self._changed = True

    def add_spikes(self, total: int | None = None, per_neuron: np.ndarray | None = None) -> None:
        if total is not None:
            self._spike_count = int(total)
        if per_neuron is not None:
            self._raster.append(np.asarray(per_neuron))
        self._changed = True

    def newest_truth(self):
        """(stamp_ns, x) of the newest truth, or None."""
        if not self._truths:
            return None
        stamp = max(self._truths)
        return stamp, self._truths[stamp]

    def plot_sample(self) -> PlotSample | None:
        """The newest estimate whose truth (same stamp) has arrived (the estimate of t_k + dt is
        published before the truth of that time), or None."""
        paired = self._estimates.keys() & self._truths.keys()
        if not paired:
            return None
        stamp = max(paired)
        (x_hat, covariance), truth = self._estimates[stamp], self._truths[stamp]
        error = x_hat - truth
        variances = np.clip(np.diag(covariance), 0.0, None)
        return PlotSample(stamp, x_hat, error, self.settings.covariance_sigma * np.sqrt(variances),
                          float(np.linalg.norm(truth[:3])), float(np.linalg.norm(x_hat[:3])),
                          self._spike_count, nees(error, covariance))

    def scene(self) -> Scene | None:
        """The 3D scene at the newest estimate (None before the first estimate or truth)."""
        s = self.settings
        newest = self.newest_truth()
        if self._estimate is None and newest is None:
            return None
        stamp = self._estimate[0] if self._estimate is not None else newest[0]
        scene = Scene(stamp, self.frame_id)
        identity = (0.0, 0.0, 0.0, 1.0)
        r = s.target_radius
        scene.spheres.append(Sphere('target', (0.0, 0.0, 0.0), (r, r, r), identity, COLORS['target']))
        if s.keep_out_radius > 0:
            k = s.keep_out_radius
            scene.spheres.append(Sphere('keep_out', (0.0, 0.0, 0.0), (k, k, k), identity, COLORS['keep_out']))
        if s.corridor_length > 0:
            scene.triangles.append(Triangles('corridor', self._corridor, COLORS['corridor']))
        if newest is not None:
            scene.spheres.append(Sphere('chaser_true', tuple(newest[1][:3]), (0.5, 0.5, 0.5), identity,
                                        COLORS['truth']))
        if len(self._true_trail) > 1:
            scene.lines.append(Lines('trail_true', self._true_trail.points(), COLORS['truth']))
        if self._estimate is not None:
            _, x_hat, covariance = self._estimate
            scene.spheres.append(Sphere('chaser_estimate', tuple(x_hat[:3]), (0.5, 0.5, 0.5), identity,
                                        COLORS['estimate']))
            scene.spheres.append(covariance_ellipsoid('covariance', x_hat[:3], covariance[:3, :3],
                                                      s.covariance_sigma, COLORS['covariance']))
            if len(self._estimated_trail) > 1:
                scene.lines.append(Lines('trail_estimate', self._estimated_trail.points(), COLORS['estimate']))
            end = x_hat[:3] + s.thrust_scale * self._control
            scene.arrows.append(Arrow('thrust', tuple(x_hat[:3]), tuple(float(e) for e in end), COLORS['thrust']))
        return scene

    def raster(self) -> np.ndarray | None:
        """(neurons, steps) spike counts of the last steps, oldest first (None: no spikes yet;
        a network whose size changed is padded with zeros)."""
        if not self._raster:
            return None
        sizes = {len(r) for r in self._raster}
        if len(sizes) == 1:
            return np.array(self._raster, dtype=np.int64).T
        image = np.zeros((max(sizes), len(self._raster)), dtype=np.int64)
        for column, counts in enumerate(self._raster):
            image[:len(counts), column] = counts
        return image

    def frame(self) -> Frame | None:
        """The frame of what arrived since the last one, or None (nothing new, or no stamped
        input yet)."""
        if not self._changed or self._heard_ns is None:
            return None
        self._changed = False
        self.frames += 1
        sample = self.plot_sample()
        if sample is not None and sample.stamp_ns <= self._plotted_ns:
            sample = None  # plotted already
        elif sample is not None:
            self._plotted_ns = sample.stamp_ns
        return Frame(self._heard_ns, self.scene(), sample, self.raster())


def raster_image(raster: np.ndarray) -> np.ndarray:
    """A mono8 image (neurons rows, steps columns) of a raster: 255 where a neuron spiked."""
    return np.where(raster > 0, 255, 0).astype(np.uint8)


def _finite(values) -> dict:
    return {name: float(v) for name, v in zip(STATES, values) if math.isfinite(v)}


def plot_record(sample: PlotSample, epoch_ns: int = 0) -> dict:
    """The JSON-ready values of a plot sample: finite numbers only (a value that is not is left
    out, as is an absent spike count or NEES). ``timestamp``: its stamp on the real epoch
    ``epoch_ns`` (:class:`LogClock`); ``time``: simulated s (the plots' x axis)."""
    stamp = epoch_ns + sample.stamp_ns
    record = {
        'timestamp': {'sec': stamp // 1_000_000_000, 'nsec': stamp % 1_000_000_000},
        'time': sample.stamp_ns * 1e-9,
        'estimate': _finite(sample.estimate), 'error': _finite(sample.error),
        'three_sigma': _finite(sample.three_sigma), 'minus_three_sigma': _finite(-sample.three_sigma),
    }
    for name in ('range_true', 'range_estimated', 'nees'):
        value = getattr(sample, name)
        if value is not None and math.isfinite(value):
            record[name] = float(value)
    if sample.spikes is not None:
        record['spikes'] = int(sample.spikes)
    return record
