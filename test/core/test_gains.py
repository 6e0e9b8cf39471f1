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

