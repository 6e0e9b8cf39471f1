"""The approach flown over ROS (``make demo SCENARIO=approach``), from its recorded bag: how it
ended, contact conditions, safety figures, the guidance's events and a decimated trajectory,
as results/approach_ros.json (docs/decisions.md, 69), and the lines snn_demo prints of them.
The geometry and limits are the core's (snn_estimator.plant.approach, snn_estimator.sim.approach).
"""

from __future__ import annotations

import numpy as np

from snn_estimator.plant.approach import APPROACH_ELLIPSOID, KEEP_OUT_RADIUS, Corridor, at_port, port_contact
from snn_estimator.sim.approach import CONTACT_LATERAL, CONTACT_SPEED, HOLDS, approach_guidance

#: Seconds between two samples of the trajectory kept in a ROS approach's results file.
TRAJECTORY_EVERY = 20.0


def ros_results(run, wall_time: float | None = None, every: float = TRAJECTORY_EVERY) -> dict:
    """The figures of one approach flown over ROS, from its recorded bag (snn_tools.bags.data.RunData):
    how it ended, the contact conditions where the truth reached the port (closing speed along
    V-bar, lateral offset), keep-out-sphere entries before the go of the hold outside it, the
    truth outside the corridor, the guidance's events, and the trajectory every ``every`` s
    (and its last sample): time, truth and estimated position, and the estimate's position
    3-sigma per axis (3 sqrt of P's diagonal: the bag keeps the diagonal)."""
    truth, t = run.truth, run.truth_t
    corridor = Corridor()
    keep_out_hold = HOLDS[approach_guidance(0.0).keep_out_hold].name
    events = [{'time': stamp, 'event': event, **values} for stamp, event, values in run.guidance]
    go_keep_out = next((e['time'] for e in events if e['event'] == f'go {keep_out_hold}'), None)
    inside = np.flatnonzero(np.linalg.norm(truth[:, :3], axis=1) < KEEP_OUT_RADIUS)
    entry = None if inside.size == 0 else float(t[inside[0]])
    outside = np.array([corridor.applies(p) and p[0] < 0.0 and not corridor.contains(p) for p in truth[:, :3]],
                       dtype=bool)
    excess = [corridor.lateral(p) - corridor.radius(p[0]) for p in truth[outside, :3]]
    depth = 1.0 - np.sqrt(np.sum((truth[:, :3] / np.array(APPROACH_ELLIPSOID)) ** 2, axis=1))
    contact = ({'time': float(t[-1]), **port_contact(truth[-1])} if truth.size and at_port(truth[-1]) else None)
    ended = [e for e in events if e.get('phase') in ('abort', 'no_go')]
    outcome = 'contact' if contact else ended[0]['phase'] if ended else 'unfinished'
    success = (contact is not None and CONTACT_SPEED[0] <= contact['closing_speed'] <= CONTACT_SPEED[1]
               and contact['lateral'] <= CONTACT_LATERAL and not outside.any()
               and (entry is None or (go_keep_out is not None and go_keep_out <= entry)))
    # the estimate at each truth stamp (both on the loop's grid)
    index = {round(v * 1e3): i for i, v in enumerate(run.estimate_t)}
    rows = [i for i in range(len(t)) if round(t[i] * 1e3) in index]
    keep = sorted({*(i for i in rows if t[i] % every == 0.0), rows[-1]}) if rows else []
    est = [index[round(t[i] * 1e3)] for i in keep]
    return {
        'outcome': outcome, 'success': bool(success), 'steps': int(len(t) - 1), 'sim_time': float(t[-1]),
        'wall_time': wall_time, 'contact': contact,
        'contact_limits': {'closing_speed': list(CONTACT_SPEED), 'lateral': CONTACT_LATERAL},
        'keep_out_entry': None if entry is None else {
            'time': entry, 'go': go_keep_out, 'before_go': go_keep_out is None or entry < go_keep_out},
        'corridor_exit_steps': int(outside.sum()),
        'corridor_exit': float(t[np.argmax(outside)]) if outside.any() else None,
        'max_corridor_excess': float(max(excess)) if excess else 0.0,
        'ellipsoid_entry': float(t[np.argmax(depth > 0.0)]) if (depth > 0.0).any() else None,
        'delta_v': float(np.sum(np.linalg.norm(run.control, axis=1)) * (t[1] - t[0])) if len(t) > 1 else 0.0,
        'events': events,
        'holds': [{'name': h.name, 'distance': h.distance} for h in HOLDS],
        'corridor': {'half_angle_deg': float(np.degrees(corridor.half_angle)), 'apex_radius': corridor.apex_radius,
                     'length': corridor.length},
        'keep_out_radius': KEEP_OUT_RADIUS, 'approach_ellipsoid': list(APPROACH_ELLIPSOID),
        'trajectory': {'every_s': every, 'time': [float(t[i]) for i in keep],
                       'truth': np.round(truth[keep, :3], 4).tolist(),
                       'estimate': np.round(run.estimate[est, :3], 4).tolist(),
                       'three_sigma': np.round(3.0 * np.sqrt(run.estimate_variance[est, :3]), 5).tolist()},
    }


def ros_lines(results: dict) -> list[str]:
    """What snn_demo prints of an approach: how it ended, contact conditions, safety counts."""
    contact, entry = results['contact'], results['keep_out_entry']
    lines = [f"  approach           {results['outcome']} after {results['sim_time']:.0f} s "
             f"({'within' if results['success'] else 'NOT within'} the contact and safety limits)"]
    if contact:
        speed, lateral = results['contact_limits']['closing_speed'], results['contact_limits']['lateral']
        lines.append(f"  contact            closing speed {contact['closing_speed']:.4f} m/s (limits {speed[0]:g}-"
                     f"{speed[1]:g}), lateral offset {contact['lateral']:.4f} m (limit {lateral:g})")
    go = 'no go' if entry is None or entry['go'] is None else f"the go at {entry['go']:.0f} s"
    lines.append(f"  keep-out sphere    {int(bool(entry and entry['before_go']))} entries before its go"
                 + ('' if entry is None else f" (entered at {entry['time']:.0f} s, after {go})"
                    if not entry['before_go'] else f" (entered at {entry['time']:.0f} s, before {go})"))
    lines.append(f"  corridor exits     {results['corridor_exit_steps']} steps outside the cone "
                 f"(max {results['max_corridor_excess']:.3f} m beyond it)")
    lines.append(f"  delta-v            {results['delta_v']:.2f} m/s")
    lines.append('  guidance           ' + ', '.join(f"{e['event']} {e['time']:.0f} s" for e in results['events']))
    return lines
