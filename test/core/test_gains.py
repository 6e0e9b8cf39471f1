"""The gain laws (snn_estimator.gains): one module each, every consumer reads the same list,
and each law's compiled piece, run inside its filter's step kernel, equals its reference form
written from the paper."""

import numpy as np
import pytest

from snn_estimator import EstimatorConfig, gains, make_estimator
from snn_estimator.catalog import FILTER_KINDS
from snn_estimator.config import gain_noise_density
from snn_estimator.filters import estimators as E
from snn_estimator.spiking.costs import CostModel, filter_macs

LAWS = gains.laws()
INTERFACE = ('NAME', 'ORDER', 'FORMULA', 'EQUATION', 'USES_P', 'BASE', 'reference', 'steady_state', 'macs', 'gain')


def test_every_law_module_has_the_whole_interface_and_every_kind_names_a_law():
    for name, module in LAWS.items():
        assert all(hasattr(module, item) for item in INTERFACE), name
        assert module.BASE is None or module.BASE in LAWS
    assert {spec.gain for spec in FILTER_KINDS.values()} <= set(LAWS)
    assert {'kalman', 'msif', 'sif', 'msif_weighted', 'fixed'} <= set(LAWS)
    with pytest.raises(ValueError, match='unknown gain law .*kalman'):
        gains.law('luenberger')


def test_the_docs_tables_list_every_law_and_every_kind():
    for name, module in LAWS.items():
        assert f'``{name}``' in E.__doc__ and module.FORMULA in E.__doc__
    for kind, spec in FILTER_KINDS.items():
        assert f'``{kind}``' in E.__doc__ and spec.summary in E.__doc__


def _random_covariance(rng, n):
    root = rng.normal(size=(n, n))
    return root @ root.T * 1e-3 + 1e-3 * np.eye(n)


@pytest.mark.parametrize('kind', [k for k, spec in FILTER_KINDS.items() if not spec.spiking])
def test_the_compiled_gain_of_each_law_equals_its_reference_form(kind):
    """One step from a random full P: the kernel's K is the law's numpy reference (Eq. 5, 7,
    8-9, the remedies) of that P and innovation, for a measurement in and out of saturation."""
    rng = np.random.default_rng(11)
    config = EstimatorConfig(boundary_layer=(0.05, 0.5, 5.0), measurement_noise_units="per_sample")
    estimator = make_estimator(kind, config)
    law = gains.law(estimator.gain_law)
    s, c = estimator.settings, estimator.model.measurement_matrix
    p = _random_covariance(rng, 6)
    estimator.set_state(estimator.x_hat, p)
    x = estimator.x_hat.copy()
    z = c @ x + np.array([0.3, -0.02, 0.4])
    estimator.step(z, np.zeros(3), 0.1)
    phi = np.eye(6) + 0.1 * estimator.model.linearized_increment(None, 0.1)[0]  # the exact ZOH transition
    step = gains.SampledStep(phi, 0.1, gain_noise_density(s, 0.1) / 0.1)
    expected = law.reference(p, c, z - c @ x, step, s.r_hat, s.boundary_layer)
    np.testing.assert_allclose(estimator.gain, expected, rtol=1e-10, atol=1e-14)
    assert np.abs(expected).max() > 1e-3  # a gain that says something


@pytest.mark.parametrize('gain_law', [name for name in LAWS if name != 'fixed'])
def test_a_constant_gain_filter_steps_with_its_laws_steady_state(gain_law):
    kind = next(k for k, spec in FILTER_KINDS.items() if spec.gain == gain_law and not spec.spiking)
    estimator = make_estimator(kind, EstimatorConfig(gain_schedule='steady_state'))
    estimator.step(estimator.x_hat[:3] + 0.1, np.zeros(3), 0.1)
    expected = E.steady_state_gain(gain_law, estimator.model, estimator.settings, 0.1)
    np.testing.assert_array_equal(estimator.gain, expected)


def test_the_cost_of_a_filter_adds_its_laws_own_products():
    n, m, nu = 6, 3, 3
    base = filter_macs(n, m, nu, 'kalman', 'riccati')['gain']
    for name, module in LAWS.items():
        parts = filter_macs(n, m, nu, name, 'riccati')
        assert parts['gain'] == base + module.macs(n, m)
    assert sum(filter_macs(n, m, nu, 'kalman', 'riccati').values()) == 1026
    with pytest.raises(ValueError, match="gain_law 'luenberger' is unknown; choose one of kalman"):
        CostModel(200, 6, 3, 3, gain_law='luenberger')


