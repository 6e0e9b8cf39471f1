"""Shared fixtures and small models for the tests."""

import os

# Every test run talks on its own DDS domain, on this host only (set before rclpy loads), and
# each pytest-xdist worker (gw0, gw1) on one beside its controller's. Domains stay within 1-101,
# whose ports lie below Linux's ephemeral range.
if 'PYTEST_XDIST_WORKER' in os.environ:
    os.environ['ROS_DOMAIN_ID'] = str(int(os.environ['SNN_TEST_DOMAIN']) + 1
                                      + int(os.environ['PYTEST_XDIST_WORKER'][2:]) % 2)
else:
    os.environ.setdefault('SNN_TEST_DOMAIN', str(1 + (os.getpid() % 33) * 3))
    os.environ.setdefault('ROS_DOMAIN_ID', os.environ['SNN_TEST_DOMAIN'])
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


# ---------------------------------------------------------------- no silent skips under CI
#: Skip reasons that mean "an optional dependency is missing" (pytest.importorskip, the colcon
#: check of test_packaging). A developer without an extra sees a skip; under CI (CI=true), where
#: `make` installs every extra, such a skip means the install is broken and fails the run.
MISSING_EXTRA = ('could not import', 'is not installed')
_missing_extras: list[str] = []


def _under_ci() -> bool:
    return os.environ.get('CI', '').strip().lower() in ('1', 'true', 'yes')


def _record_skip(report) -> None:
    if not (report.skipped and _under_ci()):
        return
    reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
    if any(marker in reason for marker in MISSING_EXTRA):
        _missing_extras.append(f'{report.nodeid}: {reason}')


def pytest_collectreport(report):
    _record_skip(report)


def pytest_runtest_logreport(report):
    _record_skip(report)


def pytest_sessionfinish(session, exitstatus):
    if _missing_extras and exitstatus in (pytest.ExitCode.OK, pytest.ExitCode.NO_TESTS_COLLECTED):
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_terminal_summary(terminalreporter):
    if _missing_extras:
        terminalreporter.section('skipped for a missing extra under CI (CI=true): failing the run', red=True)
        for line in sorted(set(_missing_extras)):
            terminalreporter.line(line)
