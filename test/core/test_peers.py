"""Peers gone and back, without ROS: logged once, levels raised and cleared."""

import pytest

from snn_estimator.runners.peers import ERROR, OK, WARN, PeerWatch


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def test_a_silent_input_is_warned_about_once_raised_to_error_and_cleared_when_it_returns():
    wall, logs = Clock(), []
    watch = PeerWatch(['measurement', 'clock'], timeout=2.0, log=lambda level, m: logs.append((level, m)),
                      wall_clock=wall)
    assert not watch.check() and watch.level == OK  # never seen: nothing to miss
    watch.saw('measurement')
    wall.now = 1.9
    assert not watch.check()
    wall.now = 2.1
    assert watch.check() and watch.levels == {'measurement': WARN, 'clock': OK}
    wall.now = 5.0
    assert not watch.check()  # still WARN: said once
    wall.now = 10.5
    assert watch.check() and watch.level == ERROR
    assert [level for level, _ in logs] == ['warning', 'error']
    assert watch.problems() == ["no 'measurement' for 10.5 s"]
    watch.saw('measurement')
    assert watch.level == OK and logs[-1] == ('info', "'measurement' is back after 10.5 s")
    assert watch.values() == {'peer.measurement': 'OK', 'peer.clock': 'OK', 'peer_outages.measurement': 1,
                              'peer_outages.clock': 0}


def test_a_peer_timeout_must_be_positive():
    with pytest.raises(ValueError, match='peer_timeout'):
        PeerWatch(['truth'], timeout=0.0)