def test_the_laws_declare_the_filter_kinds_direct_filters_first_then_their_spiking_twins():
    kinds = list(FILTER_KINDS)
    spiking = [FILTER_KINDS[kind].spiking for kind in kinds]
    assert spiking == sorted(spiking) and spiking.count(False) == spiking.count(True)  # direct, then twins
    today = ['ekf', 'emsif', 'esif', 'emsif_weighted']
    assert [kind for kind in kinds if kind in today] == today  # in the laws' ORDER (a new law may join)
    for kind, spec in FILTER_KINDS.items():
        law = gains.law(spec.gain)
        assert kind in law.KINDS and spec.covariance == law.COVARIANCE
        if spec.spiking:
            assert FILTER_KINDS[spec.twin].gain == spec.gain and not FILTER_KINDS[spec.twin].spiking



@pytest.mark.parametrize('kind', ['emsif_weighted', 'snn_emsif_weighted', 'emsif', 'snn_emsif'])
def test_the_variable_boundary_layer_gives_the_kalman_gain_inside_the_layer_and_saturates_outside(kind):
    """boundary_layer_mode variable (Decision 48): inside the layer the MSIF's correction dt K is
    the Kalman gain of the sampled step, K_d = P C^T (C P C^T + R_d)^-1, written out here (the
    weighted inverse: K itself, velocity rows included; the C^+ forms: C K); outside it the
    saturation is 1, as Eq. 8's; the spiking twins take the same gain."""
    dt, r_d = 0.1, 0.05 / 0.1  # R_hat = 5 x 1e-2 (a density), R_d = R_hat / dt
    c = np.hstack([np.eye(3), np.zeros((3, 3))])
    for a, inside in ((0.01, True), (1.0, False)):  # C P C^T = a I: a / (a + R_d) below or above dt
        p = np.block([[a * np.eye(3), 0.3 * a * np.eye(3)], [0.3 * a * np.eye(3), 0.2 * a * np.eye(3)]])
        p[0, 1] = p[1, 0] = 0.2 * a  # correlated position axes: C P C^T is not diagonal
        estimator = make_estimator(kind, EstimatorConfig(boundary_layer_mode='variable'))
        estimator.set_state(estimator.x_hat, p)
        estimator.step(c @ estimator.x_hat + 0.01, np.zeros(3), dt)
        cpc = c @ p @ c.T
        if inside:
            kalman = p @ c.T @ np.linalg.inv(cpc + r_d * np.eye(3))   # K_d
            # the decoupled z axis: the Kalman gain exactly (the whole column for the weighted inverse);
            # the correlated x, y axes: per component (diagonal of C P C^T), the saturations below
            if 'weighted' in kind:
                np.testing.assert_allclose(dt * estimator.gain[:, 2], kalman[:, 2], rtol=1e-12)
            np.testing.assert_allclose(dt * (c @ estimator.gain)[:, 2], (c @ kalman)[:, 2], rtol=1e-12, atol=1e-15)
            per_axis = np.diag(cpc) / (np.diag(cpc) + r_d) / dt       # the saturations
            weighted = p @ c.T @ np.linalg.inv(cpc) if 'weighted' in kind else np.linalg.pinv(c)
            np.testing.assert_allclose(estimator.gain, weighted @ np.diag(per_axis), rtol=1e-12)
        else:
            weighted = p @ c.T @ np.linalg.inv(cpc) if 'weighted' in kind else np.linalg.pinv(c)
            np.testing.assert_allclose(estimator.gain, weighted, rtol=1e-12)  # saturated: sat = 1
        fixed = make_estimator(kind, EstimatorConfig())
        fixed.set_state(fixed.x_hat, p)
        fixed.step(c @ fixed.x_hat + 0.01, np.zeros(3), dt)
        floor = 0.05 / 0.1  # the fixed layer's R_hat / delta: never below it
        assert np.all(np.diag(c @ fixed.gain) >= floor) and (not inside or np.all(np.diag(c @ estimator.gain) < floor))


def test_the_variable_layer_reference_equals_the_kalman_gain_where_c_p_ct_and_r_d_are_diagonal():
    """msif_weighted.reference with mode variable (the numpy form the kernel is held to): its
    dt K equals K_d = P C^T (C P C^T + R_d)^-1 for a P whose C P C^T is diagonal."""
    rng = np.random.default_rng(4)
    c = np.hstack([np.eye(3), np.zeros((3, 3))])
    cross = rng.normal(size=(3, 3)) * 1e-3
    p = np.block([[np.diag([0.01, 0.02, 0.005]), cross], [cross.T, 1e-2 * np.eye(3)]])
    r_d, dt = np.diag([0.5, 0.4, 0.6]), 0.1
    step = gains.SampledStep(np.eye(6), dt, r_d)
    k = gains.law('msif_weighted').reference(p, c, None, step, 0.05 * np.eye(3), np.full(3, 0.1), mode='variable')
    np.testing.assert_allclose(dt * k, p @ c.T @ np.linalg.inv(c @ p @ c.T + r_d), rtol=1e-12)


def test_the_variable_layer_needs_a_time_varying_gain():
    with pytest.raises(ValueError, match='boundary_layer_mode variable .* gain_schedule time_varying'):
        make_estimator('emsif_weighted', EstimatorConfig(boundary_layer_mode='variable', gain_schedule='steady_state'))
