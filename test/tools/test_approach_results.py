"""The ROS approach's results from a recorded run (snn_tools.bags.approach), on hand-made
trajectories whose contact, keep-out entry and corridor exit are known."""

from pathlib import Path

import numpy as np
import pytest

from snn_tools.bags.approach import ros_lines, ros_results
from snn_tools.bags.data import RunData


def run_along(x, z, events, speed=0.04):
    """A run whose truth (and estimate, 0.01 m off in z) is at x[k], z[k] at k s."""
    t = np.arange(len(x), dtype=float)
    truth = np.zeros((len(x), 6))
    truth[:, 0], truth[:, 2], truth[:, 3] = x, z, speed
    estimate = truth + np.array([0.0, 0.0, 0.01, 0.0, 0.0, 0.0])
    return RunData(path=Path('.'), truth_t=t, truth=truth, estimate_t=t, estimate=estimate,
                   estimate_variance=np.full((len(x), 6), 1e-4), control=np.full((len(x) - 1, 3), 1e-3),
                   guidance=[(stamp, event, {'phase': phase}) for stamp, event, phase in events])


def test_a_run_into_the_port_after_the_go_inside_the_cone_is_a_success_with_its_contact_conditions():
    x = np.linspace(-260.0, 0.02, 41)
    results = ros_results(run_along(x, np.zeros_like(x), [(5.0, 'go 250 m', 'transfer')]), every=10.0)
    assert results['outcome'] == 'contact' and results['success']
    assert results['contact'] == {'time': 40.0, 'closing_speed': pytest.approx(0.04), 'lateral': 0.0}
    entry = results['keep_out_entry']
    assert entry['go'] == 5.0 and not entry['before_go'] and entry['time'] == 10.0  # first x > -200: k = 10
    assert results['corridor_exit_steps'] == 0 and results['delta_v'] == pytest.approx(40 * np.sqrt(3) * 1e-3)
    assert results['trajectory']['time'] == [0.0, 10.0, 20.0, 30.0, 40.0]
    assert results['trajectory']['three_sigma'][0] == [0.03, 0.03, 0.03]
    assert any('contact' in line for line in ros_lines(results))


def test_a_keep_out_entry_before_the_go_and_a_corridor_exit_fail_the_run():
    x = np.linspace(-260.0, 0.02, 41)
    z = np.where(x > -100.0, 30.0, 0.0)  # 30 m off the axis inside 100 m: the cone is 17.7 m wide there
    results = ros_results(run_along(x, z, [(30.0, 'go 250 m', 'transfer')]))
    assert not results['success'] and results['keep_out_entry']['before_go']
    assert results['corridor_exit_steps'] > 0
    closest = x[x < 0.0][-1]  # the cone is narrowest next to the port
    assert results['max_corridor_excess'] == pytest.approx(30.0 - 0.1 - np.tan(np.radians(10.0)) * -closest)


def test_an_abort_is_the_outcome_of_a_run_that_never_reached_the_port():
    x = np.linspace(-260.0, -150.0, 21)
    results = ros_results(run_along(x, np.zeros_like(x), [(5.0, 'go 250 m', 'transfer'), (18.0, 'abort', 'abort')]))
    assert results['outcome'] == 'abort' and results['contact'] is None and not results['success']
