"""Shared fixtures and small models for the tests."""

import os

# Every test run talks on its own DDS domain, on this host only (set before rclpy loads).
os.environ.setdefault('ROS_DOMAIN_ID', str(101 + os.getpid() % 100))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from snn_estimator.models import StateSpaceModel  # noqa: E402


class DoubleIntegrator(StateSpaceModel):
    """p'' = u with p measured: the smallest model that exercises the common interface."""

    state_names = ('p', 'v')
    input_names = ('u',)
    measurement_names = ('p',)
    is_linear = True

    def f(self, x, u):
        x, u = np.asarray(x, dtype=float), np.asarray(u, dtype=float)
        return np.stack([x[..., 1], u[..., 0]], axis=-1)

    def jacobian(self, x, u):
        return np.array([[0.0, 1.0], [0.0, 0.0]])

    @property
    def input_matrix(self):
        return np.array([[0.0], [1.0]])

    @property
    def measurement_matrix(self):
        return np.array([[1.0, 0.0]])


@pytest.fixture
def double_integrator():
    return DoubleIntegrator()


def pytest_collection_modifyitems(config, items):
    """Mark the tests of modules that need rclpy with ``ros`` (``-m "not ros"``: the core alone)."""
    needs_ros = {}
    for item in items:
        path = item.path
        if path not in needs_ros:
            needs_ros[path] = "importorskip('rclpy')" in path.read_text()
        if needs_ros[path]:
            item.add_marker(pytest.mark.ros)
