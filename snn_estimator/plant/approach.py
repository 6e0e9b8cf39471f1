"""Approach guidance (issue 39, part 2): hold points on V-bar with a go/no-go each, a cone
corridor to the docking port, a collision-avoidance manoeuvre (CAM) when the estimate's 3-sigma
leaves it. Frame and state as the relative-motion models (x along V-bar, z toward Earth; the
target's docking port at the origin, the chaser behind it at x < 0). SI units, time in s.

Each part owns its state and is read and tested alone: :class:`GoNoGo` decides one hold from
the estimate and its covariance, :class:`Corridor` is the cone's geometry, and
:class:`ApproachGuidance` holds the sequence (hold, transfer, final approach, abort) and gives
the LQR its setpoint, u = u_ff - K (x_hat - x_ref) (docs/decisions.md, 55-57).
:class:`OutOfPlaneHop` flies the observability manoeuvre of an angles-only far phase at a hold,
before its go/no-go starts (docs/decisions.md, 74).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: ISS keep-out sphere radius, m, and approach ellipsoid semi-axes (x, y, z), m (SSP 50011 via
#: NASA/JSC DuPont 2005: 200 m; 4 x 2 x 2 km).
KEEP_OUT_RADIUS = 200.0
APPROACH_ELLIPSOID = (2000.0, 1000.0, 1000.0)

GO, NO_GO = 'go', 'no_go'
#: The phases of a flying approach, and those that end it without contact.
ACTIVE_PHASES, ENDS_WITHOUT_CONTACT = ('hold', 'transfer', 'final'), ('abort', NO_GO)


@dataclass(frozen=True)
class HoldPoint:
    """A hold ``distance`` m behind the target on V-bar (x = -distance) and its go criteria:
    the estimated position within ``error_bound`` m of the hold, the position's 3-sigma
    (3 sqrt of the largest eigenvalue of P's position block) below ``sigma_bound`` m, the
    estimated speed below ``speed_bound`` m/s, all three without a break for ``dwell`` s; no-go
    when that has not happened ``timeout`` s after the vehicle reached the hold."""

    name: str
    distance: float
    error_bound: float
    sigma_bound: float
    speed_bound: float
    dwell: float
    timeout: float

    @property
    def state(self) -> np.ndarray:
        return np.array([-self.distance, 0.0, 0.0, 0.0, 0.0, 0.0])


def position_three_sigma(covariance) -> float:
    """3 sqrt(lambda_max) of the position block of a 6x6 covariance, m."""
    return 3.0 * float(np.sqrt(max(np.linalg.eigvalsh(np.asarray(covariance)[:3, :3])[-1], 0.0)))


class GoNoGo:
    """The go/no-go of one hold, from the estimate and its covariance (never the truth)."""

    def __init__(self, hold: HoldPoint, arrived: float):
        self.hold = hold
        self.arrived = float(arrived)
        self.ok_since: float | None = None
        self.decision: str | None = None
        self.decided_at: float | None = None

    def criteria(self, x_hat, covariance) -> dict[str, float]:
        """Hold error (m), position 3-sigma (m) and speed (m/s) of the estimate."""
        x_hat = np.asarray(x_hat, dtype=float)
        return {'error': float(np.linalg.norm(x_hat[:3] - self.hold.state[:3])),
                'three_sigma': position_three_sigma(covariance),
                'speed': float(np.linalg.norm(x_hat[3:6]))}

    def update(self, t: float, x_hat, covariance) -> str | None:
        """Go, no-go or None (undecided) at time ``t`` s; a decision is final."""
        if self.decision is not None:
            return self.decision
        c, hold = self.criteria(x_hat, covariance), self.hold
        ok = c['error'] <= hold.error_bound and c['three_sigma'] <= hold.sigma_bound and c['speed'] <= hold.speed_bound
        self.ok_since = (self.ok_since if self.ok_since is not None else t) if ok else None
        if self.ok_since is not None and t - self.ok_since >= hold.dwell:
            self.decision, self.decided_at = GO, t
        elif t - self.arrived >= hold.timeout:
            self.decision, self.decided_at = NO_GO, t
        return self.decision


@dataclass(frozen=True)
class Corridor:
    """A cone about -V-bar with its apex at the docking port: radius
    ``apex_radius + tan(half_angle) (-x)`` m at along-track position x; it applies within
    ``length`` m of the port (inside the keep-out sphere)."""

    half_angle: float = np.radians(10.0)
    apex_radius: float = 0.1
    length: float = KEEP_OUT_RADIUS

    def radius(self, x: float) -> float:
        return self.apex_radius + np.tan(self.half_angle) * max(-float(x), 0.0)

    def applies(self, p) -> bool:
        return -float(p[0]) <= self.length

    @staticmethod
    def lateral(p) -> float:
        return float(np.hypot(p[1], p[2]))

    def contains(self, p) -> bool:
        """True when position ``p`` (m) is inside the cone (or where the corridor does not apply)."""
        return not self.applies(p) or self.lateral(p) <= self.radius(p[0])

    def three_sigma_lateral(self, x_hat, covariance) -> float:
        """Estimated lateral offset plus 3 sqrt(lambda_max) of P's (y, z) block, m."""
        block = np.asarray(covariance)[1:3, 1:3]
        return self.lateral(x_hat) + 3.0 * float(np.sqrt(max(np.linalg.eigvalsh(block)[-1], 0.0)))

    def estimate_leaves(self, x_hat, covariance) -> bool:
        """True when the estimate's 3-sigma lateral bound reaches outside the cone."""
        return self.applies(x_hat) and self.three_sigma_lateral(x_hat, covariance) > self.radius(x_hat[0])


@dataclass(frozen=True)
class Leg:
    """A transfer along V-bar: the setpoint's speed toward the next hold is
    ``clip((s - s_next) / time_constant, min_speed, max_speed)`` m/s (s its distance behind the
    target), changed by at most ``max_acceleration`` m/s^2."""

    max_speed: float
    time_constant: float
    min_speed: float
    max_acceleration: float = 2e-3


@dataclass(frozen=True)
class ObservabilityManoeuvre:
    """An out-of-plane hop at the hold named ``hold``: ``delay`` s after the vehicle reached it,
    a burn of n ``size`` m/s along y starts the free out-of-plane oscillation y = size sin(n t),
    a second burn half an orbit later, back on V-bar, stops it (:class:`OutOfPlaneHop`)."""

    hold: str
    size: float
    delay: float

    def __post_init__(self):
        if not self.size or not np.isfinite(self.size):
            raise ValueError(f'the observability hop needs a finite, non-zero size (m); got {self.size!r}')
        if not (np.isfinite(self.delay) and self.delay >= 0.0):
            raise ValueError(f'the observability hop delay is s after arrival, finite and >= 0; got {self.delay!r}')


class OutOfPlaneHop:
    """The observability manoeuvre of one hold, flown once: 'waiting' until ``arrived + delay``,
    then 'flying' half an orbit on the free out-of-plane oscillation, then 'done'.

    Why out of plane: bearings alone cannot tell x from k x while the chaser sits on V-bar
    (Woffinden & Geller 2009: with linear dynamics the range is observable only through a
    known thrust that moves the chaser across the line of sight); a known y offset of
    ``size`` m turns the azimuth by size / r, and the filter, which predicts with the same
    commanded u, sees size / r_hat instead. Out of plane the CW motion is a free oscillation
    decoupled from the V-bar hold (y'' = -n^2 y): the hop costs two burns of n size m/s and
    leaves the along-track hold alone. ``update`` gives the setpoint's (y, v_y) and the burn's
    acceleration over the step (the filters know it: it is in the commanded u)."""

    def __init__(self, manoeuvre: ObservabilityManoeuvre, mean_motion: float, arrived: float):
        self.manoeuvre, self.n = manoeuvre, float(mean_motion)
        self.begins = float(arrived) + float(manoeuvre.delay)
        self.phase = 'waiting'
        self.started: float | None = None
        self.ended: float | None = None

    @property
    def duration(self) -> float:
        """Half an orbit, s: the free oscillation is back on V-bar."""
        return np.pi / self.n

    @property
    def done(self) -> bool:
        return self.phase == 'done'

    def update(self, t: float, dt: float) -> tuple[float, float, float]:
        """At time ``t`` for the step of ``dt`` s: the setpoint's y (m), v_y (m/s) before this
        step's burn, and the burn's acceleration along y (m/s^2; zero between the burns)."""
        size, n = self.manoeuvre.size, self.n
        if self.phase == 'waiting' and t >= self.begins:
            self.phase, self.started = 'flying', t
            return 0.0, 0.0, n * size / dt
        if self.phase != 'flying':
            return 0.0, 0.0, 0.0
        phase = n * (t - self.started - 0.5 * dt)  # a burn over a step acts at its middle
        y, v_y = size * np.sin(phase), n * size * np.cos(phase)
        if t - self.started >= self.duration:
            self.phase, self.ended = 'done', t
            return y, v_y, -v_y / dt
        return y, v_y, 0.0


@dataclass
class GuidanceEvent:
    time: float
    name: str
    detail: dict = field(default_factory=dict)


class ApproachGuidance:
    """The approach as a sequence: hold at ``holds[0]``, go, transfer to the next hold, ..., go at
    the last hold, then the final approach at ``final_speed`` m/s along V-bar through the port.
    After the go of the hold outside the keep-out sphere, an estimate whose 3-sigma leaves the
    ``corridor`` aborts: one step of ``cam_delta_v`` m/s along -x (back, away from the port),
    then free drift. A no-go ends the approach at its hold. ``mean_motion`` (rad/s) gives the
    feed-forward a setpoint moving along V-bar needs (CW: f_z = 2 n v_x, f_x = dv_x/dt).
    With a ``manoeuvre`` (:class:`ObservabilityManoeuvre`) its hold flies the out-of-plane hop
    first (:class:`OutOfPlaneHop`); that hold's go/no-go starts when the hop is done."""

    def __init__(self, holds, legs, corridor: Corridor, mean_motion: float, final_speed: float = 0.04,
                 cam_delta_v: float = 0.4, keep_out_radius: float = KEEP_OUT_RADIUS,
                 manoeuvre: ObservabilityManoeuvre | None = None):
        if len(legs) != len(holds) - 1:
            raise ValueError(f'legs: one per transfer between the {len(holds)} holds, got {len(legs)}')
        names = [h.name for h in holds]
        if manoeuvre is not None and manoeuvre.hold not in names:
            raise ValueError(f"the observability manoeuvre's hold must be one of {', '.join(names)}; "
                             f'got {manoeuvre.hold!r}')
        self.manoeuvre = manoeuvre
        self.holds, self.legs, self.corridor = tuple(holds), tuple(legs), corridor
        self.n, self.final_speed, self.cam_delta_v = float(mean_motion), float(final_speed), float(cam_delta_v)
        #: Index of the first hold whose go allows entering the keep-out sphere.
        self.keep_out_hold = next((i for i, h in enumerate(self.holds) if h.distance <= keep_out_radius),
                                  len(self.holds)) - 1
        self.phase, self.index = 'hold', 0
        self.decisions: list[GoNoGo] = []
        self.events: list[GuidanceEvent] = []
        self._s, self._v = self.holds[0].distance, 0.0  # setpoint distance behind the port, speed
        self._arrive(0.0)

    @property
    def active(self) -> bool:
        return self.phase in ACTIVE_PHASES

    def go_time(self, index: int) -> float | None:
        """When hold ``index`` was given its go (None: not, or not yet)."""
        done = [g for g in self.decisions if g.hold is self.holds[index] and g.decision == GO]
        return done[0].decided_at if done else None

    def corridor_armed(self) -> bool:
        return self.go_time(self.keep_out_hold) is not None

    def update(self, t: float, dt: float, x_hat, covariance) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Advance the sequence to time ``t`` on the estimate; returns (x_ref, u_ff, u_cam): the
        setpoint (6,), its feed-forward acceleration (3,) and the CAM's acceleration over this
        step (3,), zero but in the step of an abort."""
        cam, hop_ref, hop_u = np.zeros(3), np.zeros(6), np.zeros(3)
        if self.active and self.corridor_armed() and self.corridor.estimate_leaves(x_hat, covariance):
            self._finish(t, 'abort', {'three_sigma_lateral': self.corridor.three_sigma_lateral(x_hat, covariance),
                                      'corridor_radius': self.corridor.radius(x_hat[0])})
            cam[0] = -self.cam_delta_v / dt
        elif self.phase == 'hold' and self.hop is not None and not self.hop.done:
            hop_ref, hop_u = self._fly_hop(t, dt)
        elif self.phase == 'hold':
            self._hold(t, x_hat, covariance)
        v_old = self._v
        if self.phase == 'transfer':
            self._transfer(t, dt)
        elif self.phase == 'final':
            self._v = min(self.final_speed, self._v + 2e-3 * dt)
            self._s -= self._v * dt
        elif self.phase != 'hold':
            self._v = 0.0
        x_ref = np.array([-self._s, 0.0, 0.0, self._v, 0.0, 0.0]) + hop_ref
        u_ff = np.array([(self._v - v_old) / dt, 0.0, 2.0 * self.n * self._v]) + hop_u if self.active else np.zeros(3)
        return x_ref, u_ff, cam

    def _arrive(self, t: float) -> None:
        """At hold ``self.index`` at ``t``: its go/no-go starts, or first its hop."""
        hold = self.holds[self.index]
        self.gonogo = GoNoGo(hold, t)
        manoeuvre = self.manoeuvre
        self.hop = OutOfPlaneHop(manoeuvre, self.n, t) if manoeuvre and manoeuvre.hold == hold.name else None

    def _fly_hop(self, t: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """The hop's setpoint offset (6,) and burn (3,); its go/no-go starts when it is done."""
        before = self.hop.phase
        y, v_y, a_y = self.hop.update(t, dt)
        if self.hop.phase != before:
            hold = self.holds[self.index]
            self.events.append(GuidanceEvent(t, f'hop {hold.name}' if self.hop.phase == 'flying'
                                             else f'hop done {hold.name}'))
            if self.hop.done:
                self.gonogo = GoNoGo(hold, t)
        return np.array([0.0, y, 0.0, 0.0, v_y, 0.0]), np.array([0.0, a_y, 0.0])

    def _hold(self, t, x_hat, covariance) -> None:
        decision = self.gonogo.update(t, x_hat, covariance)
        if decision is None:
            return
        self.decisions.append(self.gonogo)
        self.events.append(GuidanceEvent(t, f'{decision} {self.gonogo.hold.name}',
                                         self.gonogo.criteria(x_hat, covariance)))
        if decision == NO_GO:
            self._finish(t, 'no_go', {'hold': self.gonogo.hold.name})
        elif self.index == len(self.holds) - 1:
            self.phase = 'final'
        else:
            self.phase = 'transfer'

    def _transfer(self, t, dt) -> None:
        leg, target = self.legs[self.index], self.holds[self.index + 1]
        wanted = np.clip((self._s - target.distance) / leg.time_constant, leg.min_speed, leg.max_speed)
        self._v = float(np.clip(wanted, self._v - leg.max_acceleration * dt, self._v + leg.max_acceleration * dt))
        self._s -= self._v * dt
        if self._s <= target.distance:
            self._s, self._v = target.distance, 0.0
            self.index += 1
            self.phase = 'hold'
            self._arrive(t)
            self.events.append(GuidanceEvent(t, f'arrive {target.name}'))

    def _finish(self, t: float, phase: str, detail: dict | None = None) -> None:
        self.phase = phase
        self.events.append(GuidanceEvent(t, phase, detail or {}))

    def contact(self, t: float) -> None:
        """The sequence ends in contact (told by whoever sees the truth cross the port)."""
        if self.active:
            self._finish(t, 'contact')


def approach_control(guidance: ApproachGuidance, gain, t: float, dt: float, x_hat, covariance) -> np.ndarray:
    """The acceleration (3,) m/s^2 over the step from ``t``: the LQR tracking the guidance's
    setpoint, u = u_ff - K (x_hat - x_ref), the CAM in the step of an abort, zero once the
    approach has ended. The offline loop and the controller node both call this."""
    if not guidance.active:
        return np.zeros(3)
    x_ref, u_ff, cam = guidance.update(t, dt, x_hat, covariance)
    return cam if guidance.phase == 'abort' else u_ff - np.asarray(gain) @ (np.asarray(x_hat) - x_ref)


def port_contact(x) -> dict[str, float]:
    """The contact conditions of the state ``x`` at the port: closing speed along V-bar (m/s)
    and lateral offset from the docking axis (m)."""
    return {'closing_speed': float(x[3]), 'lateral': Corridor.lateral(x[:3])}


def at_port(x) -> bool:
    """True once the chaser's state ``x`` has reached the docking port's plane (x >= 0 along
    V-bar): contact, as the truth sees it."""
    return float(x[0]) >= 0.0
